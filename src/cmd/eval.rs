//! `tcsense eval`: decoders side by side on a dataset split (the loop is `tcsense_infer::eval`).

use anyhow::{bail, Result};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use std::path::PathBuf;
use std::process::ExitCode;
use tcsense_datasets::Dataset;
use tcsense_infer::eval::{evaluate, evaluate_ladder, EvalRow, EvalSettings};
use tcsense_infer::registry::open_decoder_at_onset;
use tcsense_sensor::npy::write_bytes;
use tcsense_sensor::output::Outputs;
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
    /// Decoders to compare, by their registry names (the list follows): `tval3`, `depth-fit:1`,
    /// `unet:RUN`, `zoo:NAME`, `onnx:MODEL.onnx`, `tval3+fit` …; repeat the flag. Lifetimes of
    /// cube decoders come from the reconvolution fit (`tcsense lifetime`).
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
    /// The photon ladder: evaluate at each of these light levels (the brightest tap's signal
    /// as a share of the full well, e.g. 0.8,0.1,0.02,0.005; noise on), the same items and
    /// noise seeds at each: every decoder's photon-efficiency curve.
    #[arg(long, value_delimiter = ',', value_parser = super::number_in(1e-6, 1.0), conflicts_with = "brightness")]
    light: Vec<f64>,
    /// Ambient light as a signal-to-background ratio (1: as many ambient photons per pixel as
    /// signal photons, on the frame's average); noise on. Default: no ambient.
    #[arg(long, value_parser = super::number_in(1e-3, 1e6))]
    sbr: Option<f64>,
    /// With --light: draw the curve (median first-return error in bins and the share within
    /// half a bin, against the brightest tap's signal electrons) into this PNG.
    #[arg(long, value_name = "PNG", requires = "light")]
    plot: Option<PathBuf>,
    /// The decays' onset in ns when known (a calibration; FLIm datasets): the lifetime fits and
    /// the lifetime networks on the fit's evidence take it and fit only the IRF's width; the
    /// other decoders fit no onset and decode as without it. Default: fitted to each item.
    #[arg(long, value_parser = super::number_in(-1000.0, 1000.0))]
    onset_ns: Option<f64>,
    /// Noise seed (item i uses a stream derived from it).
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Write the table as JSON (and CSV next to it).
    #[arg(short, long)]
    output: Option<PathBuf>,
}

pub fn run(a: EvalArgs) -> Result<ExitCode> {
    // every output checked before any work
    let csv = a.output.as_ref().map(|o| o.with_extension("csv"));
    let mut planned: Vec<(&str, &std::path::Path)> = Vec::new();
    if let (Some(o), Some(c)) = (&a.output, &csv) {
        planned.extend([("-o", o.as_path()), ("-o's CSV", c.as_path())]);
    }
    planned.extend(a.plot.as_deref().map(|p| ("--plot", p)));
    let mut outputs = Outputs::plan(&planned)?;
    let ds = Dataset::open(&a.dataset)?;
    let sensor = a.sensor.sensor()?;
    let nonideal = a.nonideal.nonideal()?;
    if a.onset_ns.is_some() && ds.manifest.kind != tcsense_datasets::store::Kind::Flim {
        bail!("--onset-ns: {} is not a FLIm dataset; only lifetime decoders fit an onset", a.dataset.display());
    }
    let onset_s = a.onset_ns.map(|t| t * 1e-9);
    let mut decoders = open_for(&ds, &a.sensor, &sensor, &a.decoder, &a.tval3, onset_s, &a.device)?;
    if let Some(t) = a.onset_ns {
        println!("the onset given: {t} ns (to the lifetime fits and the lifetime networks on the fit's evidence)");
    }
    let noise = NoiseParams { signal_fraction: NoiseParams::default().signal_fraction * a.brightness, ..NoiseParams::default() };
    let noise = noise.validate().map_err(|e| anyhow::anyhow!("--brightness {}: {e}", a.brightness))?;
    let noisy = a.noise || !a.light.is_empty() || a.sbr.is_some();
    let settings = EvalSettings {
        split: a.split.clone(),
        items: a.items,
        noise: noisy.then_some(noise),
        seed: a.seed,
        sensor: Some(nonideal),
        sbr: a.sbr,
    };
    let cancel = interrupt_flag();
    let pb = item_bar();
    let on_item = |name: &str, done: usize, of: usize| item_done(&pb, name, done, of);
    let rows = if a.light.is_empty() {
        evaluate(&ds, &sensor, &mut decoders, &settings, &on_item, &cancel)
    } else {
        evaluate_ladder(&ds, &sensor, &mut decoders, &settings, &a.light, &on_item, &cancel)
    };
    pb.finish_and_clear();
    let mut rows = rows?;
    for r in rows.iter_mut() {
        r.onset_given_s = onset_s;
    }
    let mut level = None;
    for r in &rows {
        if r.light != level {
            if let Some(l) = r.light {
                let ambient = l.sbr.map_or("no ambient".to_string(), |s| format!("SBR {s}"));
                println!("\nsignal {} of the full well ({:.0} e⁻ in the brightest tap), {ambient}", l.signal_fraction, l.signal_electrons);
            }
            if let Some(c) = r.clipped_share {
                println!("{:.1} % of the pixels have a tap clipped at the full well: no range or lifetime there", 100.0 * c);
            }
            println!("{:<24} {:>5} {:>11} {:>8}", "decoder", "items", "MSE", "PSNR dB");
            level = r.light;
        }
        println!("{}", r.line());
    }
    let mut lines = Vec::new();
    if let (Some(out), Some(csv)) = (&a.output, &csv) {
        write_bytes(&outputs.stage(out)?, (serde_json::to_string_pretty(&rows)? + "\n").as_bytes())?;
        write_bytes(&outputs.stage(csv)?, EvalRow::csv(&rows).as_bytes())?;
        lines.push(format!("wrote {} and {}", out.display(), csv.display()));
    }
    if let Some(png) = &a.plot {
        if rows.iter().any(|r| r.lifetime_mae_s.is_some()) && rows.iter().all(|r| r.depth_median_m.is_empty()) {
            tcsense_infer::curves::lifetime_curve(
                &outputs.stage(png)?,
                &rows,
                &[("", sensor.nominal())],
                sensor.spec().sampling().k(),
                &noise,
                a.sbr,
            )?;
        } else {
            tcsense_infer::curves::range_curve(&outputs.stage(png)?, &rows, &[("", sensor.nominal())], &noise, a.sbr)?;
        }
        lines.push(format!("wrote {}", png.display()));
    }
    outputs.commit()?;
    lines.iter().for_each(|l| println!("{l}"));
    Ok(ExitCode::SUCCESS)
}

/// The decoders `names` opened for evaluating `ds` through `sensor` (from `args`): the sensor's
/// grid must be the dataset's, and a trained run must have been trained with the sensor's codes.
pub(super) fn open_for(
    ds: &Dataset,
    args: &SensorArgs,
    sensor: &tcsense_sensor::Sensor,
    names: &[String],
    tval3: &Tval3Args,
    onset_s: Option<f64>,
    device: &super::DeviceArgs,
) -> Result<Vec<tcsense_infer::registry::NamedDecoder>> {
    let (codes, spec) = (sensor.codes(), sensor.spec());
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
    let opts = tval3.options()?;
    let mut decoders = Vec::new();
    let device = if names.iter().any(|d| ["admm-net:", "unet:", "lifetime:", "zoo:"].iter().any(|k| d.starts_with(k))) {
        device.device()?
    } else {
        tcsense_models::Device::flex()
    };
    for name in names {
        let d = open_decoder_at_onset(name, &opts, onset_s, &device)?;
        if let (Some(run_codes), Some((_, run))) = (d.codes(), name.split_once(':')) {
            if run_codes.shape() != codes.shape() || (0..codes.subpixels() * codes.taps()).any(|c| run_codes.channel(c) != codes.channel(c))
            {
                let run = tcsense_models::zoo::resolve(if name.starts_with("zoo:") { name } else { run })?;
                bail!(
                    "{}: the run was trained with other codes than {}; evaluate it with its own {}",
                    run.display(),
                    args.codes.display(),
                    run.join("codes.json").display()
                );
            }
        }
        decoders.push(d);
    }
    Ok(decoders)
}

/// The progress bar of an evaluation: a decoder's items, one bar per decoder and level.
pub(super) fn item_bar() -> ProgressBar {
    let pb = ProgressBar::new(0);
    pb.set_style(
        ProgressStyle::with_template("{msg} [{bar:30}] {pos}/{len} eta {eta}")
            .unwrap_or_else(|_| ProgressStyle::default_bar())
            .progress_chars("=> "),
    );
    pb
}

/// The evaluation's `on_item(decoder, done, of)` on `pb`: a new bar at each decoder's first item.
pub(super) fn item_done(pb: &ProgressBar, name: &str, done: usize, of: usize) {
    if done == 1 {
        pb.reset();
        pb.set_length(of as u64);
        pb.set_message(name.to_string());
    }
    pb.set_position(done as u64);
}
