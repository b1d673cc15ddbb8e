//! `tcsense eval`: decoders side by side on a dataset split.

use anyhow::{bail, Result};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use ndarray::{Axis, Ix3, Ix4};
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;
use tcsense_datasets::Dataset;
use tcsense_infer::eval::EvalRow;
use tcsense_models::{tval3, ModelError};
use tcsense_sensor::noise::{add_noise, derive_seed, Exposure};
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
    /// Decoders to compare: `tval3` and/or `admm-net:RUN` (a training run directory); repeat the flag.
    #[arg(long, num_args = 1.., default_value = "tval3")]
    decoder: Vec<String>,
    #[command(flatten)]
    tval3: Tval3Args,
    /// Add shot and read noise to the simulated measurements (full well 20 000 e⁻, σ = 40 e⁻).
    #[arg(long)]
    noise: bool,
    /// Noise seed (item i uses a stream derived from it).
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Write the table as JSON (and CSV next to it).
    #[arg(short, long)]
    output: Option<PathBuf>,
}

pub fn run(a: EvalArgs) -> Result<ExitCode> {
    let ds = Dataset::open(&a.dataset)?;
    let (codes, spec, matrix) = a.sensor.matrix()?;
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
    let x = ds.load(&a.split, "x")?.into_dimensionality::<Ix4>()?;
    let n = a.items.unwrap_or(x.dim().0).min(x.dim().0);
    if n == 0 {
        bail!("{}: no items in split {:?}", a.dataset.display(), a.split);
    }
    let depth = if ds.manifest.fields.contains_key("depth") { Some(ds.load(&a.split, "depth")?.into_dimensionality::<Ix4>()?) } else { None };
    let lifetime = if ds.manifest.fields.contains_key("lifetime") { Some(ds.load(&a.split, "lifetime")?.into_dimensionality::<Ix3>()?) } else { None };
    let (_, _, h, w) = x.dim();
    let plan = matrix.plan(h, w)?;
    let opts = a.tval3.options()?;
    let cancel = interrupt_flag();
    let mut rows = Vec::new();
    for dec in &a.decoder {
        let mut admm = match dec.split_once(':') {
            Some(("admm-net", run)) => {
                let r = super::train::AdmmRunner::open(std::path::Path::new(run))?;
                if r.codes.shape() != codes.shape() || (0..codes.subpixels() * codes.taps()).any(|c| r.codes.channel(c) != codes.channel(c)) {
                    bail!("{run}: the run was trained with other codes than {}; evaluate it with its own {run}/codes.json", a.sensor.codes.display());
                }
                Some(r)
            }
            None if dec == "tval3" => None,
            _ => bail!("--decoder {dec:?}: unknown decoder; expected tval3 or admm-net:RUN"),
        };
        let mut row = EvalRow::new(dec);
        let pb = ProgressBar::new(n as u64);
        pb.set_style(ProgressStyle::with_template("{msg} [{bar:30}] {pos}/{len} eta {eta}").unwrap_or_else(|_| ProgressStyle::default_bar()).progress_chars("=> "));
        pb.set_message(dec.clone());
        for i in 0..n {
            let xi = x.index_axis(Axis(0), i);
            let mut y = plan.forward(&xi)?;
            if a.noise {
                let noisy = add_noise(&y.view().into_dyn(), &NoiseParams::default(), Exposure::Auto, derive_seed(a.seed, i as u64))?;
                y = noisy.in_input_units().into_dimensionality::<Ix3>()?;
            }
            let t0 = Instant::now();
            let xh = match admm.as_mut() {
                Some(r) => r.run(&y.clone().insert_axis(Axis(0)))?.index_axis(Axis(0), 0).to_owned(),
                None => match tval3(&matrix, &plan, &y.view(), &opts, &|_, _| {}, &cancel) {
                    Err(ModelError::Cancelled) => bail!("interrupted"),
                    r => r?.0,
                },
            };
            let secs = t0.elapsed().as_secs_f64();
            let d = depth.as_ref().map(|d| d.index_axis(Axis(0), i));
            let l = lifetime.as_ref().map(|l| l.index_axis(Axis(0), i));
            row.add(&xh.view(), &xi, d.as_ref(), l.as_ref(), spec.bin_width_s(), secs);
            pb.inc(1);
        }
        pb.finish_and_clear();
        rows.push(row);
    }
    println!("{:<24} {:>5} {:>11} {:>8}", "decoder", "items", "MSE", "PSNR dB");
    for r in &rows {
        println!("{}", r.line());
    }
    if let Some(out) = &a.output {
        write_bytes(out, (serde_json::to_string_pretty(&rows)? + "\n").as_bytes())?;
        let mut csv = String::from("decoder,items,mse,psnr_db,bounce1_rmse_m,bounce1_mae_m,bounce1_detection,bounce2_rmse_m,bounce2_mae_m,bounce2_detection,lifetime_mae_s,seconds_per_frame\n");
        for r in &rows {
            let b = |k: usize| r.depth.get(k).map_or(",,".to_string(), |d| format!("{},{},{}", d.rmse_m, d.mae_m, d.detection_rate()));
            csv.push_str(&format!("{},{},{},{},{},{},{},{}\n", r.decoder, r.items, r.mse, r.psnr_db, b(0), b(1), r.lifetime_mae_s.map_or(String::new(), |v| v.to_string()), r.seconds_per_frame));
        }
        write_bytes(&out.with_extension("csv"), csv.as_bytes())?;
        println!("wrote {} and {}", out.display(), out.with_extension("csv").display());
    }
    Ok(ExitCode::SUCCESS)
}
