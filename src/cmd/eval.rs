//! `tcsense eval`: decoders side by side on a dataset split (the loop is `tcsense_infer::eval`).

use anyhow::{bail, Result};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use std::path::PathBuf;
use std::process::ExitCode;
use tcsense_datasets::Dataset;
use tcsense_infer::eval::{evaluate, evaluate_ladder, EvalRow, EvalSettings};
use tcsense_infer::registry::open_decoder;
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
    let device = if a.decoder.iter().any(|d| ["admm-net:", "unet:", "lifetime:", "zoo:"].iter().any(|k| d.starts_with(k))) {
        a.device.device()?
    } else {
        tcsense_models::Device::flex()
    };
    for name in &a.decoder {
        let d = open_decoder(name, &opts, &device)?;
        if let (Some(run_codes), Some((_, run))) = (d.codes(), name.split_once(':')) {
            if run_codes.shape() != codes.shape() || (0..codes.subpixels() * codes.taps()).any(|c| run_codes.channel(c) != codes.channel(c))
            {
                let run = tcsense_models::zoo::resolve(if name.starts_with("zoo:") { name } else { run })?;
                bail!(
                    "{}: the run was trained with other codes than {}; evaluate it with its own {}",
                    run.display(),
                    a.sensor.codes.display(),
                    run.join("codes.json").display()
                );
            }
        }
        decoders.push(d);
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
    let pb = ProgressBar::new(0);
    pb.set_style(
        ProgressStyle::with_template("{msg} [{bar:30}] {pos}/{len} eta {eta}")
            .unwrap_or_else(|_| ProgressStyle::default_bar())
            .progress_chars("=> "),
    );
    let on_item = |name: &str, done: usize, of: usize| {
        if done == 1 {
            pb.reset();
            pb.set_length(of as u64);
            pb.set_message(name.to_string());
        }
        pb.set_position(done as u64);
    };
    let rows = if a.light.is_empty() {
        evaluate(&ds, &sensor, &mut decoders, &settings, &on_item, &cancel)
    } else {
        evaluate_ladder(&ds, &sensor, &mut decoders, &settings, &a.light, &on_item, &cancel)
    };
    pb.finish_and_clear();
    let rows = rows?;
    let mut level = None;
    for r in &rows {
        if r.light != level {
            if let Some(l) = r.light {
                let ambient = l.sbr.map_or("no ambient".to_string(), |s| format!("SBR {s}"));
                println!("\nsignal {} of the full well ({:.0} e⁻ in the brightest tap), {ambient}", l.signal_fraction, l.signal_electrons);
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
            lifetime_curve(&outputs.stage(png)?, &rows, sensor.nominal(), sensor.spec().sampling().k(), &noise, a.sbr)?;
        } else {
            photon_curve(&outputs.stage(png)?, &rows, sensor.nominal(), &noise, a.sbr)?;
        }
        lines.push(format!("wrote {}", png.display()));
    }
    outputs.commit()?;
    lines.iter().for_each(|l| println!("{l}"));
    Ok(ExitCode::SUCCESS)
}

/// One series per decoder of ladder rows (in their order): `f` of each row against the
/// brightest tap's signal electrons of its level.
fn decoder_series(rows: &[EvalRow], f: &dyn Fn(&EvalRow) -> Option<f64>) -> Vec<tcsense_infer::figures::Series> {
    let mut names: Vec<&str> = Vec::new();
    for r in rows {
        if !names.contains(&r.decoder.as_str()) {
            names.push(&r.decoder);
        }
    }
    names
        .iter()
        .map(|n| tcsense_infer::figures::Series {
            label: n.to_string(),
            points: rows.iter().filter(|r| r.decoder == *n).filter_map(|r| Some((r.light?.signal_electrons, f(r)?))).collect(),
        })
        .collect()
}

/// The largest share of a return's light one tap collects (photons = tap electrons / share).
fn brightest_tap_share(a: &tcsense_sensor::MeasurementMatrix) -> f64 {
    let m = a.a();
    let (n, taps, t) = m.dim();
    let mut share = 0f64;
    for i in 0..n {
        for j in 0..t {
            let col: Vec<f64> = (0..taps).map(|k| m[(i, k, j)] as f64).collect();
            let total: f64 = col.iter().sum();
            if total > 0.0 {
                share = share.max(col.iter().fold(0.0, |x: f64, &v| x.max(v)) / total);
            }
        }
    }
    share
}

/// The photon-efficiency figure of FLIm ladder rows: each decoder's lifetime MAE (ns) and the
/// share of the fluorophore pixels with a lifetime against the brightest tap's signal
/// electrons, beside the codes' Cramér–Rao bound of a 2 ns lifetime seen by a whole block with
/// its onset known ([`tcsense_sensor::identify::lifetime_bound`], mean over 8 onsets), under the
/// noise model's read noise and the ambient light.
fn lifetime_curve(
    png: &std::path::Path,
    rows: &[EvalRow],
    a: &tcsense_sensor::MeasurementMatrix,
    k: usize,
    noise: &NoiseParams,
    sbr: Option<f64>,
) -> Result<()> {
    use tcsense_infer::figures::Series;
    use tcsense_sensor::identify::{lifetime_bound, Columns, Light};
    let share = brightest_tap_share(a);
    let mut levels: Vec<f64> = rows.iter().filter_map(|r| r.light.map(|l| l.signal_electrons)).collect();
    levels.dedup();
    let cols = Columns::new(a, k);
    let weights = vec![1.0; a.a().dim().0];
    let bound = (share > 0.0).then(|| Series {
        label: "Cramér–Rao bound (a block, τ = 2 ns, onset known)".into(),
        points: levels
            .iter()
            .map(|&e| {
                let photons = e / share;
                let light = Light { photons, ambient: sbr.map_or(0.0, |s| photons / s), read_noise_e: noise.read_noise_e };
                (e, lifetime_bound(&cols, &light, &[2e-9], 8, &weights)[0].known_mean_s * 1e9)
            })
            .collect(),
    });
    let series = |f: &dyn Fn(&EvalRow) -> Option<f64>| decoder_series(rows, f);
    let errors = series(&|r| r.lifetime_mae_s.map(|v| v * 1e9));
    let shares = series(&|r| r.lifetime_coverage.map(|v| 100.0 * v));
    let ambient = sbr.map_or("no ambient light".to_string(), |s| format!("ambient at SBR {s}"));
    tcsense_infer::figures::photon_curve(
        png,
        &format!("Photon efficiency: lifetime error against the light ({ambient})"),
        "signal electrons in the brightest tap (e⁻)",
        "lifetime MAE (ns)",
        "fluorophore pixels with a lifetime (%)",
        &errors,
        &shares,
        bound.as_ref(),
    )?;
    Ok(())
}

/// The photon-efficiency figure of ladder rows: each decoder's median first-return error (bins)
/// and share within half a bin against the brightest tap's signal electrons.
/// Beside them, the codes' Cramér–Rao bound of one return seen by a whole block
/// ([`tcsense_sensor::identify::range_bound`], mean over the cycle) whose brightest tap holds
/// the level's signal electrons, with the noise model's read noise and the ambient light.
fn photon_curve(
    png: &std::path::Path,
    rows: &[EvalRow],
    a: &tcsense_sensor::MeasurementMatrix,
    noise: &NoiseParams,
    sbr: Option<f64>,
) -> Result<()> {
    use tcsense_infer::figures::Series;
    use tcsense_sensor::identify::{range_bound, Light};
    let bin_m = 299_792_458.0 * a.bin_width_s() / 2.0;
    let share = brightest_tap_share(a);
    let mut levels: Vec<f64> = rows.iter().filter_map(|r| r.light.map(|l| l.signal_electrons)).collect();
    levels.dedup();
    let bound = (share > 0.0).then(|| Series {
        label: "Cramér–Rao bound (a block, one return)".into(),
        points: levels
            .iter()
            .map(|&e| {
                let photons = e / share;
                let light = Light { photons, ambient: sbr.map_or(0.0, |s| photons / s), read_noise_e: noise.read_noise_e };
                (e, range_bound(a, &light, 2).mean_bins)
            })
            .collect(),
    });
    let series = |f: &dyn Fn(&EvalRow) -> Option<f64>| decoder_series(rows, f);
    let errors = series(&|r| r.depth_median_m.first().map(|m| m / bin_m));
    let shares = series(&|r| r.depth_within_half_bin.first().map(|s| 100.0 * s));
    if errors.iter().all(|s| s.points.is_empty()) {
        bail!(
            "--plot: the decoders gave no first-return ranges nor lifetimes (a LiDAR dataset with depth and decoders of depth or cubes, or a FLIm dataset and lifetime decoders, draw the curve)"
        );
    }
    let ambient = sbr.map_or("no ambient light".to_string(), |s| format!("ambient at SBR {s}"));
    tcsense_infer::figures::photon_curve(
        png,
        &format!("Photon efficiency: first-return range error against the light ({ambient})"),
        "signal electrons in the brightest tap (e⁻)",
        "median first-return error (bins)",
        "first returns within half a bin (%)",
        &errors,
        &shares,
        bound.as_ref(),
    )?;
    Ok(())
}
