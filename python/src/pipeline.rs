//! Whole pipelines: the demo, and calibration from a laser-delay sweep.

use std::io::Write;

use pyo3::prelude::*;
use pyo3::types::PyDict;
use tcsense_pipeline::bringup::{self as bring, BringupOptions};
use tcsense_pipeline::demo::{self, DemoOptions, Observer};
use tcsense_sensor::calibration::calibrate as calibrate_sweep;
use tcsense_sensor::sweep::Sweep;
use tcsense_train::Progress;

use crate::codes::codes_of;
use crate::sensor::{build, IrfArgOwned};
use crate::{err, existing, path_of, run_long};

/// The demo's log on stderr (lines, and an epoch line per training epoch) unless quiet.
struct Stderr {
    quiet: bool,
}

impl Progress for Stderr {
    fn epoch(&self, m: &tcsense_train::EpochMetrics) {
        if !self.quiet {
            let val: Vec<String> = m.val.iter().map(|(n, v)| format!("{n} {v:.4e}")).collect();
            let _ = writeln!(std::io::stderr(), "  epoch {:>4}  train loss {:.4e}  {}", m.epoch, m.train_loss, val.join("  "));
        }
    }
}

impl Observer for Stderr {
    fn line(&self, text: &str) {
        if !self.quiet {
            let _ = writeln!(std::io::stderr(), "{text}");
        }
    }
    fn training(&self) -> &dyn Progress {
        self
    }
}

/// Run the demo into `out` (`tcsense demo`): datasets, code selection and deep sensing,
/// trainings within `budget_minutes`, ONNX export and Runtime, evaluation, timing at
/// `timing_size`, figures and `out/report.html`. Rerunning into `out` resumes; Ctrl-C stops
/// it at the next step, keeping what is done. Returns `{report, seconds, resumed}`.
#[pyfunction]
#[pyo3(signature = (out, *, quick = false, budget_minutes = None, size = None, scenes = None, timing_size = (188, 212), seed = 1, quiet = false))]
#[allow(clippy::too_many_arguments)]
fn run_demo<'py>(
    py: Python<'py>,
    out: &Bound<'py, PyAny>,
    quick: bool,
    budget_minutes: Option<f64>,
    size: Option<(usize, usize)>,
    scenes: Option<usize>,
    timing_size: (usize, usize),
    seed: u64,
    quiet: bool,
) -> PyResult<Bound<'py, PyDict>> {
    let dir = path_of(out)?;
    let options = DemoOptions { quick, budget_minutes, size, scenes, timing_size, seed };
    let obs = Stderr { quiet };
    let s = run_long(py, |cancel| demo::run(&options, &dir, &obs, cancel))?.map_err(err)?;
    let d = PyDict::new(py);
    d.set_item("report", s.report)?;
    d.set_item("seconds", s.seconds)?;
    d.set_item("resumed", s.resumed)?;
    Ok(d)
}

/// Calibrate a sensor from a laser-delay sweep directory (`tcsense calibrate`): the nominal
/// sensor of `codes` under `irf` and `heterodyne`/`oversample`; writes `out` (calibration.json,
/// A.npy, gain.npy, dark.npy, residual.npy and, unless `report=False`, report.html) and
/// returns calibration.json as a dict.
#[pyfunction]
#[pyo3(signature = (codes, sweep, out, *, irf = None, oversample = None, heterodyne = None, report = true))]
#[allow(clippy::too_many_arguments)]
fn calibrate<'py>(
    py: Python<'py>,
    codes: &Bound<'py, PyAny>,
    sweep: &Bound<'py, PyAny>,
    out: &Bound<'py, PyAny>,
    irf: Option<&Bound<'py, PyAny>>,
    oversample: Option<usize>,
    heterodyne: Option<usize>,
    report: bool,
) -> PyResult<Bound<'py, PyAny>> {
    let codes = codes_of(codes)?;
    let irf = match irf {
        Some(i) => {
            IrfArgOwned::parse(i, tcsense_sensor::params::DEFAULT_LASER_FWHM_S * 1e9, tcsense_sensor::params::DEFAULT_TAP_TAU_S * 1e9)?
        }
        None => IrfArgOwned::parse(&pyo3::types::PyString::new(py, "ideal").into_any(), 0.0, 0.0)?,
    };
    let sensor = build(codes, irf, oversample, heterodyne, None)?.inner;
    let nominal = sensor.nominal();
    let sweep_dir = path_of(sweep)?;
    existing(&sweep_dir, "sweep")?;
    let out = path_of(out)?;
    let cal = run_long(py, |_| -> PyResult<_> {
        let sw = Sweep::load(&sweep_dir).map_err(err)?;
        let cal = calibrate_sweep(&sw, nominal, sensor.codes(), sensor.spec().sampling()).map_err(err)?;
        cal.save(&out).map_err(err)?;
        if report {
            if let Err(e) = tcsense_infer::calibration_report::write_calibration_report(&cal, nominal, &out) {
                let _ = std::fs::remove_dir_all(&out);
                return Err(err(format!("{}: writing the report failed ({e}); nothing was written", out.display())));
            }
        }
        Ok(cal)
    })??;
    crate::to_python(py, &serde_json::to_value(&cal.meta).map_err(err)?)
}

/// Bring a sensor up from a laser-delay sweep (`tcsense bringup`): calibration, the zoo's
/// `decoders` (default: the designed-codes entries of the sensor's domain) fine-tuned to the
/// calibrated sensor within `budget_minutes`, ONNX models that take its raw tap images, a check
/// on held-back scenes and `out/report.html`. Rerunning into `out` resumes; Ctrl-C stops it.
/// Returns `{report, models, steps}` (steps: `[(name, seconds)]`).
#[pyfunction]
#[pyo3(signature = (sweep, codes, out, *, irf = "physical", heterodyne = None, decoders = None, budget_minutes = 20.0, epochs = None, scenes = 400, size = (64, 64), check_items = 8, seed = 1, quiet = false))]
#[allow(clippy::too_many_arguments)]
fn bringup<'py>(
    py: Python<'py>,
    sweep: &Bound<'py, PyAny>,
    codes: &Bound<'py, PyAny>,
    out: &Bound<'py, PyAny>,
    irf: &str,
    heterodyne: Option<usize>,
    decoders: Option<Vec<String>>,
    budget_minutes: f64,
    epochs: Option<usize>,
    scenes: usize,
    size: (usize, usize),
    check_items: usize,
    seed: u64,
    quiet: bool,
) -> PyResult<Bound<'py, PyDict>> {
    let irf = match tcsense_sensor::waveform::parse_irf_default(irf, "irf").map_err(err)? {
        tcsense_sensor::waveform::IrfSpec::Model(irf) => irf,
        tcsense_sensor::waveform::IrfSpec::Measured(_) => return Err(err(format!("irf {irf:?}: expected \"physical\" or \"ideal\""))),
    };
    let sampling = tcsense_sensor::Sampling::from_factors(None, heterodyne, tcsense_sensor::Sampling::Oversample(1)).map_err(err)?;
    let options = BringupOptions {
        sweep: path_of(sweep)?,
        codes: path_of(codes)?,
        sampling,
        irf,
        decoders: decoders.unwrap_or_default(),
        budget_minutes,
        epochs,
        scenes,
        size,
        check_items,
        seed,
    };
    let dir = path_of(out)?;
    let obs = Stderr { quiet };
    let s = run_long(py, |cancel| bring::run(&options, &dir, &obs, cancel))?.map_err(err)?;
    let d = PyDict::new(py);
    d.set_item("report", s.report)?;
    d.set_item("models", s.models)?;
    d.set_item("steps", s.steps)?;
    Ok(d)
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(bringup, m)?)?;
    m.add_function(wrap_pyfunction!(run_demo, m)?)?;
    m.add_function(wrap_pyfunction!(calibrate, m)?)?;
    Ok(())
}
