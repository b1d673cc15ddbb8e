//! `tcsense bench …`: throughput figures, printed (never asserted).

use anyhow::Result;
use clap::Subcommand;
use ndarray::Array3;
use std::process::ExitCode;
use std::time::Instant;
use tcsense_kernels::timing::{median_by, median_ms};
use tcsense_sensor::codes::{CodeShape, Constraints};
use tcsense_sensor::generate::random_codes;
use tcsense_models::runs::ModelConfig;
use tcsense_sensor::{MeasurementMatrix, Sampling, SensorParams};

#[derive(Subcommand)]
pub enum BenchCmd {
    /// Forward and adjoint throughput (voxels/s) at the prototype's frame size.
    Forward {
        /// Frame size HxW.
        #[arg(long, default_value = "188x212", value_parser = super::parse_hw)]
        size: (usize, usize),
        /// Repetitions per measurement (median reported).
        #[arg(long, default_value_t = 20)]
        reps: usize,
    },
    /// TVAL3 time per frame (LiDAR scene, tap constraint, paper settings, maxit iterations).
    Tval3 {
        /// Frame size HxW.
        #[arg(long, default_value = "188x212", value_parser = super::parse_hw)]
        size: (usize, usize),
        /// Bins T = 32·K (K = T/32).
        #[arg(long, default_value_t = 32)]
        bins: usize,
        /// Iterations.
        #[arg(long, default_value_t = 200)]
        maxit: usize,
        /// Frames.
        #[arg(long, default_value_t = 3)]
        frames: usize,
    },
    /// ADMM-Net: time per training step (batch 2) and inference time per frame.
    Train {
        /// Training frame size HxW.
        #[arg(long, default_value = "64x64", value_parser = super::parse_hw)]
        size: (usize, usize),
        /// Bins T (L = 32, K = T/32).
        #[arg(long, default_value_t = 32)]
        bins: usize,
        /// Stages S.
        #[arg(long, default_value_t = 9)]
        stages: usize,
        /// Channels CN.
        #[arg(long, default_value_t = 32)]
        channels: usize,
        /// Timed steps.
        #[arg(long, default_value_t = 5)]
        steps: usize,
        /// Inference frame size HxW.
        #[arg(long, default_value = "188x212", value_parser = super::parse_hw)]
        infer_size: (usize, usize),
        /// U-Net base width.
        #[arg(long, default_value_t = 8)]
        unet_width: usize,
        /// U-Net levels.
        #[arg(long, default_value_t = 3)]
        unet_levels: usize,
    },
    /// ADMM-Net's kernels (3×3 conv forward and gradients, data consistency, back-projection)
    /// against burn-flex's generic paths.
    Kernels {
        /// Frame size HxW.
        #[arg(long, default_value = "64x64", value_parser = super::parse_hw)]
        size: (usize, usize),
        /// Batch B.
        #[arg(long, default_value_t = 2)]
        batch: usize,
        /// Conv channels C (C → C).
        #[arg(long, default_value_t = 32)]
        channels: usize,
        /// Bins T of the data-consistency step (L = 32, K = T/32).
        #[arg(long, default_value_t = 32)]
        bins: usize,
        /// Repetitions per measurement (median reported).
        #[arg(long, default_value_t = 20)]
        reps: usize,
    },
    /// Dataset generation throughput (samples/s).
    Dataset(super::dataset::BenchDatasetArgs),
    /// Deployment inference: frames/s of an exported model through ONNX Runtime (1 and 2
    /// intra-op threads) and of the same network in burn, interleaved, with the FLOP rate.
    /// Without --run or --model, a fresh network of --decoder on the prototype's codes.
    Infer(super::deploy::BenchInferArgs),
}

pub fn run(cmd: BenchCmd) -> Result<ExitCode> {
    match cmd {
        BenchCmd::Forward { size: (h, w), reps } => {
            println!("forward/adjoint, frame {h}x{w}, block 2x2, 4 taps, {} threads", rayon::current_num_threads());
            println!("{:>5} {:>4} {:>12} {:>14} {:>12} {:>14}", "T", "K", "forward ms", "Gvoxel/s", "adjoint ms", "Gvoxel/s");
            for (length, k) in [(32usize, 1usize), (32, 4)] {
                let shape = CodeShape { bh: 2, bw: 2, taps: 4, length, drain: false };
                let codes = random_codes(shape, 607e6, Constraints { tap: true, hamming: Some(2), window: Some(2) }, 1)?;
                let spec = SensorParams { sampling: Sampling::Oversample(k), ..SensorParams::from_codes(&codes) }.validate()?;
                let plan = MeasurementMatrix::synthesize(&codes, &spec)?.plan(h, w)?;
                let t = spec.bins();
                let x = Array3::from_shape_fn((t, h, w), |(j, r, c)| ((j * 7 + r * 3 + c) % 11) as f32);
                let mut y = Array3::zeros((4, h, w));
                let mut xa = Array3::zeros((t, h, w));
                let fwd = median_ms(|| plan.forward_into(&x.view(), &mut y.view_mut()), reps)?;
                let adj = median_ms(|| plan.adjoint_into(&y.view(), &mut xa.view_mut()), reps)?;
                let vox = (t * h * w) as f64;
                println!("{t:>5} {k:>4} {fwd:>12.3} {:>14.3} {adj:>12.3} {:>14.3}", vox / fwd / 1e6, vox / adj / 1e6);
            }
        }
        BenchCmd::Dataset(a) => super::dataset::bench(a)?,
        BenchCmd::Infer(a) => super::deploy::bench_infer(a)?,
        BenchCmd::Train { size: (h, w), bins, stages, channels, steps, infer_size: (ih, iw), unet_width, unet_levels } => {
            if bins == 0 || bins % 32 != 0 {
                anyhow::bail!("--bins {bins}: expected a multiple of 32");
            }
            let k = bins / 32;
            let shape = CodeShape { bh: 2, bw: 2, taps: 4, length: 32, drain: false };
            let codes = random_codes(shape, 607e6, Constraints { tap: true, hamming: Some(2), window: Some(2) }, 1)?;
            let spec = SensorParams { sampling: Sampling::Oversample(k), ..SensorParams::from_codes(&codes) }.validate()?;
            let a = MeasurementMatrix::synthesize(&codes, &spec)?;
            let cfg = ModelConfig::AdmmNet(tcsense_models::AdmmNetConfig::new(4, bins).with_stages(stages).with_channels(channels));
            let r = tcsense_train::bench::bench_step(&a, &cfg, h, w, steps)?;
            println!("ADMM-Net S = {stages}, CN = {channels}, T = {bins}, {} threads", rayon::current_num_threads());
            println!("training step (batch 2, {h}x{w}): {:.1} ms (forward {:.1} ms, backward {:.1} ms, Adam {:.1} ms)", r.step_ms, r.forward_ms, r.backward_ms, r.optim_ms);
            let f = tcsense_train::bench::bench_forward(&a, &cfg, ih, iw, 3)?;
            println!("inference forward ({ih}x{iw}, batch 1): {f:.1} ms per frame; {} parameters", tcsense_train::bench::parameters(&cfg));
            if unet_width == 0 || !(1..=6).contains(&unet_levels) {
                anyhow::bail!("--unet-width {unet_width}, --unet-levels {unet_levels}: expected a width ≥ 1 and 1–6 levels");
            }
            let range_m = 299_792_458.0 * spec.cycle_s() / 2.0;
            let unet = tcsense_models::UnetConfig::new(4, bins, range_m).with_base_width(unet_width).with_levels(unet_levels);
            let flops = unet.flops(ih, iw);
            let cfg = ModelConfig::Unet(unet);
            let r = tcsense_train::bench::bench_step(&a, &cfg, h, w, steps)?;
            println!("Aᵀ + U-Net K = 2, base width {unet_width}, {unet_levels} levels, T = {bins}");
            println!("training step (batch 2, {h}x{w}): {:.1} ms (forward {:.1} ms, backward {:.1} ms, Adam {:.1} ms)", r.step_ms, r.forward_ms, r.backward_ms, r.optim_ms);
            let f = tcsense_train::bench::bench_forward(&a, &cfg, ih, iw, 3)?;
            println!("inference forward ({ih}x{iw}, batch 1): {f:.1} ms per frame, {:.2} GFLOP per frame ({:.1} GFLOP/s); {} parameters", flops / 1e9, flops / f / 1e6, tcsense_train::bench::parameters(&cfg));
        }
        BenchCmd::Kernels { size: (h, w), batch, channels, bins, reps } => {
            if bins == 0 || bins % 32 != 0 {
                anyhow::bail!("--bins {bins}: expected a multiple of 32 (L = 32, K = T/32)");
            }
            if h == 0 || w == 0 || h % 2 != 0 || w % 2 != 0 || batch == 0 || channels == 0 {
                anyhow::bail!("--size {h}x{w}, --batch {batch}, --channels {channels}: expected non-zero sizes and an even frame (2x2 blocks)");
            }
            let shape = CodeShape { bh: 2, bw: 2, taps: 4, length: 32, drain: false };
            let codes = random_codes(shape, 607e6, Constraints { tap: true, hamming: Some(2), window: Some(2) }, 1)?;
            let spec = SensorParams { sampling: Sampling::Oversample(bins / 32), ..SensorParams::from_codes(&codes) }.validate()?;
            let a = MeasurementMatrix::synthesize(&codes, &spec)?;
            println!("kernels: batch {batch}, {h}x{w}, conv {channels}->{channels}, DC with T = {bins}, M = 4, 2x2 blocks, {} threads", rayon::current_num_threads());
            println!("{:<22} {:>10} {:>10} {:>10} {:>10} {:>8}", "op", "ours ms", "GFLOP/s", "burn ms", "GFLOP/s", "speedup");
            for r in tcsense_models::bench::bench_kernels(&a, batch, channels, h, w, reps)? {
                let rate = |ms: f64| if r.flop > 0.0 { format!("{:.1}", r.flop / ms / 1e6) } else { "-".into() };
                println!("{:<22} {:>10.3} {:>10} {:>10.3} {:>10} {:>7.1}x", r.name, r.ours_ms, rate(r.ours_ms), r.burn_ms, rate(r.burn_ms), r.burn_ms / r.ours_ms);
            }
            let (ops, whole) = tcsense_models::bench::bench_unet_ops(&a, 188, 212, reps)?;
            println!("\nU-Net resampling at 188x212 (default widths):");
            println!("{:<30} {:>10} {:>10} {:>8}", "op", "ours ms", "burn ms", "speedup");
            for r in ops {
                println!("{:<30} {:>10.3} {:>10.3} {:>7.1}x", r.name, r.ours_ms, r.burn_ms, r.burn_ms / r.ours_ms);
            }
            println!("whole U-Net forward (ours): {whole:.1} ms per frame");
        }
        BenchCmd::Tval3 { size: (h, w), bins, maxit, frames } => {
            use tcsense_datasets::{lidar::LidarParams, TimeGrid};
            if bins == 0 || bins % 32 != 0 {
                anyhow::bail!("--bins {bins}: expected a multiple of 32 (L = 32, K = T/32)");
            }
            let k = bins / 32;
            let shape = CodeShape { bh: 2, bw: 2, taps: 4, length: 32, drain: false };
            let codes = random_codes(shape, 607e6, Constraints { tap: true, ..Default::default() }, 1)?;
            let spec = SensorParams { sampling: Sampling::Oversample(k), ..SensorParams::from_codes(&codes) }.validate()?;
            let a = MeasurementMatrix::synthesize(&codes, &spec)?;
            let plan = a.plan(h, w)?;
            let grid = TimeGrid { sampling: Sampling::Oversample(k), ..TimeGrid::default() };
            let gen = LidarParams { height: h, width: w, ..Default::default() };
            let opts = tcsense_models::Tval3Options { maxit, tol: 1e-12, maxcnt: usize::MAX, ..Default::default() };
            println!("TVAL3 {h}x{w}x{bins}, 4 taps 2x2, maxit {maxit}, {} threads", rayon::current_num_threads());
            let never = std::sync::atomic::AtomicBool::new(false);
            // this machine's memory bandwidth: a parallel copy of 256 MiB, median of 5
            let (src, mut dst) = (vec![1f32; 1 << 26], vec![0f32; 1 << 26]);
            let copy_gbs = {
                use rayon::prelude::*;
                let ms = median_ms(|| -> Result<()> {
                    dst.par_chunks_mut(1 << 16).zip(src.par_chunks(1 << 16)).for_each(|(d, s)| d.copy_from_slice(s));
                    Ok(())
                }, 5)?;
                2.0 * (src.len() * 4) as f64 / ms / 1e6
            };
            drop((src, dst));
            let cube_mb = (bins * h * w * 4) as f64 / 1e6;
            println!("memory bandwidth (parallel copy, read + write): {copy_gbs:.1} GB/s; one pass over the cube = {cube_mb:.1} MB");
            type Solve = fn(&MeasurementMatrix, &tcsense_sensor::FramePlan, &ndarray::ArrayView3<'_, f32>, &tcsense_models::Tval3Options, &(dyn Fn(usize, usize) + Sync), &std::sync::atomic::AtomicBool) -> tcsense_models::Result<(ndarray::Array3<f32>, tcsense_models::Tval3Report)>;
            let solvers: [(&str, Solve); 2] = [("reference", tcsense_models::tval3::tval3_reference), ("optimised", tcsense_models::tval3)];
            let mut times = vec![Vec::new(); solvers.len()];
            for i in 0..frames.max(1) {
                let x = gen.sample(&grid, 1, i as u64).x;
                let y = plan.forward(&x.view())?;
                // interleaved: both solvers on each frame
                for (k, (name, solve)) in solvers.iter().enumerate() {
                    let t0 = Instant::now();
                    let (xh, rep) = solve(&a, &plan, &y.view(), &opts, &|_, _| {}, &never)?;
                    let dt = t0.elapsed().as_secs_f64();
                    let mse = tcsense_infer::metrics::mse(xh.as_slice().unwrap_or(&[]), x.as_slice().unwrap_or(&[]));
                    let passes = dt * copy_gbs * 1e3 / cube_mb / rep.iterations.max(1) as f64;
                    println!(
                        "frame {i} {name:<9}: {:.3} s, {} iterations ({:.2} ms/iteration ≈ {passes:.0} cube passes at copy bandwidth, {} backtracks, {} fallbacks), MSE {mse:.3e}",
                        dt,
                        rep.iterations,
                        dt * 1e3 / rep.iterations.max(1) as f64,
                        rep.backtracks,
                        rep.fallbacks
                    );
                    times[k].push(dt);
                }
            }
            let med: Vec<f64> = times.iter().map(|t| median_by(t, |v| *v).unwrap_or(f64::NAN)).collect();
            println!("median per frame: reference {:.3} s, optimised {:.3} s ({:.2}x)", med[0], med[1], med[0] / med[1]);
        }
    }
    Ok(ExitCode::SUCCESS)
}
