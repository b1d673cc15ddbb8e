//! `tcsense export onnx` and `tcsense infer`: the deployment path.

use anyhow::{bail, Result};
use clap::{Args, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};
use std::path::PathBuf;
use std::process::ExitCode;
use tcsense_infer::onnx::{export_to, ExportOptions};
use tcsense_infer::runtime::OnnxModel;
use tcsense_infer::stream::{run_stream, FrameSource, Products};
use tcsense_models::{runs, Device};
use tcsense_sensor::npy::read_npy;

use super::dataset::interrupt_flag;

#[derive(Subcommand)]
pub enum ExportCmd {
    /// A trained run (ADMM-Net or U-Net) as an ONNX model (opset 17) with its codes, sensor
    /// model, units and frame rule in the metadata.
    Onnx {
        /// Run directory (from `tcsense train`).
        #[arg(long)]
        run: PathBuf,
        /// Take the sensor matrix [N, M, T] as a second input (`sensor_matrix`) instead of
        /// baking it in, so a recalibrated sensor needs no new export.
        #[arg(long)]
        matrix_input: bool,
        /// Output model.
        #[arg(short, long)]
        output: PathBuf,
    },
}

pub fn export(cmd: ExportCmd) -> Result<ExitCode> {
    match cmd {
        ExportCmd::Onnx { run, matrix_input, output } => {
            let loaded = runs::load(&run, &Device::flex())?;
            let bytes = export_to(&loaded, ExportOptions { matrix_input }, &output)?;
            let meta = tcsense_infer::onnx::OnnxMeta::of_run(&loaded, ExportOptions { matrix_input });
            println!(
                "wrote {}: {} ({:.1} kB), input measurements [B, {}, H, W] with H, W multiples of {}x{}{}, outputs {}",
                output.display(),
                loaded.spec.model.name(),
                bytes as f64 / 1e3,
                meta.taps,
                meta.frame_multiple.0,
                meta.frame_multiple.1,
                if matrix_input { format!(" and sensor_matrix [{}, {}, {}]", loaded.sensor.subpixels(), meta.taps, meta.bins) } else { String::new() },
                meta.outputs().join(", ")
            );
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
    /// Products to write: cube, depth, peaks, ply, lifetime (default: cube for ADMM-Net,
    /// depth for the U-Net).
    #[arg(long)]
    products: Option<String>,
    /// Returns per pixel found in a cube (depth, peaks, ply of a cube model).
    #[arg(long, default_value_t = 2)]
    returns: usize,
    /// Horizontal field of view of the camera for point clouds (degrees).
    #[arg(long, default_value_t = 40.0)]
    fov: f64,
    /// A recalibrated sensor matrix .npy [N, M, T] (models exported with --matrix-input).
    #[arg(long)]
    sensor_matrix: Option<PathBuf>,
    /// ONNX Runtime intra-op threads (default: --threads, else all cores).
    #[arg(long)]
    ort_threads: Option<usize>,
    /// Output directory.
    #[arg(short, long)]
    output: PathBuf,
}

pub fn infer(a: InferArgs, threads: Option<usize>) -> Result<ExitCode> {
    if a.returns == 0 {
        bail!("--returns 0: at least one return per pixel");
    }
    let mut model = OnnxModel::open(&a.model, a.ort_threads.or(threads).unwrap_or(0))?;
    let cube_model = model.meta.decoder != "unet";
    let list = a.products.clone().unwrap_or_else(|| if cube_model { "cube".into() } else { "depth".into() });
    let mut products = Products::parse(&list, cube_model)?;
    products.returns = a.returns;
    products.fov_deg = a.fov;
    if let Some(p) = &a.sensor_matrix {
        let arr = read_npy(p)?;
        let shape = arr.shape().to_vec();
        let arr = arr.into_dimensionality::<ndarray::Ix3>().map_err(|_| anyhow::anyhow!("{}: shape {shape:?}, expected [N, M, T]", p.display()))?;
        model.set_matrix_array(arr.view()).map_err(|e| anyhow::anyhow!("{}: {e}", p.display()))?;
    }
    let source = FrameSource::open(&a.measurements)?;
    let frames = source.len();
    let cancel = interrupt_flag();
    let pb = ProgressBar::new(frames as u64);
    pb.set_style(ProgressStyle::with_template("{msg} [{bar:30}] {pos}/{len} {per_sec} eta {eta}").unwrap_or_else(|_| ProgressStyle::default_bar()).progress_chars("=> "));
    pb.set_message(format!("onnx {}", model.meta.decoder));
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
