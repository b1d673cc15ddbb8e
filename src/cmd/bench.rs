//! `tcsense bench …`: throughput figures, printed (never asserted).

use anyhow::Result;
use clap::{Args, Subcommand};
use ndarray::Array3;
use std::process::ExitCode;
use std::time::Instant;
use tcsense_kernels::timing::{median_by, median_ms};
use tcsense_models::runs::ModelConfig;
use tcsense_sensor::codes::{CodeShape, Constraints};
use tcsense_sensor::generate::random_codes;
use tcsense_sensor::{Irf, MeasurementMatrix, Sampling, Sensor};

#[derive(Subcommand)]
pub enum BenchCmd {
    /// Forward and adjoint throughput (voxels/s) at the prototype's frame size.
    Forward(ForwardArgs),
    /// TVAL3 time per frame (LiDAR scene, tap constraint, paper settings, maxit iterations).
    Tval3(Tval3Args),
    /// Training step of every network (ADMM-Net with the bins and the delay prior, the Aᵀ +
    /// U-Net, ADMM-Net learning its codes) at each --bins: time, GFLOP per step, GFLOP/s and the share of the step outside
    /// the convolutions' multiply-add loops; with --infer-size, inference time per frame too.
    Train(TrainArgs),
    /// ADMM-Net's kernels (3×3 conv forward and gradients, data consistency, back-projection)
    /// against burn-flex's generic paths.
    Kernels(KernelsArgs),
    /// Dataset generation throughput (samples/s).
    Dataset(super::dataset::BenchDatasetArgs),
    /// Deployment inference: frames/s of an exported model through ONNX Runtime (1 and 2
    /// intra-op threads) and of the same network in burn, interleaved, with the FLOP rate.
    /// Without --run or --model, a fresh network of --decoder on the prototype's codes.
    Infer(super::deploy::BenchInferArgs),
    /// The U-Net's range fit in the tap domain (`tcsense_fits::range`): time per frame on the
    /// paper's LiDAR scenes (about half with a sheet in front), from the true ranges moved by
    /// about a bin, with one return per pixel and with two where the scene has them, and the
    /// error left.
    RangeFit(RangeFitArgs),
    /// Speed against accuracy of decoders: each one's frames/s on a stream of noisy frames at
    /// the sensor's frame size (the dataset's items mirrored to it; `onnx:MODEL` is the
    /// deployed path), beside its error at every level of a light ladder on the dataset; a
    /// table, JSON, CSV, a speed–accuracy figure and the photon-efficiency curve.
    Decoders(super::bench_decoders::BenchDecodersArgs),
}

/// The settings of `tcsense bench forward`.
#[derive(Args)]
pub struct ForwardArgs {
    /// Frame size HxW.
    #[arg(long, default_value = "188x212", value_parser = super::parse_hw)]
    pub size: (usize, usize),
    /// Repetitions per measurement (median reported).
    #[arg(long, default_value_t = 20)]
    pub reps: usize,
}

/// The settings of `tcsense bench tval3`.
#[derive(Args)]
pub struct Tval3Args {
    /// Frame size HxW.
    #[arg(long, default_value = "188x212", value_parser = super::parse_hw)]
    pub size: (usize, usize),
    /// Bins T = 32·K (K = T/32).
    #[arg(long, default_value_t = 32)]
    pub bins: usize,
    /// Iterations.
    #[arg(long, default_value_t = 200)]
    pub maxit: usize,
    /// Frames (1 to 1000).
    #[arg(long, default_value_t = 3, value_parser = super::count_in(1, 1000))]
    pub frames: usize,
}

/// The settings of `tcsense bench train`.
#[derive(Args)]
pub struct TrainArgs {
    /// Training frame size HxW.
    #[arg(long, default_value = "64x64", value_parser = super::parse_hw)]
    pub size: (usize, usize),
    /// Bins T, one or more (L = 32, K = T/32).
    #[arg(long, default_value = "32,256", value_delimiter = ',')]
    pub bins: Vec<usize>,
    /// Stages S.
    #[arg(long, default_value_t = 9)]
    pub stages: usize,
    /// Channels CN of the bins prior.
    #[arg(long, default_value_t = 32)]
    pub channels: usize,
    /// Channels per bin of the delay prior.
    #[arg(long, default_value_t = 4)]
    pub delay_channels: usize,
    /// Timed steps (median reported, after one warm-up step).
    #[arg(long, default_value_t = 5)]
    pub steps: usize,
    /// Also time inference of one frame of this size HxW (batch 1).
    #[arg(long, value_parser = super::parse_hw)]
    pub infer_size: Option<(usize, usize)>,
    /// U-Net base width.
    #[arg(long, default_value_t = 8)]
    pub unet_width: usize,
    /// U-Net levels.
    #[arg(long, default_value_t = 3)]
    pub unet_levels: usize,
    /// Only the networks whose label contains this (e.g. "delay", "U-Net").
    #[arg(long)]
    pub only: Option<String>,
    /// How the delay prior's layers run on the CPU: the delay-tap kernels (in place), or
    /// composed (roll + concatenate + 3×3 conv, as before the kernels and on the GPU).
    #[arg(long, value_enum, default_value = "kernel")]
    pub delay_path: DelayPath,
}

/// The settings of `tcsense bench kernels`.
#[derive(Args)]
pub struct KernelsArgs {
    /// Frame size HxW.
    #[arg(long, default_value = "64x64", value_parser = super::parse_hw)]
    pub size: (usize, usize),
    /// Batch B.
    #[arg(long, default_value_t = 2)]
    pub batch: usize,
    /// Conv channels C (C → C).
    #[arg(long, default_value_t = 32)]
    pub channels: usize,
    /// Bins T of the data-consistency step (L = 32, K = T/32).
    #[arg(long, default_value_t = 32)]
    pub bins: usize,
    /// Repetitions per measurement (median reported).
    #[arg(long, default_value_t = 20)]
    pub reps: usize,
}

/// The settings of `tcsense bench range-fit`.
#[derive(Args)]
pub struct RangeFitArgs {
    /// Frame size HxW.
    #[arg(long, default_value = "188x212", value_parser = super::parse_hw)]
    pub size: (usize, usize),
    /// Frames (each timed once per case, interleaved; 1 to 1000).
    #[arg(long, default_value_t = 3, value_parser = super::count_in(1, 1000))]
    pub frames: usize,
}

/// How the delay prior's layers run (`bench train --delay-path`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum DelayPath {
    /// The delay-tap kernels.
    Kernel,
    /// Roll + concatenate + 3×3 conv.
    Composed,
}

pub fn run(cmd: BenchCmd) -> Result<ExitCode> {
    match cmd {
        BenchCmd::Forward(a) => forward(a)?,
        BenchCmd::Dataset(a) => super::dataset::bench(a)?,
        BenchCmd::Infer(a) => super::deploy::bench_infer(a)?,
        BenchCmd::Train(a) => train(a)?,
        BenchCmd::Kernels(a) => kernels(a)?,
        BenchCmd::RangeFit(a) => range_fit(a)?,
        BenchCmd::Tval3(a) => tval3(a)?,
        BenchCmd::Decoders(a) => super::bench_decoders::run(a)?,
    }
    Ok(ExitCode::SUCCESS)
}

/// `tcsense bench forward`.
fn forward(a: ForwardArgs) -> Result<()> {
    let ForwardArgs { size: (h, w), reps } = a;
    println!("forward/adjoint, frame {h}x{w}, block 2x2, 4 taps, {} threads", rayon::current_num_threads());
    println!("{:>5} {:>4} {:>12} {:>14} {:>12} {:>14}", "T", "K", "forward ms", "Gvoxel/s", "adjoint ms", "Gvoxel/s");
    for (length, k) in [(32usize, 1usize), (32, 4)] {
        let shape = CodeShape { bh: 2, bw: 2, taps: 4, length, drain: false };
        let codes = random_codes(shape, 607e6, Constraints { tap: true, hamming: Some(2), window: Some(2) }, 1)?;
        let sensor = Sensor::ideal(codes.clone(), Sampling::Oversample(k), Irf::Ideal)?;
        let plan = sensor.plan(h, w)?;
        let t = sensor.bins();
        let x = Array3::from_shape_fn((t, h, w), |(j, r, c)| ((j * 7 + r * 3 + c) % 11) as f32);
        let mut y = Array3::zeros((4, h, w));
        let mut xa = Array3::zeros((t, h, w));
        let fwd = median_ms(|| plan.forward_into(&x.view(), &mut y.view_mut()), reps)?;
        let adj = median_ms(|| plan.adjoint_into(&y.view(), &mut xa.view_mut()), reps)?;
        let vox = (t * h * w) as f64;
        println!("{t:>5} {k:>4} {fwd:>12.3} {:>14.3} {adj:>12.3} {:>14.3}", vox / fwd / 1e6, vox / adj / 1e6);
    }
    Ok(())
}

/// `tcsense bench tval3`.
fn tval3(a: Tval3Args) -> Result<()> {
    let Tval3Args { size: (h, w), bins, maxit, frames } = a;
    use tcsense_datasets::{lidar::LidarParams, TimeGrid};
    if bins == 0 || bins % 32 != 0 {
        anyhow::bail!("--bins {bins}: expected a multiple of 32 (L = 32, K = T/32)");
    }
    let k = bins / 32;
    let shape = CodeShape { bh: 2, bw: 2, taps: 4, length: 32, drain: false };
    let codes = random_codes(shape, 607e6, Constraints { tap: true, ..Default::default() }, 1)?;
    let sensor = Sensor::ideal(codes.clone(), Sampling::Oversample(k), Irf::Ideal)?;
    let a = sensor.matrix();
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
        let ms = median_ms(
            || -> Result<()> {
                dst.par_chunks_mut(1 << 16).zip(src.par_chunks(1 << 16)).for_each(|(d, s)| d.copy_from_slice(s));
                Ok(())
            },
            5,
        )?;
        2.0 * (src.len() * 4) as f64 / ms / 1e6
    };
    drop((src, dst));
    let cube_mb = (bins * h * w * 4) as f64 / 1e6;
    println!("memory bandwidth (parallel copy, read + write): {copy_gbs:.1} GB/s; one pass over the cube = {cube_mb:.1} MB");
    type Solve = fn(
        &MeasurementMatrix,
        &tcsense_sensor::FramePlan,
        &ndarray::ArrayView3<'_, f32>,
        &tcsense_models::Tval3Options,
        &(dyn Fn(usize, usize) + Sync),
        &std::sync::atomic::AtomicBool,
    ) -> tcsense_models::Result<(ndarray::Array3<f32>, tcsense_models::Tval3Report)>;
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
    Ok(())
}

/// `tcsense bench train`.
fn train(a: TrainArgs) -> Result<()> {
    let TrainArgs { size: (h, w), bins, stages, channels, delay_channels, steps, infer_size, unet_width, unet_levels, only, delay_path } =
        a;
    tcsense_kernels::delay_op::use_composed(delay_path == DelayPath::Composed);
    if bins.is_empty() || bins.iter().any(|&t| t == 0 || t % 32 != 0) {
        let list: Vec<String> = bins.iter().map(|t| t.to_string()).collect();
        anyhow::bail!("--bins {}: expected each a multiple of 32", list.join(","));
    }
    if unet_width == 0 || !(1..=6).contains(&unet_levels) {
        anyhow::bail!("--unet-width {unet_width}, --unet-levels {unet_levels}: expected a width ≥ 1 and 1–6 levels");
    }
    if h == 0 || w == 0 || h % 2 != 0 || w % 2 != 0 || stages == 0 || channels == 0 || delay_channels == 0 {
        anyhow::bail!("--size {h}x{w}, --stages {stages}, --channels {channels}, --delay-channels {delay_channels}: expected non-zero sizes and an even frame (2x2 blocks)");
    }
    use tcsense_models::admm::Prior;
    println!(
        "training step: batch {}, {h}x{w}, 4 taps 2x2, Adam, {} threads, delay path {delay_path:?}; GFLOP = 3 x forward; non-conv = share of the step's core time outside the convolutions' multiply-add loops (GEMM or direct)",
        tcsense_train::bench::BENCH_BATCH,
        rayon::current_num_threads()
    );
    println!(
        "{:<36} {:>5} {:>10} {:>10} {:>10} {:>10} {:>8} {:>8}",
        "network", "T", "step ms", "fwd ms", "bwd ms", "GFLOP", "GFLOP/s", "non-conv"
    );
    let codes = super::prototype_codes()?;
    let mut inference = Vec::new();
    for &t in &bins {
        let sensor = Sensor::ideal(codes.clone(), Sampling::Oversample(t / 32), Irf::Ideal)?;
        let a = sensor.matrix();
        let admm =
            |prior: Prior, cn: usize| tcsense_models::AdmmNetConfig::new(4, t).with_stages(stages).with_channels(cn).with_prior(prior);
        let range_m = tcsense_sensor::C * sensor.spec().cycle_s() / 2.0;
        let bins_prior = ModelConfig::AdmmNet(admm(Prior::Bins, channels));
        // (label, network, whether it learns its codes)
        let nets = [
            (format!("ADMM-Net bins prior S={stages} CN={channels}"), bins_prior.clone(), false),
            (
                format!("ADMM-Net delay prior S={stages} C={delay_channels}/bin"),
                ModelConfig::AdmmNet(admm(Prior::Delay, delay_channels)),
                false,
            ),
            (
                format!("Aᵀ + U-Net K=2 width {unet_width}, {unet_levels} levels"),
                ModelConfig::Unet(
                    tcsense_models::UnetConfig::new(4, t, range_m)
                        .with_base_width(unet_width)
                        .with_levels(unet_levels)
                        .with_head(tcsense_models::UnetHead::ScoreVolume),
                ),
                false,
            ),
            ("ADMM-Net bins prior, learned codes".to_string(), bins_prior, true),
        ];
        for (label, cfg, learn) in nets.iter().filter(|(l, _, _)| only.as_ref().is_none_or(|o| l.contains(o.as_str()))) {
            let r = if *learn {
                tcsense_train::bench::bench_step_learned(&codes, Sampling::Oversample(t / 32), cfg, h, w, steps)?
            } else {
                tcsense_train::bench::bench_step(&a, cfg, h, w, steps)?
            };
            println!(
                "{label:<36} {t:>5} {:>10.1} {:>10.1} {:>10.1} {:>10.2} {:>8.1} {:>7.0}%",
                r.step_ms,
                r.forward_ms,
                r.backward_ms,
                r.flop / 1e9,
                r.gflops(),
                100.0 * r.outside_conv()
            );
            if let (Some((ih, iw)), false) = (infer_size, *learn) {
                let f = tcsense_train::bench::bench_forward(&sensor, cfg, ih, iw, 2)?;
                let flop = cfg.flops(ih, iw);
                inference.push(format!(
                    "{label:<36} {t:>5} {f:>10.1} {:>10.2} {:>8.1} {:>10}",
                    flop / 1e9,
                    flop / f / 1e6,
                    tcsense_train::bench::parameters(cfg)
                ));
            }
        }
    }
    if let Some((ih, iw)) = infer_size {
        println!("\ninference in burn ({ih}x{iw}, batch 1, median of 2 after a warm-up):");
        println!("{:<36} {:>5} {:>10} {:>10} {:>8} {:>10}", "network", "T", "ms/frame", "GFLOP", "GFLOP/s", "params");
        for l in inference {
            println!("{l}");
        }
    }
    Ok(())
}

/// `tcsense bench kernels`.
fn kernels(a: KernelsArgs) -> Result<()> {
    let KernelsArgs { size: (h, w), batch, channels, bins, reps } = a;
    if bins == 0 || bins % 32 != 0 {
        anyhow::bail!("--bins {bins}: expected a multiple of 32 (L = 32, K = T/32)");
    }
    if h == 0 || w == 0 || h % 2 != 0 || w % 2 != 0 || batch == 0 || channels == 0 {
        anyhow::bail!("--size {h}x{w}, --batch {batch}, --channels {channels}: expected non-zero sizes and an even frame (2x2 blocks)");
    }
    let codes = super::prototype_codes()?;
    let sensor = Sensor::ideal(codes.clone(), Sampling::Oversample(bins / 32), Irf::Ideal)?;
    let a = sensor.matrix();
    println!(
        "kernels: batch {batch}, {h}x{w}, conv {channels}->{channels}, DC with T = {bins}, M = 4, 2x2 blocks, {} threads",
        rayon::current_num_threads()
    );
    println!("{:<22} {:>10} {:>10} {:>10} {:>10} {:>8}", "op", "ours ms", "GFLOP/s", "burn ms", "GFLOP/s", "speedup");
    for r in tcsense_models::bench::bench_kernels(&a, batch, channels, h, w, reps)? {
        let rate = |ms: f64| if r.flop > 0.0 { format!("{:.1}", r.flop / ms / 1e6) } else { "-".into() };
        println!(
            "{:<22} {:>10.3} {:>10} {:>10.3} {:>10} {:>7.1}x",
            r.name,
            r.ours_ms,
            rate(r.ours_ms),
            r.burn_ms,
            rate(r.burn_ms),
            r.burn_ms / r.ours_ms
        );
    }
    let (ops, whole) = tcsense_models::bench::bench_unet_ops(&a, 188, 212, reps)?;
    println!("\nU-Net resampling at 188x212 (default widths):");
    println!("{:<30} {:>10} {:>10} {:>8}", "op", "ours ms", "burn ms", "speedup");
    for r in ops {
        println!("{:<30} {:>10.3} {:>10.3} {:>7.1}x", r.name, r.ours_ms, r.burn_ms, r.burn_ms / r.ours_ms);
    }
    println!("whole U-Net forward (ours): {whole:.1} ms per frame");
    Ok(())
}

/// `tcsense bench range-fit`.
fn range_fit(a: RangeFitArgs) -> Result<()> {
    let RangeFitArgs { size: (h, w), frames } = a;
    use tcsense_datasets::{lidar::LidarParams, TimeGrid};
    use tcsense_fits::range::{refine_ranges, RangeFitOptions};
    if h == 0 || w == 0 || h % 2 != 0 || w % 2 != 0 {
        anyhow::bail!("--size {h}x{w}: expected an even frame (2x2 blocks)");
    }
    let codes = super::prototype_codes()?;
    use tcsense_sensor::params::{DEFAULT_LASER_FWHM_S, DEFAULT_TAP_TAU_S};
    let sensor = Sensor::ideal(
        codes.clone(),
        Sampling::Oversample(1),
        Irf::Physical { laser_fwhm_s: DEFAULT_LASER_FWHM_S, tap_tau_s: DEFAULT_TAP_TAU_S },
    )?;
    let a = sensor.matrix();
    let plan = a.plan(h, w)?;
    let gen = LidarParams { height: h, width: w, ..LidarParams::paper() };
    let dz = tcsense_sensor::C * sensor.bin_width_s() / 2.0;
    println!("range fit {h}x{w}, prototype codes (T = 32), physical IRF, default settings, {} threads; estimates: the true ranges + 0.7 bin (first) and − 0.6 bin (second)", rayon::current_num_threads());
    println!("{:<28} {:>10} {:>16} {:>16}", "case", "ms/frame", "first MAE (bin)", "second MAE (bin)");
    let cases = ["one return per pixel", "two where the scene has"];
    let mut rows: Vec<(Vec<f64>, [f64; 4])> = vec![(Vec::new(), [0.0; 4]); cases.len()];
    for i in 0..frames.max(1) {
        let sample = gen.sample(&TimeGrid::default(), 1, i as u64);
        let y = plan.forward(&sample.x.view())?.insert_axis(ndarray::Axis(0));
        for (case, row) in rows.iter_mut().enumerate() {
            let mut est = sample.depth.clone().insert_axis(ndarray::Axis(0));
            est.index_axis_mut(ndarray::Axis(1), 0).mapv_inplace(|v| v + (0.7 * dz) as f32);
            est.index_axis_mut(ndarray::Axis(1), 1).mapv_inplace(|v| if case == 0 { f32::NAN } else { v - (0.6 * dz) as f32 });
            let t0 = std::time::Instant::now();
            refine_ranges(y.view(), &a, &mut est, &RangeFitOptions::default());
            row.0.push(t0.elapsed().as_secs_f64() * 1e3);
            for r in 0..2 {
                for (e, t) in est.index_axis(ndarray::Axis(1), r).iter().zip(sample.depth.index_axis(ndarray::Axis(0), r)) {
                    if e.is_finite() && t.is_finite() {
                        row.1[2 * r] += ((e - t) as f64 / dz).abs();
                        row.1[2 * r + 1] += 1.0;
                    }
                }
            }
        }
    }
    for (name, (ms, err)) in cases.iter().zip(&rows) {
        let mut ms = ms.clone();
        ms.sort_by(f64::total_cmp);
        let mae = |k: usize| if err[2 * k + 1] > 0.0 { format!("{:.3}", err[2 * k] / err[2 * k + 1]) } else { "—".into() };
        println!("{name:<28} {:>10.1} {:>16} {:>16}", ms[ms.len() / 2], mae(0), mae(1));
    }
    Ok(())
}
