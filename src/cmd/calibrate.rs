//! `tcsense calibrate`: a real sensor's dark, gain and matrix from a laser-delay sweep (the
//! work is `tcsense_sensor::calibration`; the report page `tcsense_infer::calibration_report`).

use anyhow::{bail, Result};
use clap::Args;
use std::path::PathBuf;
use std::process::ExitCode;
use tcsense_sensor::calibration::calibrate;
use tcsense_sensor::sweep::Sweep;

use super::sensor::SensorArgs;

#[derive(Args)]
pub struct CalibrateArgs {
    /// The nominal sensor: the codes the sweep was taken with, the IRF and sampling to compare
    /// against (the calibrated matrix has its shape).
    #[command(flatten)]
    sensor: SensorArgs,
    /// Sweep directory with its `sweep.json` (from the sensor, or `tcsense simulate --sweep`).
    #[arg(long)]
    sweep: PathBuf,
    /// Output calibration directory (calibration.json, A.npy, gain.npy, dark.npy,
    /// residual.npy and report.html).
    #[arg(short, long)]
    output: PathBuf,
    /// Skip the report page and its figures.
    #[arg(long)]
    no_report: bool,
}

pub fn run(a: CalibrateArgs) -> Result<ExitCode> {
    if a.sensor.calibration.is_some() {
        bail!("--calibration: calibrate writes a calibration (-o DIR); it does not read one");
    }
    let sensor = a.sensor.sensor()?;
    let nominal = sensor.nominal();
    let sweep = Sweep::load(&a.sweep)?;
    let cal = calibrate(&sweep, nominal, sensor.codes(), sensor.spec().sampling())?;
    cal.save(&a.output)?;
    if !a.no_report {
        if let Err(e) = tcsense_infer::calibration_report::write_calibration_report(&cal, nominal, &a.output) {
            let _ = std::fs::remove_dir_all(&a.output);
            bail!("{}: writing the report failed ({e}); nothing was written", a.output.display());
        }
    }
    let gains: Vec<String> = cal.meta.tap_gains.iter().map(|g| format!("{g:.4}")).collect();
    println!(
        "wrote {}: A [{}, {}, {}] from {} delays, gain and dark maps {}x{}; tap gains [{}], RMS residual {:.2e} of the peak{}",
        a.output.display(),
        nominal.subpixels(),
        nominal.taps(),
        nominal.bins(),
        cal.meta.delays,
        cal.meta.size[0],
        cal.meta.size[1],
        gains.join(", "),
        cal.meta.residual_rms,
        if a.no_report { String::new() } else { format!("; report {}", a.output.join("report.html").display()) }
    );
    Ok(ExitCode::SUCCESS)
}
