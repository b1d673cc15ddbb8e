//! `tcsense sensor …` and `tcsense simulate`.

use anyhow::{bail, Result};
use clap::{Args, Subcommand, ValueEnum};
use std::path::PathBuf;
use std::process::ExitCode;
use tcsense_sensor::measure::{measure, Measurement};
use tcsense_sensor::noise::Exposure;
use tcsense_sensor::npy::{read_cube, write_npy};
use tcsense_sensor::params::{DEFAULT_LASER_FWHM_S, DEFAULT_TAP_TAU_S};
use tcsense_sensor::{Codes, Irf, MeasurementMatrix, NoiseParams, Sampling, SensorParams, SensorSpec};

/// Sensor-model flags shared by every command that needs `A`.
#[derive(Args, Clone)]
pub struct SensorArgs {
    /// Codes JSON file.
    #[arg(long)]
    pub codes: PathBuf,
    /// Instrument response: `ideal` (rectangular gates), `physical` (laser pulse ⋆ tap
    /// response), or a measured matrix `A.npy` of shape [N, M, T].
    #[arg(long, default_value = "ideal")]
    pub irf: String,
    /// Oversampling factor K of the reconstruction grid (T = L·K).
    #[arg(long, value_name = "K", conflicts_with = "heterodyne")]
    pub oversample: Option<usize>,
    /// Heterodyne sweep with K steps of T_c/K (T = L·K).
    #[arg(long, value_name = "K")]
    pub heterodyne: Option<usize>,
    /// Laser pulse FWHM in ns (physical IRF).
    #[arg(long, default_value_t = 2.55)]
    pub laser_fwhm_ns: f64,
    /// First-order tap time constant in ns (physical IRF).
    #[arg(long, default_value_t = 0.3)]
    pub tap_tau_ns: f64,
}

impl SensorArgs {
    /// Load the codes and build the checked spec (without noise settings).
    pub fn spec(&self) -> Result<(Codes, SensorSpec)> {
        let codes = Codes::load(&self.codes)?;
        let sampling = match (self.oversample, self.heterodyne) {
            (_, Some(k)) => Sampling::Heterodyne(k),
            (Some(k), None) => Sampling::Oversample(k),
            (None, None) => Sampling::Oversample(1),
        };
        let irf = match self.irf.as_str() {
            "physical" => Irf::Physical { laser_fwhm_s: self.laser_fwhm_ns * 1e-9, tap_tau_s: self.tap_tau_ns * 1e-9 },
            _ => Irf::Ideal,
        };
        let spec = SensorParams { sampling, irf, ..SensorParams::from_codes(&codes) }.validate()?;
        Ok((codes, spec))
    }

    /// The measurement matrix: synthesised, or loaded when `--irf` names a file.
    pub fn matrix(&self) -> Result<(Codes, SensorSpec, MeasurementMatrix)> {
        let (codes, spec) = self.spec()?;
        let a = match self.irf.as_str() {
            "ideal" | "physical" => MeasurementMatrix::synthesize(&codes, &spec)?,
            path if path.ends_with(".npy") => MeasurementMatrix::load(std::path::Path::new(path), &spec)?,
            other => bail!("--irf {other:?}: expected `ideal`, `physical` or a measured matrix file `A.npy`"),
        };
        Ok((codes, spec, a))
    }
}

/// `ideal`, or `physical` with the sensor crate's default laser pulse and tap response.
pub fn parse_irf(name: &str) -> Result<Irf> {
    match name {
        "ideal" => Ok(Irf::Ideal),
        "physical" => Ok(Irf::Physical { laser_fwhm_s: DEFAULT_LASER_FWHM_S, tap_tau_s: DEFAULT_TAP_TAU_S }),
        other => bail!("--irf {other:?}: expected ideal or physical"),
    }
}

#[derive(Subcommand)]
pub enum SensorCmd {
    /// Write the measurement matrix A [N, M, T] as .npy.
    Matrix {
        #[command(flatten)]
        sensor: SensorArgs,
        /// Output .npy.
        #[arg(short, long)]
        output: PathBuf,
    },
}

pub fn run(cmd: SensorCmd) -> Result<ExitCode> {
    match cmd {
        SensorCmd::Matrix { sensor, output } => {
            let (_, spec, a) = sensor.matrix()?;
            a.save(&output)?;
            println!(
                "wrote {}: A [N, M, T] = [{}, {}, {}], bin width {:.1} ps, cycle {:.2} ns",
                output.display(),
                a.subpixels(),
                a.taps(),
                a.bins(),
                spec.bin_width_s() * 1e12,
                spec.cycle_s() * 1e9
            );
        }
    }
    Ok(ExitCode::SUCCESS)
}

/// Units of the simulated measurements.
#[derive(Clone, Copy, ValueEnum)]
pub enum Units {
    /// Same units as the noiseless A x (noise rescaled back).
    Input,
    /// Electrons.
    Electrons,
    /// ADC codes.
    Adc,
}

#[derive(Args)]
pub struct SimulateArgs {
    #[command(flatten)]
    sensor: SensorArgs,
    /// Transient cube .npy, [T, H, W] or a batch [B, T, H, W].
    #[arg(long)]
    cube: PathBuf,
    /// Add shot noise, read noise, full-well clipping and ADC quantisation.
    #[arg(long)]
    noise: bool,
    /// Full-well capacity (e⁻).
    #[arg(long, default_value_t = 20_000.0)]
    full_well: f64,
    /// Read noise σ (e⁻).
    #[arg(long, default_value_t = 40.0)]
    read_noise: f64,
    /// Brightest tap scaled to this fraction of full well.
    #[arg(long, default_value_t = 0.8)]
    signal_fraction: f64,
    /// Electrons per unit of A x (overrides --signal-fraction).
    #[arg(long)]
    electrons_per_unit: Option<f64>,
    /// ADC bits over the full well (0: no quantisation).
    #[arg(long, default_value_t = 12)]
    adc_bits: u32,
    /// Output units with --noise.
    #[arg(long, value_enum, default_value = "input")]
    units: Units,
    /// Noise seed.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Output .npy: [M, H, W] (or [B, M, H, W]).
    #[arg(short, long)]
    output: PathBuf,
}

pub fn simulate(a: SimulateArgs) -> Result<ExitCode> {
    let noise = NoiseParams {
        full_well_e: a.full_well,
        read_noise_e: a.read_noise,
        signal_fraction: a.signal_fraction,
        adc_bits: a.adc_bits,
    }
    .validate()?;
    let (codes, spec, matrix) = a.sensor.matrix()?;
    let x = read_cube(&a.cube, true)?;
    let shape = x.shape().to_vec();
    let (t, h, w) = (shape[shape.len() - 3], shape[shape.len() - 2], shape[shape.len() - 1]);
    if t != spec.bins() {
        bail!(
            "{}: cube has {t} time bins, but the sensor grid has T = L·K = {} bins (L = {}, K = {}); pass --oversample/--heterodyne to match",
            a.cube.display(),
            spec.bins(),
            spec.params().length,
            spec.sampling().k()
        );
    }
    let plan = matrix.plan(h, w).map_err(|e| anyhow::anyhow!("{}: {e}", a.cube.display()))?;
    let exposure = match a.electrons_per_unit {
        Some(s) => Exposure::ElectronsPerUnit(s),
        None => Exposure::Auto,
    };
    let y = match measure(&plan, &x.view(), a.noise.then_some(&noise), exposure, a.seed)? {
        Measurement::Noiseless(y) => y,
        Measurement::Noisy(noisy) => {
            eprintln!("noise: {:.4} e⁻ per unit, full well {} e⁻, read noise {} e⁻", noisy.electrons_per_unit, noise.full_well_e, noise.read_noise_e);
            match a.units {
                Units::Input => noisy.in_input_units(),
                Units::Electrons => noisy.electrons,
                Units::Adc => noisy.in_adc_codes(&noise),
            }
        }
    };
    let units = match (a.noise, a.units) {
        (false, _) | (true, Units::Input) => "input",
        (true, Units::Electrons) => "electrons",
        (true, Units::Adc) => "adc",
    };
    let sidecar = tcsense_sensor::sidecar::Sidecar::new(&codes, &matrix, spec.sampling(), a.noise.then_some(noise), a.noise.then_some(a.seed), units);
    write_npy(&a.output, &y.view())?;
    let meta = sidecar.write_for(&a.output)?;
    println!("wrote {}: y {:?} (sensor in {})", a.output.display(), y.shape(), meta.display());
    Ok(ExitCode::SUCCESS)
}
