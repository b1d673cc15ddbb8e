//! Time per frame of a decoder at deployment: an exported model through ONNX Runtime at each
//! intra-op thread count and, where the trained run is given, the same network in burn, timed
//! in interleaved rounds (this machine's speed drifts; interleaving keeps the ratios honest)
//! and reported as medians.

use ndarray::Array4;
use serde::Serialize;
use std::path::Path;
use std::time::Instant;
use tcsense_kernels::timing::median_by;
use tcsense_models::net::{to_tensor, Network};
use tcsense_models::runs::{LoadedRun, ModelConfig, TrainedNet};
use tcsense_models::{Device, SensorTensors};

use crate::runtime::OnnxModel;
use crate::{InferError, Result};

/// One engine's median time per frame.
#[derive(Debug, Clone, Serialize)]
pub struct EngineTime {
    /// `ort (Rust), 2 threads`, `burn (flex), 2 threads`.
    pub engine: String,
    /// ONNX Runtime intra-op threads, or the rayon pool of burn's kernels.
    pub threads: usize,
    pub ms_per_frame: f64,
    pub frames_per_s: f64,
}

/// Times of one decoder at one frame size, batch 1.
#[derive(Debug, Clone, Serialize)]
pub struct Timing {
    pub decoder: String,
    pub height: usize,
    pub width: usize,
    pub taps: usize,
    pub bins: usize,
    /// Multiply-adds ×2 per frame, where the network is known.
    pub gflop_per_frame: Option<f64>,
    pub rounds: usize,
    pub engines: Vec<EngineTime>,
}

/// Time `model` (an exported ONNX file) at `ort_threads` each and, with `run`, the run's
/// network in burn, on one synthetic frame `[1, M, h, w]`: one warm-up, then `rounds`
/// interleaved rounds; medians.
pub fn time_decoder(run: Option<&LoadedRun>, model: &Path, (h, w): (usize, usize), ort_threads: &[usize], rounds: usize) -> Result<Timing> {
    if ort_threads.is_empty() || ort_threads.contains(&0) {
        return Err(InferError::InvalidParam {
            field: "ort threads",
            got: format!("{ort_threads:?}"),
            expected: "thread counts ≥ 1, e.g. 2,1".into(),
        });
    }
    let mut engines: Vec<(String, usize, OnnxModel)> = Vec::new();
    for &threads in ort_threads {
        engines.push((
            format!("ort (Rust), {threads} thread{}", if threads > 1 { "s" } else { "" }),
            threads,
            OnnxModel::open(model, threads)?,
        ));
    }
    let meta = engines[0].2.meta.clone();
    let (fh, fw) = meta.frame_multiple;
    if h % fh != 0 || w % fw != 0 {
        return Err(InferError::InvalidParam {
            field: "frame size",
            got: format!("{h}x{w}"),
            expected: format!("multiples of {fh}x{fw} for {}", model.display()),
        });
    }
    // a frame's working set: the input, the cube and a network's widest activations (32
    // channels or T, a few alive at once), in f32
    let per_pixel = (meta.taps + 8 * meta.bins.max(32)) as f64 * 4.0;
    tcsense_sensor::mem::check_fits(&format!("a {h}x{w} frame"), per_pixel * (h * w) as f64, "use a smaller frame size")?;
    let flops = run.map(|r| match &r.spec.model {
        ModelConfig::Unet(c) => c.flops(h, w),
        ModelConfig::AdmmNet(c) => c.flops(h, w),
        ModelConfig::Lifetime(c) => c.flops(h, w),
    });
    let mut seed = 1u64;
    let y = Array4::from_shape_fn((1, meta.taps, h, w), |_| {
        seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        ((seed >> 33) % 4096) as f32
    });
    let device = Device::flex();
    let st = run.map(|r| SensorTensors::new(r.sensor.matrix(), h, w, &device)).transpose()?;
    let burn_step = |r: &LoadedRun, st: &SensorTensors| -> f64 {
        let t0 = Instant::now();
        let yt = to_tensor(&y.view(), &device);
        let out = match &r.net {
            TrainedNet::AdmmNet(n) => n.predict(yt, st),
            TrainedNet::Unet(n) => n.predict(yt, st),
            TrainedNet::Lifetime(n) => n.predict(yt, st),
        };
        let _ = out.into_data();
        t0.elapsed().as_secs_f64() * 1e3
    };
    // warm up every engine, then interleave the rounds
    for (_, _, m) in engines.iter_mut() {
        m.run(y.view())?;
    }
    if let (Some(r), Some(st)) = (run, &st) {
        burn_step(r, st);
    }
    let rounds = rounds.max(1);
    let mut times: Vec<Vec<f64>> = vec![Vec::new(); engines.len() + 1];
    for _ in 0..rounds {
        for (i, (_, _, m)) in engines.iter_mut().enumerate() {
            let t0 = Instant::now();
            m.run(y.view())?;
            times[i].push(t0.elapsed().as_secs_f64() * 1e3);
        }
        if let (Some(r), Some(st)) = (run, &st) {
            times[engines.len()].push(burn_step(r, st));
        }
    }
    let mut names: Vec<(String, usize)> = engines.iter().map(|(n, t, _)| (n.clone(), *t)).collect();
    if run.is_some() {
        let t = rayon::current_num_threads();
        names.push((format!("burn (flex), {t} thread{}", if t > 1 { "s" } else { "" }), t));
    }
    let engines = names
        .into_iter()
        .zip(&times)
        .filter_map(|((engine, threads), t)| {
            median_by(t, |v| *v).map(|ms| EngineTime { engine, threads, ms_per_frame: ms, frames_per_s: 1e3 / ms })
        })
        .collect();
    Ok(Timing {
        decoder: meta.decoder.clone(),
        height: h,
        width: w,
        taps: meta.taps,
        bins: meta.bins,
        gflop_per_frame: flops.map(|f| f / 1e9),
        rounds,
        engines,
    })
}
