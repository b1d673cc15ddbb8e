//! `tcsense export onnx` and `tcsense infer`: the deployment path.

use anyhow::{bail, Result};
use clap::{Args, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use tcsense_infer::onnx::{export_to, ExportOptions};
use tcsense_infer::runtime::OnnxModel;
use tcsense_infer::stream::{run_stream, FrameSource, ModelKind, Products};
use tcsense_models::{runs, Device};
use tcsense_sensor::npy::read_npy;

use super::dataset::interrupt_flag;

#[derive(Subcommand)]
pub enum ExportCmd {
    /// A trained run (ADMM-Net or U-Net) as an ONNX model (opset 17) with its codes, sensor
    /// model, units and frame rule in the metadata.
    Onnx {
        /// Run directory (from `tcsense train`) or a zoo entry, `zoo:NAME`.
        #[arg(long, value_parser = super::parse_run)]
        run: PathBuf,
        /// Take the sensor matrix [N, M, T] as a second input (`sensor_matrix`) instead of
        /// baking it in, so a recalibrated sensor needs no new export.
        #[arg(long)]
        matrix_input: bool,
        /// Build a sensor calibration (`tcsense calibrate`) into the model: it takes raw tap
        /// images of the calibration's frame size and corrects them for its dark and gain maps
        /// in the graph, and decodes with its matrix.
        #[arg(long, value_name = "DIR")]
        calibration: Option<PathBuf>,
        /// A U-Net on the range fit's evidence (`zoo:unet-lidar-evidence-*`) as one graph from
        /// the tap images: the evidence (cost volume, windows, noise level, pooling by likeness)
        /// computed in the graph, and the posterior's mode refined in the tap domain on the
        /// smallest window (3×3 to 7×7, of like-range neighbours) that pins it, so that any ONNX
        /// runtime decodes the taps with the file alone. One return (no second); `tcsense
        /// infer` writes the graph's product as it is.
        #[arg(long)]
        from_taps: bool,
        /// Output model.
        #[arg(short, long)]
        output: PathBuf,
    },
}

pub fn export(cmd: ExportCmd) -> Result<ExitCode> {
    match cmd {
        ExportCmd::Onnx { run, matrix_input, calibration, from_taps, output } => {
            let loaded = runs::load(&run, &Device::flex())?;
            let calibrated = calibration.as_ref().map(|d| loaded.sensor.clone().calibrated_from(d)).transpose()?;
            let cal = calibrated.as_ref().and_then(|s| s.calibration()).cloned();
            let opts = ExportOptions { matrix_input, calibration: cal.as_ref(), from_taps };
            let bytes = export_to(&loaded, opts, &output)?;
            let meta = tcsense_infer::onnx::OnnxMeta::of_run(&loaded, opts);
            println!(
                "wrote {}: {} ({:.1} kB), input measurements [B, {}, H, W] with H, W multiples of {}x{}{}, outputs {}",
                output.display(),
                loaded.spec.model.name(),
                bytes as f64 / 1e3,
                meta.taps,
                meta.frame_multiple.0,
                meta.frame_multiple.1,
                match (&meta.calibration, matrix_input) {
                    (Some(c), _) => format!(
                        " (raw {} tap images of {}x{} only: calibration {} built in)",
                        c.units,
                        c.size[0],
                        c.size[1],
                        calibration.as_ref().map(|d| d.display().to_string()).unwrap_or_default()
                    ),
                    (None, true) => format!(" and sensor_matrix [{}, {}, {}]", loaded.sensor.spec().subpixels(), meta.taps, meta.bins),
                    (None, false) => String::new(),
                },
                meta.outputs().join(", ")
            );
            if from_taps {
                println!("  one graph from the taps: the range fit's evidence, the network, its posterior's mode refined in the tap domain (one return) in the graph; any ONNX runtime decodes with this file alone");
            }
            if let Some(e) = &meta.range_evidence {
                let c = meta.bins * e.oversample;
                println!(
                    "  the graph reads the range fit's evidence on {c} candidate ranges over {:.3} m{}, which `tcsense infer` (and eval onnx:) computes from the measurements and refines in the tap domain (with the fit's second return); its own inputs: evidence [B, H, W, {}], log_likelihood [B, H, W, {}] (the log-likelihoods of {} windows)",
                    meta.range_m,
                    if e.pool_like == 0 { String::new() } else { format!(", its 3×3 window pooled by likeness over {0}×{0}", e.pool_like) },
                    tcsense_fits::depth::range_feature_channels(c, e.pool),
                    tcsense_fits::depth::SCALES * c,
                    tcsense_fits::depth::SCALES,
                );
            }
            if let Some(e) = &meta.evidence {
                println!(
                    "  the graph reads the fit's evidence on {} lifetimes {}–{} ns, which `tcsense infer` (and eval onnx:) computes from the measurements; its own inputs: evidence [B, H, W, {}], log_likelihood [B, H, W, {}]",
                    e.points,
                    e.tau_range_ns[0],
                    e.tau_range_ns[1],
                    e.channels().0,
                    e.channels().1
                );
            }
            Ok(ExitCode::SUCCESS)
        }
    }
}

#[derive(Args)]
pub struct InferArgs {
    /// Exported model (from `tcsense export onnx`).
    #[arg(long)]
    model: PathBuf,
    /// Tap images: a frame .npy [M, H, W], a stack .npy [F, M, H, W], or a directory of
    /// frames (.npy [M, H, W], or grayscale 16-bit PNGs with the M tap images side by side).
    #[arg(long)]
    measurements: PathBuf,
    /// Products to write: cube, depth, peaks, ply, lifetime, intensity, phasor (a cube model:
    /// all, default cube; the U-Net: depth, ply, default depth; the lifetime decoder: lifetime,
    /// intensity, phasor, default lifetime,intensity).
    #[arg(long)]
    products: Option<String>,
    /// Returns per pixel found in a cube (depth, peaks, ply of a cube model; 1 to 8, default 2)
    /// or by --depth-fit (1 or 2); a depth network gives its own number and takes no other.
    #[arg(long, value_parser = super::count_in(1, 8))]
    returns: Option<usize>,
    /// Horizontal field of view of the camera for point clouds (degrees, 1 to 179).
    #[arg(long, default_value_t = 40.0, value_parser = super::number_in(1.0, 179.0))]
    fov: f64,
    /// A recalibrated sensor matrix .npy [N, M, T] (models exported with --matrix-input).
    #[arg(long)]
    sensor_matrix: Option<PathBuf>,
    /// ONNX Runtime intra-op threads (default: --threads, else all cores; 1 to 256).
    #[arg(long, value_parser = super::count_in(1, super::MAX_THREADS))]
    ort_threads: Option<usize>,
    /// A depth model's ranges as the network gives them, without the range fit in the tap
    /// domain that `reconstruct unet` (and by default `infer`) applies after it.
    #[arg(long, conflicts_with = "depth_fit")]
    no_range_fit: bool,
    /// Depth (and ply, confidence) by the template fit of ranges to the taps through the model's
    /// codes and sensor (every range of the cycle at once, no network; needs codes that do not
    /// alias), not by the network, which is not run when no other product is asked for.
    /// `--returns 1` for one return per pixel (the fastest), 2 for a second where the taps call
    /// for one.
    #[arg(long)]
    depth_fit: bool,
    /// Lifetimes, intensity and phasor by the fit to the taps through the model's codes and
    /// sensor (the template fit: onset and IRF width estimated once on the first frame), not
    /// by the network; the network is not run when no other product is asked for.
    #[arg(long)]
    lifetime_fit: bool,
    /// The onset (ns) of the decays, when known (a calibration, a bright reference): only the
    /// IRF width is fitted, by --lifetime-fit or a lifetime decoder on the fit's evidence.
    #[arg(long)]
    onset_ns: Option<f64>,
    /// Side of the square window of pixels whose costs the fit to the taps sums (odd).
    #[arg(long, requires = "lifetime_fit", default_value_t = 3, value_parser = super::count_in(1, tcsense_fits::range::MAX_WINDOW))]
    window: usize,
    /// Pool each window with the neighbouring windows of like lifetime (--lifetime-fit) or
    /// range (--depth-fit) that tile this side (an odd multiple of the window: 9, 15, 21 for
    /// 3×3; the `lifetime-fit-pooled` and `depth-fit-pooled` decoders): the 3×3 fit in bright
    /// light, a wider window on one surface or cell in dim light.
    #[arg(long, value_parser = super::count_in(1, tcsense_fits::range::MAX_WINDOW))]
    pool_like: Option<usize>,
    /// What a tap clipped at the full well reads, in the frames' units (an ADC's full scale;
    /// `simulate` records its own in `y.meta.json`, used when this is not given): pixels with
    /// a tap at it get no range and no lifetime.
    #[arg(long, value_parser = super::number_in(1e-30, 1e30))]
    clip_level: Option<f64>,
    /// Output directory.
    #[arg(short, long)]
    output: PathBuf,
}

pub fn infer(a: InferArgs, threads: Option<usize>) -> Result<ExitCode> {
    if a.depth_fit && a.lifetime_fit {
        bail!("--depth-fit with --lifetime-fit: a stream fits ranges (LiDAR) or lifetimes (FLIm) to the taps, not both");
    }
    let mut model = OnnxModel::open(&a.model, a.ort_threads.or(threads).unwrap_or(0))?;
    let kind = ModelKind::of(&model.meta.decoder);
    // a fit to the taps must suit the model's sensor: refused here, before any product list is
    // read, so that the two refusals never send the user to each other
    match kind {
        ModelKind::Depth if a.lifetime_fit => bail!("--lifetime-fit: {} is a depth model ({}); the fit to the taps gives lifetimes through a FLIm model's sensor (a lifetime or cube model)", a.model.display(), model.meta.decoder),
        ModelKind::Lifetime if a.depth_fit => bail!("--depth-fit: {} is a lifetime model ({}); the fit to the taps gives ranges through a LiDAR model's sensor (a depth or cube model)", a.model.display(), model.meta.decoder),
        _ => {}
    }
    // the products: as asked, else the fit's when a fit is asked for, else the model's
    let list = match (&a.products, a.depth_fit, a.lifetime_fit) {
        (Some(l), _, _) => l.clone(),
        (None, true, _) => "depth".into(),
        (None, _, true) => "lifetime,intensity".into(),
        (None, false, false) => kind.products().1.to_string(),
    };
    let mut products = Products::parse(&list, kind)?;
    // returns: a depth network gives its own number; a cube's peaks and the depth fit take one
    let returns = match (a.returns, kind, a.depth_fit) {
        (Some(r), ModelKind::Depth, false) if r != model.meta.returns => {
            bail!(
                "--returns {r}: {} gives {} return(s) per pixel (its network's); use --depth-fit for a fit of 1 or 2 returns to the taps",
                a.model.display(),
                model.meta.returns
            )
        }
        (Some(r), _, true) if r > 2 => bail!("--depth-fit with --returns {r}: the fit gives 1 or 2 returns per pixel"),
        (Some(r), _, _) => r,
        (None, ModelKind::Depth, false) => model.meta.returns,
        (None, _, _) => 2,
    };
    products.returns = returns;
    products.fov_deg = a.fov;
    if a.no_range_fit {
        if kind != ModelKind::Depth {
            bail!(
                "--no-range-fit: {} is a {} model; only a depth network's ranges are refined by the range fit",
                a.model.display(),
                model.meta.decoder
            );
        }
        products.range_fit = None;
    }
    if a.pool_like.is_some() && !(a.depth_fit || a.lifetime_fit) {
        bail!("--pool-like: for --depth-fit or --lifetime-fit (it pools the fit's windows); give one of them");
    }
    if a.depth_fit {
        if !(products.depth || products.ply) {
            bail!("--depth-fit with --products {list}: the fit gives depth and ply; ask for one of them");
        }
        let opts = tcsense_fits::depth::DepthFitOptions { returns, ..Default::default() }.pooled(a.pool_like.unwrap_or(0));
        opts.validate().map_err(|e| anyhow::anyhow!("--depth-fit settings (--pool-like): {e}"))?;
        products.depth_fit = Some(opts);
        if let Some(w) = tcsense_infer::fitted::alias_warning(&model.sensor, model.meta.codes.length()) {
            eprintln!("{w}");
        }
    }
    if a.onset_ns.is_some() && !a.lifetime_fit {
        if model.meta.evidence.is_none() {
            bail!(
                "--onset-ns: for --lifetime-fit or a lifetime decoder on the fit's evidence; {} ({}) does not fit an instrument",
                a.model.display(),
                model.meta.decoder
            );
        }
        products.onset_s = a.onset_ns.map(|t| t * 1e-9);
    }
    if a.lifetime_fit {
        if !(products.lifetime || products.intensity || products.phasor) {
            bail!("--lifetime-fit with --products {list}: the fit gives lifetime, intensity and phasor; ask for one of them");
        }
        let opts = tcsense_fits::lifetime_taps::TapFitOptions {
            onset_s: a.onset_ns.map(|t| t * 1e-9),
            window: a.window,
            pool_like: a.pool_like.unwrap_or(0),
            ..Default::default()
        };
        opts.validate().map_err(|e| anyhow::anyhow!("--lifetime-fit settings (--onset-ns, --window, --pool-like): {e}"))?;
        products.lifetime_fit = Some(opts);
    }
    // a recalibrated sensor matrix, read once: given to the model and checked against the sidecar
    let recalibrated = match &a.sensor_matrix {
        Some(p) => {
            let arr = read_npy(p)?;
            let shape = arr.shape().to_vec();
            let arr = arr
                .into_dimensionality::<ndarray::Ix3>()
                .map_err(|_| anyhow::anyhow!("{}: shape {shape:?}, expected [N, M, T]", p.display()))?;
            model.set_matrix_array(arr.view()).map_err(|e| anyhow::anyhow!("{}: {e}", p.display()))?;
            Some(tcsense_sensor::MeasurementMatrix::from_array(arr, &model.meta.spec()?)?)
        }
        None => None,
    };
    let sidecar = tcsense_sensor::sidecar::Sidecar::read_for(&a.measurements)?;
    // the clip level: given, else the one a simulation recorded beside the measurements
    products.clip_level = a.clip_level.map(|v| v as f32).or(sidecar.as_ref().and_then(|s| s.clip_level));
    if let Some(meta) = sidecar {
        let path = tcsense_sensor::sidecar::Sidecar::path_for(&a.measurements);
        match (&recalibrated, &model.meta.calibration) {
            // a recalibrated matrix: the measurements must carry its digest
            (Some(a_cal), _) => meta.check(&path, a_cal, None)?,
            // a calibration in the graph: raw frames of the nominal sensor, in the sweep's units
            (None, Some(cal)) => {
                let nominal = tcsense_sensor::Sensor::ideal(model.meta.codes.clone(), model.meta.sampling, model.meta.irf)?;
                meta.check(&path, nominal.matrix(), Some(&model.meta.codes))?;
                if meta.units != cal.units {
                    bail!("{}: the measurements are in {:?} (field units), the model's built-in calibration corrects raw {:?}; record them in the units of the sweep", path.display(), meta.units, cal.units);
                }
            }
            (None, None) => meta.check(&path, &model.sensor, Some(&model.meta.codes))?,
        }
    }
    let source = FrameSource::open(&a.measurements)?;
    let frames = source.len();
    let cancel = interrupt_flag();
    let pb = ProgressBar::new(frames as u64);
    pb.set_style(
        ProgressStyle::with_template("{msg} [{bar:30}] {pos}/{len} {per_sec} eta {eta}")
            .unwrap_or_else(|_| ProgressStyle::default_bar())
            .progress_chars("=> "),
    );
    pb.set_message(if a.lifetime_fit || a.depth_fit {
        format!("onnx {} + fit to the taps", model.meta.decoder)
    } else {
        format!("onnx {}", model.meta.decoder)
    });
    let on_frame = |done: usize, _total: usize| pb.set_position(done as u64);
    let report = run_stream(&mut model, source, &a.output, &products, &cancel, &on_frame);
    pb.finish_and_clear();
    let report = match report {
        Err(tcsense_infer::InferError::Cancelled) => bail!("interrupted; nothing was written to {}", a.output.display()),
        r => r?,
    };
    let names: Vec<String> = report.written.iter().map(|p| p.display().to_string()).collect();
    println!(
        "{} frames in {:.2} s: {:.1} frames/s end to end, {:.1} ms per frame in ONNX Runtime; wrote {}",
        report.frames,
        report.seconds,
        report.frames as f64 / report.seconds.max(1e-9),
        1e3 * report.infer_seconds / report.frames.max(1) as f64,
        names.join(", ")
    );
    if let Some((i, summed)) = report.instrument {
        println!(
            "instrument: onset {:.3} ns, IRF {:.3} ns FWHM ({}), from {}",
            i.onset_s * 1e9,
            i.irf_fwhm_s * 1e9,
            if a.onset_ns.is_some() { "the onset given" } else { "fitted" },
            if summed == 1 {
                "the first frame".to_string()
            } else {
                format!("{summed} frames of the first's scene, summed (the first was dim)")
            }
        );
    }
    if let Some(kb) = peak_rss_kb() {
        println!("peak memory (VmHWM): {:.1} MiB", kb as f64 / 1024.0);
    }
    Ok(ExitCode::SUCCESS)
}

/// Peak resident memory of this process (Linux).
pub fn peak_rss_kb() -> Option<u64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    s.lines().find(|l| l.starts_with("VmHWM:"))?.split_whitespace().nth(1)?.parse().ok()
}

#[derive(Args)]
pub struct BenchInferArgs {
    /// An exported model (timed through ONNX Runtime only, unless --run gives its network).
    #[arg(long)]
    model: Option<PathBuf>,
    /// A trained run (or `zoo:NAME`): timed in burn, and exported for ONNX Runtime when
    /// --model is not given.
    #[arg(long, value_parser = super::parse_run)]
    run: Option<PathBuf>,
    /// Without --run/--model: a fresh network of this kind (unet, admm-net or lifetime) on the
    /// prototype's codes (4 taps, 2x2, L = 32, tap + H 2 + W 2).
    #[arg(long, default_value = "unet")]
    decoder: String,
    /// Fresh ADMM-Net: stages S.
    #[arg(long, default_value_t = 9)]
    stages: usize,
    /// Fresh ADMM-Net: channels CN (per bin with --prior delay).
    #[arg(long, default_value_t = 32)]
    channels: usize,
    /// Fresh ADMM-Net: the prior (`bins` or `delay`).
    #[arg(long, default_value = "bins", value_parser = ["bins", "delay"])]
    prior: String,
    /// Fresh networks: bins T (L = 32, K = T/32).
    #[arg(long, default_value_t = 32)]
    bins: usize,
    /// Frame size HxW.
    #[arg(long, default_value = "188x212", value_parser = super::parse_hw)]
    size: (usize, usize),
    /// Timed rounds (each round runs every engine once; medians reported).
    #[arg(long, default_value_t = 7)]
    reps: usize,
    /// ONNX Runtime intra-op thread counts to time (comma-separated).
    #[arg(long, default_value = "2,1", value_delimiter = ',')]
    ort_threads: Vec<usize>,
    /// Keep the exported model here (e.g. for scripts/bench_onnx.py on the same model).
    #[arg(long)]
    save_model: Option<PathBuf>,
}

/// A fresh network on the prototype's codes, as a run.
fn fresh_run(a: &BenchInferArgs) -> Result<runs::LoadedRun> {
    use tcsense_sensor::{Irf, Sampling};
    if a.bins == 0 || a.bins % 32 != 0 {
        bail!("--bins {}: expected a multiple of 32", a.bins);
    }
    let codes = super::prototype_codes()?;
    let sampling = Sampling::Oversample(a.bins / 32);
    use runs::network_names::{ADMM_NET, LIFETIME, UNET};
    let model = match a.decoder.as_str() {
        UNET => runs::ModelConfig::Unet(
            tcsense_models::UnetConfig::new(4, a.bins, tcsense_sensor::C * 32.0 / 607e6 / 2.0)
                .with_head(tcsense_models::UnetHead::ScoreVolume),
        ),
        ADMM_NET => {
            let prior = if a.prior == "delay" { tcsense_models::Prior::Delay } else { tcsense_models::Prior::Bins };
            runs::ModelConfig::AdmmNet(
                tcsense_models::AdmmNetConfig::new(4, a.bins)
                    .with_stages(a.stages)
                    .with_channels(a.channels)
                    .with_normalize(true)
                    .with_prior(prior),
            )
        }
        LIFETIME => runs::ModelConfig::Lifetime(tcsense_models::LifetimeNetConfig::new(4, a.bins)),
        other => bail!("--decoder {other:?}: expected unet, admm-net or lifetime"),
    };
    let spec = runs::RunSpec { model, sampling, irf: Irf::Ideal, measured: false };
    let sensor = spec.sensor(Path::new("."), codes)?;
    let device = Device::flex();
    let net = match &spec.model {
        runs::ModelConfig::AdmmNet(c) => runs::TrainedNet::AdmmNet(c.init(&device)),
        runs::ModelConfig::Unet(c) => runs::TrainedNet::Unet(c.init(&device)),
        runs::ModelConfig::Lifetime(c) => runs::TrainedNet::Lifetime(c.init(&device)),
    };
    Ok(runs::LoadedRun { dir: PathBuf::from("."), spec, sensor, net })
}

pub fn bench_infer(a: BenchInferArgs) -> Result<()> {
    if a.ort_threads.is_empty() || a.ort_threads.contains(&0) {
        bail!("--ort-threads: expected thread counts ≥ 1, e.g. 2,1");
    }
    let (h, w) = a.size;
    let run = match (&a.run, &a.model) {
        (Some(r), _) => Some(runs::load(r, &Device::flex())?),
        (None, None) => Some(fresh_run(&a)?),
        (None, Some(_)) => None,
    };
    let tmp = a.save_model.clone().unwrap_or_else(|| tempfile_path("bench-infer.onnx"));
    let model_path = match (&a.model, &run) {
        (Some(m), _) => m.clone(),
        (None, Some(r)) => {
            export_to(r, ExportOptions::default(), &tmp)?;
            tmp.clone()
        }
        (None, None) => unreachable!("a run exists when no model is given"),
    };
    let timing = tcsense_infer::timing::time_decoder(run.as_ref(), &model_path, (h, w), &a.ort_threads, a.reps).map_err(|e| match e {
        tcsense_infer::InferError::InvalidParam { field: "frame size", got, expected } => {
            anyhow::anyhow!("--size {got}: the model takes frames that are {expected}")
        }
        e => e.into(),
    });
    // the exported model is kept (--save-model) only when the benchmark ran: a failed command
    // leaves nothing behind
    if a.save_model.is_none() || (timing.is_err() && a.model.is_none()) {
        let _ = std::fs::remove_file(&tmp);
    }
    let t = timing?;
    println!(
        "{} at {h}x{w}, T = {}, M = {}, batch 1, median of {} interleaved rounds{}",
        t.decoder,
        t.bins,
        t.taps,
        t.rounds,
        t.gflop_per_frame.map(|f| format!(", {f:.2} GFLOP per frame")).unwrap_or_default()
    );
    println!("{:<26} {:>10} {:>10} {:>10}", "engine", "ms/frame", "frames/s", "GFLOP/s");
    for e in &t.engines {
        let rate = t.gflop_per_frame.map(|f| format!("{:>10.1}", f / e.ms_per_frame * 1e3)).unwrap_or_else(|| format!("{:>10}", "-"));
        println!("{:<26} {:>10.2} {:>10.1} {rate}", e.engine, e.ms_per_frame, e.frames_per_s);
    }
    if t.engines.len() > 1 {
        let ratios: Vec<String> = t.engines[1..]
            .iter()
            .map(|e| format!("{} / {}: {:.2}", t.engines[0].engine, e.engine, t.engines[0].ms_per_frame / e.ms_per_frame))
            .collect();
        println!("time ratios: {}", ratios.join("; "));
    }
    Ok(())
}

fn tempfile_path(name: &str) -> PathBuf {
    std::env::temp_dir().join(format!("tcsense-{}-{name}", std::process::id()))
}
