//! Training and bring-up from Python: `train` and `fine_tune` (the training crate's
//! `TrainRequest`, the command line's options and run directories), and `simulate_sweep` (a
//! laser-delay sweep of a simulated, non-ideal sensor for `calibrate`).

use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};
use tcsense_models::{zoo, Device};
use tcsense_sensor::nonideal::NonIdeal;
use tcsense_sensor::sweep::{simulate_sweep as sweep_of, SweepSettings};
use tcsense_sensor::NoiseParams;
use tcsense_train::request::{self, TrainRequest};
use tcsense_train::{EpochMetrics, Progress, TrainError};

use crate::sensor::PySensor;
use crate::{err, existing, merged, path_of, run_long, to_python};

/// The options dict with path-like values as strings (so they pass through JSON).
fn plain<'py>(py: Python<'py>, options: Option<&Bound<'py, PyDict>>) -> PyResult<Option<Bound<'py, PyDict>>> {
    let Some(d) = options else { return Ok(None) };
    let os = py.import("os")?;
    let out = PyDict::new(py);
    for (k, v) in d.iter() {
        let v = if v.hasattr("__fspath__")? { os.call_method1("fspath", (v,))? } else { v };
        out.set_item(k, v)?;
    }
    Ok(Some(out))
}

/// An epoch as a dict: `epoch`, `step`, `train_loss`, `seconds` and the validation metrics.
fn epoch_dict<'py>(py: Python<'py>, m: &EpochMetrics) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("epoch", m.epoch)?;
    d.set_item("step", m.step)?;
    d.set_item("train_loss", m.train_loss)?;
    d.set_item("seconds", m.seconds)?;
    for (k, v) in &m.val {
        d.set_item(k, v)?;
    }
    Ok(d)
}

/// Training progress: the caller's `progress(epoch_dict)` after every epoch (an exception
/// it raises is printed, and training goes on).
struct Callback(Option<Py<PyAny>>);

impl Progress for Callback {
    fn epoch(&self, m: &EpochMetrics) {
        if let Some(f) = &self.0 {
            Python::attach(|py| {
                if let Err(e) = epoch_dict(py, m).and_then(|d| f.call1(py, (d,))) {
                    e.print(py);
                }
            });
        }
    }
}

fn run_training<'py>(py: Python<'py>, req: TrainRequest, progress: Option<Py<PyAny>>) -> PyResult<Bound<'py, PyList>> {
    let prepared = request::prepare(&req).map_err(err)?;
    let bar = Callback(progress);
    let rows = run_long(py, |cancel| request::run(&prepared, &Device::flex(), &bar, cancel))?;
    let rows = match rows {
        Err(TrainError::Cancelled) => {
            return Err(err(format!("interrupted; the last checkpoint in {} is kept, continue with resume=True", req.output.display())))
        }
        r => r.map_err(err)?,
    };
    let out = PyList::empty(py);
    for m in &rows {
        out.append(epoch_dict(py, m)?)?;
    }
    Ok(out)
}

/// Train a decoder into the run directory `output` (`tcsense train DECODER -o OUTPUT`):
/// `decoder` is "admm-net", "unet" or "lifetime"; the options are the command line's flags
/// with `_` for `-` (`dataset`, `codes`, `epochs`, `lr`, `init_from`, `calibration`, `irf`,
/// `resume`, `seed`, `stages`, `prior`, `crop=[h, w]`, `sensor_residue=[g, p, d]`, …).
/// `progress(epoch)` is called after every epoch with its metrics. Runs with the GIL
/// released; Ctrl-C stops it at the next step, keeping the last checkpoint (continue with
/// `resume=True`). Returns the epochs trained, as dicts.
#[pyfunction]
#[pyo3(signature = (decoder, output, *, progress = None, **options))]
fn train<'py>(
    py: Python<'py>,
    decoder: &str,
    output: &Bound<'py, PyAny>,
    progress: Option<Py<PyAny>>,
    options: Option<&Bound<'py, PyDict>>,
) -> PyResult<Bound<'py, PyList>> {
    let base = TrainRequest { decoder: decoder.into(), output: path_of(output)?, ..Default::default() };
    let req: TrainRequest = merged(&base, plain(py, options)?.as_ref(), "train settings")?;
    if req.decoder != decoder || req.output != base.output {
        return Err(err("train settings: give the decoder and the output as the first two arguments"));
    }
    run_training(py, req, progress)
}

/// Fine-tune the trained run or zoo entry `run` into `output` (`tcsense train KIND
/// --init-from RUN`): its network and architecture, new `codes`, a `dataset`, optionally a
/// `calibration` directory (the decoder then reads the calibrated sensor) and any option of
/// `train`. Returns the epochs trained.
#[pyfunction]
#[pyo3(signature = (run, output, *, progress = None, **options))]
fn fine_tune<'py>(
    py: Python<'py>,
    run: &Bound<'py, PyAny>,
    output: &Bound<'py, PyAny>,
    progress: Option<Py<PyAny>>,
    options: Option<&Bound<'py, PyDict>>,
) -> PyResult<Bound<'py, PyList>> {
    let name = path_of(run)?.to_string_lossy().into_owned();
    let dir = zoo::resolve(&name).map_err(err)?;
    existing(&dir, "run")?;
    let kind = tcsense_train::setup::model_of_run(&dir).map_err(err)?.name().to_string();
    let base = TrainRequest { decoder: kind, output: path_of(output)?, init_from: Some(dir), ..Default::default() };
    let req: TrainRequest = merged(&base, plain(py, options)?.as_ref(), "fine-tuning settings")?;
    run_training(py, req, progress)
}

/// A laser-delay sweep of a flat target through `sensor` (`tcsense simulate --sweep OUT`):
/// one frame per bin, dark and flat frames and `sweep.json`, for `calibrate`. `nonideal` is the
/// real sensor's non-idealities (as for `Sensor.measure`); `average` exposures per delay;
/// `level` the brightest tap's fraction of the full well; values in electrons, or ADC codes
/// with `adc=True`; `png=True` writes 16-bit PNGs. Returns `sweep.json` as a dict.
#[pyfunction]
#[pyo3(signature = (sensor, out, *, size = (32, 32), average = 64, noise = true, level = 0.7, adc = false, png = false, seed = 0, nonideal = None))]
#[allow(clippy::too_many_arguments)]
fn simulate_sweep<'py>(
    py: Python<'py>,
    sensor: &Bound<'py, PySensor>,
    out: &Bound<'py, PyAny>,
    size: (usize, usize),
    average: usize,
    noise: bool,
    level: f64,
    adc: bool,
    png: bool,
    seed: u64,
    nonideal: Option<&Bound<'py, PyDict>>,
) -> PyResult<Bound<'py, PyAny>> {
    let s = &sensor.get().inner;
    if s.calibration().is_some() {
        return Err(err(
            "simulate_sweep: the sensor has a calibration (a decoder's knowledge of a sensor); simulate the real one with nonideal={…}",
        ));
    }
    let (bh, bw) = s.block();
    if size.0 == 0 || size.1 == 0 || size.0 % bh != 0 || size.1 % bw != 0 {
        return Err(err(format!("size {}x{}: expected a non-zero multiple of the {bh}x{bw} code block", size.0, size.1)));
    }
    let ni: NonIdeal = merged(&NonIdeal::default(), nonideal, "nonideal")?;
    let ni = ni.validate().map_err(|e| err(format!("nonideal: {e}")))?;
    let dir = path_of(out)?;
    let settings = SweepSettings { size, average, noise: NoiseParams::default(), noisy: noise, adc, png, level, seed };
    let m = run_long(py, |_| sweep_of(s.nominal(), s.codes(), &ni, &settings, &dir))?.map_err(err)?;
    to_python(py, &serde_json::to_value(&m).map_err(err)?)
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(train, m)?)?;
    m.add_function(wrap_pyfunction!(fine_tune, m)?)?;
    m.add_function(wrap_pyfunction!(simulate_sweep, m)?)?;
    Ok(())
}
