//! `tcsense sensor …` and `tcsense simulate`.

use anyhow::{bail, Result};
use clap::{Args, Subcommand, ValueEnum};
use std::path::PathBuf;
use std::process::ExitCode;
use tcsense_sensor::measure::Measurement;
use tcsense_sensor::noise::Exposure;
use tcsense_sensor::nonideal::NonIdeal;
use tcsense_sensor::npy::{read_cube, write_npy};
use tcsense_sensor::params::{DEFAULT_LASER_FWHM_S, DEFAULT_TAP_TAU_S};
use tcsense_sensor::sweep::{simulate_sweep, SweepSettings};
use tcsense_sensor::waveform::{self, IrfSpec};
use tcsense_sensor::{Codes, Irf, NoiseParams, Sampling, Sensor, SensorModel};

/// The sensor's response and time grid: the one set of flags every command that builds `A`
/// flattens in (with the codes in [`SensorArgs`], with the light in `codes analyze`'s flags).
#[derive(Args, Clone, Default)]
pub struct ResponseArgs {
    /// Instrument response: `ideal` (rectangular gates), `physical` (laser pulse ⋆ tap
    /// response), or a measured matrix `A.npy` of shape [N, M, T]. Default: `ideal` where
    /// codes decode or simulate, `physical` where they are judged (`codes analyze`, `check`,
    /// `export`; real gates are not rectangular).
    #[arg(long)]
    pub irf: Option<String>,
    /// Oversampling factor K of the reconstruction grid (T = L·K).
    #[arg(long, value_name = "K", conflicts_with = "heterodyne")]
    pub oversample: Option<usize>,
    /// Heterodyne sweep with K steps of T_c/K (T = L·K; FLIm).
    #[arg(long, value_name = "K")]
    pub heterodyne: Option<usize>,
    /// Laser pulse FWHM in ns (physical IRF) [default: 2.55].
    #[arg(long, value_name = "NS")]
    pub laser_fwhm_ns: Option<f64>,
    /// First-order tap time constant in ns (physical IRF) [default: 0.3].
    #[arg(long, value_name = "NS")]
    pub tap_tau_ns: Option<f64>,
}

impl ResponseArgs {
    /// The IRF these flags name, `default_irf` when `--irf` is not given.
    pub fn irf_spec(&self, default_irf: &str) -> Result<IrfSpec> {
        let desc = self.irf.as_deref().unwrap_or(default_irf);
        let laser = self.laser_fwhm_ns.map_or(DEFAULT_LASER_FWHM_S, |ns| ns * 1e-9);
        let tap = self.tap_tau_ns.map_or(DEFAULT_TAP_TAU_S, |ns| ns * 1e-9);
        Ok(waveform::parse_irf(desc, laser, tap, "--irf")?)
    }

    /// The first of these flags given on the command line, if any: a decoder that brings its
    /// own sensor refuses them rather than ignore them.
    pub fn given(&self) -> Option<&'static str> {
        [
            ("--irf", self.irf.is_some()),
            ("--oversample", self.oversample.is_some()),
            ("--heterodyne", self.heterodyne.is_some()),
            ("--laser-fwhm-ns", self.laser_fwhm_ns.is_some()),
            ("--tap-tau-ns", self.tap_tau_ns.is_some()),
        ]
        .into_iter()
        .find_map(|(flag, given)| given.then_some(flag))
    }

    /// The sensor model these flags describe (no calibration, no non-idealities).
    pub fn model(&self, default_irf: &str) -> Result<SensorModel> {
        let sampling = Sampling::from_factors(self.oversample, self.heterodyne, Sampling::Oversample(1))?;
        let (irf, measured) = match self.irf_spec(default_irf)? {
            IrfSpec::Model(irf) => (irf, None),
            IrfSpec::Measured(path) => (Irf::Ideal, Some(path)),
        };
        Ok(SensorModel { sampling, irf, measured, ..Default::default() })
    }

    /// The grid's factor K (T = L·K).
    pub fn k(&self) -> usize {
        self.heterodyne.or(self.oversample).unwrap_or(1)
    }
}

/// The sensor a command decodes or simulates with: codes, response and calibration.
#[derive(Args, Clone)]
pub struct SensorArgs {
    /// Codes JSON file.
    #[arg(long)]
    pub codes: PathBuf,
    #[command(flatten)]
    pub response: ResponseArgs,
    /// A calibration directory (`tcsense calibrate`): decode with its measured matrix, after
    /// correcting the tap images for its dark offset and gain maps.
    #[arg(long, value_name = "DIR")]
    pub calibration: Option<PathBuf>,
}

impl SensorArgs {
    /// The flags as the sensor crate's one description of a sensor (without non-idealities);
    /// the IRF is `ideal` unless named.
    pub fn model(&self) -> Result<SensorModel> {
        Ok(SensorModel { calibration: self.calibration.clone(), ..self.response.model("ideal")? })
    }

    /// The sensor these flags describe: the codes loaded, `A` synthesised or loaded (`--irf
    /// A.npy`), and the calibration (`--calibration`) checked against both.
    pub fn sensor(&self) -> Result<Sensor> {
        Ok(Sensor::build(Codes::load(&self.codes)?, &self.model()?)?)
    }
}

/// Sensor non-idealities of a simulated sensor (all off by default: the ideal sensor).
#[derive(Args, Clone, Default)]
pub struct NonIdealArgs {
    /// Per-tap gain mismatch: gains uniform in [1 − F, 1 + F].
    #[arg(long, value_name = "F", default_value_t = 0.0)]
    pub tap_gain: f64,
    /// Per-pixel, per-tap gain σ (photo-response non-uniformity), relative.
    #[arg(long, value_name = "F", default_value_t = 0.0)]
    pub prnu: f64,
    /// Mean dark offset, as a fraction of the full well.
    #[arg(long, value_name = "F", default_value_t = 0.0)]
    pub dark: f64,
    /// Dark fixed-pattern noise σ, as a fraction of the full well.
    #[arg(long, value_name = "F", default_value_t = 0.0)]
    pub dark_fpn: f64,
    /// Share of each tap's charge leaking evenly into the other taps.
    #[arg(long, value_name = "F", default_value_t = 0.0)]
    pub crosstalk: f64,
    /// Share of the charge collected late (diffusion tail).
    #[arg(long, value_name = "F", default_value_t = 0.0)]
    pub tail: f64,
    /// Time constant of the diffusion tail (ns).
    #[arg(long, value_name = "NS", default_value_t = 0.5)]
    pub tail_tau_ns: f64,
    /// Delay of the whole response (drift), ns.
    #[arg(long, value_name = "NS", default_value_t = 0.0)]
    pub shift_ns: f64,
    /// Skew of the taps' gates (ns): each tap opens up to this much early or late (seeded).
    #[arg(long, value_name = "NS", default_value_t = 0.0)]
    pub gate_skew_ns: f64,
    /// Modulation contrast of the pixel (e.g. 0.925): the tap leakage it implies, instead of
    /// --crosstalk.
    #[arg(long, value_name = "C", conflicts_with = "crosstalk")]
    pub modulation_contrast: Option<f64>,
    /// Response compression near full well κ: e' = e·(1 − κ·e/full well), 0–0.5.
    #[arg(long, value_name = "K", default_value_t = 0.0)]
    pub nonlinearity: f64,
    /// Seed of the random non-idealities (tap gains, PRNU, dark pattern, gate skew).
    #[arg(long, value_name = "N", default_value_t = 0)]
    pub sensor_seed: u64,
}

impl NonIdealArgs {
    /// The checked non-idealities.
    pub fn nonideal(&self) -> Result<NonIdeal> {
        let n = NonIdeal {
            tap_gain: self.tap_gain,
            prnu: self.prnu,
            dark: self.dark,
            dark_fpn: self.dark_fpn,
            crosstalk: self.crosstalk,
            tail: self.tail,
            tail_tau_s: self.tail_tau_ns * 1e-9,
            shift_s: self.shift_ns * 1e-9,
            gate_skew_s: self.gate_skew_ns * 1e-9,
            modulation_contrast: self.modulation_contrast.unwrap_or(0.0),
            nonlinearity: self.nonlinearity,
            seed: self.sensor_seed,
        };
        if self.modulation_contrast.is_some_and(|c| !(c > 0.0 && c <= 1.0)) {
            bail!("--modulation-contrast {}: expected a contrast in (0, 1], e.g. 0.925", self.modulation_contrast.unwrap_or_default());
        }
        n.validate().map_err(|e| anyhow::anyhow!("sensor non-idealities (--tap-gain, --prnu, --dark, --dark-fpn, --crosstalk, --tail, --tail-tau-ns, --shift-ns, --gate-skew-ns, --modulation-contrast, --nonlinearity): {e}"))
    }
}

/// `ideal`, or `physical` with the sensor crate's default laser pulse and tap response
/// (commands that synthesise their sensor: a measured matrix is refused).
pub fn parse_irf(name: &str) -> Result<Irf> {
    match waveform::parse_irf_default(name, "--irf")? {
        IrfSpec::Model(irf) => Ok(irf),
        IrfSpec::Measured(_) => bail!("--irf {name:?}: expected ideal or physical (this command synthesises its sensor)"),
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
            let sensor = sensor.sensor()?;
            let (spec, a) = (sensor.spec(), sensor.matrix());
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
            let k = spec.sampling().k();
            let alias = tcsense_sensor::identify::range_alias(&tcsense_sensor::identify::Columns::new(&a, k));
            println!(
                "closest returns in a block's taps: bins {} and {} ({} apart), unit signatures {:.3} apart (0: indistinguishable, 1.414: orthogonal; `tcsense codes analyze` for the bounds)",
                alias.bin,
                alias.other,
                (alias.other - alias.bin).min(a.bins() + alias.bin - alias.other),
                alias.distance
            );
        }
    }
    Ok(ExitCode::SUCCESS)
}

impl From<Units> for tcsense_sensor::Units {
    fn from(u: Units) -> Self {
        match u {
            Units::Input => tcsense_sensor::Units::Input,
            Units::Electrons => tcsense_sensor::Units::Electrons,
            Units::Adc => tcsense_sensor::Units::Adc,
        }
    }
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
    #[command(flatten)]
    nonideal: NonIdealArgs,
    /// Transient cube .npy, [T, H, W] or a batch [B, T, H, W].
    #[arg(long, required_unless_present = "sweep")]
    cube: Option<PathBuf>,
    /// Instead of a cube: write a laser-delay sweep of a flat target (one frame per bin, dark and
    /// flat frames, `sweep.json`) into DIR, for `tcsense calibrate`. Values in electrons, or ADC
    /// codes with `--units adc`.
    #[arg(long, value_name = "DIR", conflicts_with_all = ["cube", "output"])]
    sweep: Option<PathBuf>,
    /// Sweep: frame size.
    #[arg(long, value_parser = super::parse_hw, default_value = "32x32", requires = "sweep")]
    size: (usize, usize),
    /// Sweep: exposures averaged per delay (and dark and flat frames taken). FLIm needs about
    /// 64: with 16 the dark frames' noise costs the lifetime fit 10 % of its accuracy.
    #[arg(long, default_value_t = 64, requires = "sweep", value_parser = super::count_in(1, tcsense_sensor::sweep::MAX_AVERAGE))]
    average: usize,
    /// Sweep: the brightest tap's level, as a fraction of the full well.
    #[arg(long, default_value_t = 0.7, requires = "sweep")]
    sweep_level: f64,
    /// Sweep: write 16-bit PNGs per tap instead of .npy stacks.
    #[arg(long, requires = "sweep")]
    png: bool,
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
    #[arg(short, long, required_unless_present = "sweep")]
    output: Option<PathBuf>,
}

pub fn simulate(a: SimulateArgs) -> Result<ExitCode> {
    let noise =
        NoiseParams { full_well_e: a.full_well, read_noise_e: a.read_noise, signal_fraction: a.signal_fraction, adc_bits: a.adc_bits }
            .validate()?;
    if a.sensor.calibration.is_some() {
        bail!("--calibration describes a decoder's knowledge of a sensor; simulate a sensor with --tap-gain, --prnu, --dark, --tail, …");
    }
    let sensor = a.sensor.sensor()?.with_nonideal(a.nonideal.nonideal()?)?;
    let spec = sensor.spec();
    if let Some(dir) = &a.sweep {
        let settings = SweepSettings {
            size: a.size,
            average: a.average,
            noise,
            noisy: a.noise,
            adc: matches!(a.units, Units::Adc),
            png: a.png,
            level: a.sweep_level,
            seed: a.seed,
        };
        let (bh, bw) = sensor.block();
        if a.size.0 == 0 || a.size.1 == 0 || a.size.0 % bh != 0 || a.size.1 % bw != 0 {
            bail!("--size {}x{}: expected a non-zero multiple of the {bh}x{bw} code block", a.size.0, a.size.1);
        }
        let m = simulate_sweep(sensor.nominal(), sensor.codes(), sensor.nonideal(), &settings, dir)?;
        println!(
            "wrote {}: {} delays over {:.3} ns, {} frames averaged each, in {} (full scale {})",
            dir.join(tcsense_sensor::sweep::MANIFEST).display(),
            m.delays_s.len(),
            spec.cycle_s() * 1e9,
            a.average,
            m.units,
            m.full_scale
        );
        return Ok(ExitCode::SUCCESS);
    }
    let (Some(cube), Some(output)) = (&a.cube, &a.output) else { bail!("--cube and --output are required (or --sweep DIR)") };
    let x = read_cube(cube, true)?;
    let t = x.shape()[x.ndim() - 3];
    if t != spec.bins() {
        bail!(
            "{}: cube has {t} time bins, but the sensor grid has T = L·K = {} bins (L = {}, K = {}); pass --oversample/--heterodyne to match",
            cube.display(),
            spec.bins(),
            spec.params().length,
            spec.sampling().k()
        );
    }
    let exposure = match a.electrons_per_unit {
        Some(s) => Exposure::ElectronsPerUnit(s),
        None => Exposure::Auto,
    };
    let measured = sensor.measure(&x.view(), &noise, a.noise, exposure, a.seed).map_err(|e| anyhow::anyhow!("{}: {e}", cube.display()))?;
    if let Measurement::Noisy(noisy) = &measured {
        eprintln!(
            "noise: {:.4} e⁻ per unit, full well {} e⁻, read noise {} e⁻",
            noisy.electrons_per_unit, noise.full_well_e, noise.read_noise_e
        );
    }
    let units = if a.noise || !sensor.nonideal().is_ideal() { a.units.into() } else { tcsense_sensor::Units::Input };
    let clip_level = measured.clip_level(units, &noise);
    let y = measured.in_units(units, &noise);
    let sidecar = tcsense_sensor::sidecar::Sidecar {
        clip_level,
        ..sensor.sidecar(a.noise.then_some(noise), a.noise.then_some(a.seed), units.name())
    };
    write_npy(output, &y.view())?;
    let meta = sidecar.write_for(output)?;
    println!("wrote {}: y {:?} (sensor in {})", output.display(), y.shape(), meta.display());
    Ok(ExitCode::SUCCESS)
}
