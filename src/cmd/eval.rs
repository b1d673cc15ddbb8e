//! `tcsense eval`: decoders side by side on a dataset split (the loop is `tcsense_infer::eval`).

use anyhow::{bail, Result};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use std::path::PathBuf;
use std::process::ExitCode;
use tcsense_datasets::Dataset;
use tcsense_infer::eval::{evaluate, open_decoder, EvalRow, EvalSettings};
use tcsense_sensor::npy::write_bytes;
use tcsense_sensor::{NoiseParams, Sampling};

use super::dataset::interrupt_flag;
use super::recon::Tval3Args;
use super::sensor::SensorArgs;

#[derive(Args)]
pub struct EvalArgs {
    /// Dataset directory.
    #[arg(long)]
    dataset: PathBuf,
    /// Split.
    #[arg(long, default_value = "test")]
    split: String,
    /// Use at most this many items.
    #[arg(long)]
    items: Option<usize>,
    #[command(flatten)]
    sensor: SensorArgs,
    /// The sensor the measurements are simulated with, when it is not ideal (the decoders know
    /// only the nominal model, or the calibration given with --calibration).
    #[command(flatten)]
    nonideal: super::sensor::NonIdealArgs,
    /// Decoders to compare: `tval3`, `lifetime-fit`, `depth-fit` (ranges fitted to the taps, no network; `depth-fit:1` one return per pixel), `admm-net:RUN`, `unet:RUN` (its ranges refined in the tap domain; `unet-raw:RUN` without) and/or `lifetime:RUN` (training run directories; RUN may be `zoo:NAME`), `zoo:NAME` (a zoo entry of any kind), `onnx:MODEL.onnx`; a decoder of cubes followed by `+fit` (`tval3+fit`, `zoo:admm-lidar-delay+fit`) also gives ranges, the cube's peaks refined in the tap domain; repeat the flag. Lifetimes of cube decoders come from the reconvolution fit (`tcsense lifetime`).
    #[arg(long, num_args = 1.., default_value = "tval3")]
    decoder: Vec<String>,
    #[command(flatten)]
    tval3: Tval3Args,
    #[command(flatten)]
    device: super::DeviceArgs,
    /// Add shot and read noise to the simulated measurements (full well 20 000 e⁻, σ = 40 e⁻).
    #[arg(long)]
    noise: bool,
    /// Brightness of the scenes relative to the default exposure (brightest tap at 80 % of
    /// full well): 0.1 is ten times fewer photons, 10 overexposes and clips. Needs --noise.
    #[arg(long, default_value_t = 1.0, requires = "noise")]
    brightness: f64,
    /// Noise seed (item i uses a stream derived from it).
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Write the table as JSON (and CSV next to it).
    #[arg(short, long)]
    output: Option<PathBuf>,
}

pub fn run(a: EvalArgs) -> Result<ExitCode> {
    let ds = Dataset::open(&a.dataset)?;
    let sensor = a.sensor.sensor()?;
    let (codes, spec) = (sensor.codes(), sensor.spec());
    let nonideal = a.nonideal.nonideal()?;
    let g = ds.manifest.grid;
    if spec.bins() != ds.manifest.bins || (spec.bin_width_s() - ds.manifest.bin_width_s).abs() > 1e-6 * spec.bin_width_s() {
        bail!(
            "sensor grid (T = {}, Δt = {:.1} ps) differs from the dataset's (T = {}, Δt = {:.1} ps, L = {}, {}): pass matching --oversample/--heterodyne and codes",
            spec.bins(),
            spec.bin_width_s() * 1e12,
            ds.manifest.bins,
            ds.manifest.bin_width_s * 1e12,
            g.length,
            match g.sampling {
                Sampling::Oversample(k) => format!("oversample {k}"),
                Sampling::Heterodyne(k) => format!("heterodyne {k}"),
            }
        );
    }
    let opts = a.tval3.options()?;
    let mut decoders = Vec::new();
    let device = if a.decoder.iter().any(|d| ["admm-net:", "unet:", "lifetime:", "zoo:"].iter().any(|k| d.starts_with(k))) { a.device.device()? } else { tcsense_models::Device::flex() };
    for name in &a.decoder {
        let d = open_decoder(name, &opts, &device)?;
        if let (Some(run_codes), Some((_, run))) = (d.codes(), name.split_once(':')) {
            if run_codes.shape() != codes.shape() || (0..codes.subpixels() * codes.taps()).any(|c| run_codes.channel(c) != codes.channel(c)) {
                let run = tcsense_models::zoo::resolve(if name.starts_with("zoo:") { name } else { run })?;
                bail!("{}: the run was trained with other codes than {}; evaluate it with its own {}", run.display(), a.sensor.codes.display(), run.join("codes.json").display());
            }
        }
        decoders.push(d);
    }
    let noise = NoiseParams { signal_fraction: NoiseParams::default().signal_fraction * a.brightness, ..NoiseParams::default() };
    let noise = noise.validate().map_err(|e| anyhow::anyhow!("--brightness {}: {e}", a.brightness))?;
    let settings = EvalSettings { split: a.split.clone(), items: a.items, noise: a.noise.then_some(noise), seed: a.seed, sensor: Some(nonideal) };
    let cancel = interrupt_flag();
    let pb = ProgressBar::new(0);
    pb.set_style(ProgressStyle::with_template("{msg} [{bar:30}] {pos}/{len} eta {eta}").unwrap_or_else(|_| ProgressStyle::default_bar()).progress_chars("=> "));
    let on_item = |name: &str, done: usize, of: usize| {
        if done == 1 {
            pb.reset();
            pb.set_length(of as u64);
            pb.set_message(name.to_string());
        }
        pb.set_position(done as u64);
    };
    let rows = evaluate(&ds, &sensor, &mut decoders, &settings, &on_item, &cancel);
    pb.finish_and_clear();
    let rows = rows?;
    println!("{:<24} {:>5} {:>11} {:>8}", "decoder", "items", "MSE", "PSNR dB");
    for r in &rows {
        println!("{}", r.line());
    }
    if let Some(out) = &a.output {
        write_bytes(out, (serde_json::to_string_pretty(&rows)? + "\n").as_bytes())?;
        write_bytes(&out.with_extension("csv"), EvalRow::csv(&rows).as_bytes())?;
        println!("wrote {} and {}", out.display(), out.with_extension("csv").display());
    }
    Ok(ExitCode::SUCCESS)
}
