//! Decoders: `tval3`, `lifetime_fit`, and `Decoder` objects for every kind — training runs
//! (ADMM-Net, Aᵀ + U-Net, the lifetime network; `zoo:NAME` too), TVAL3, the fit to the taps and
//! exported ONNX models — all behind the crates' one decoder contract.

use std::path::PathBuf;
use std::sync::Mutex;

use ndarray::{Array4, Axis, Ix4};
use numpy::{IntoPyArray, PyUntypedArrayMethods};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};
use tcsense_fits::lifetime_taps::TapFitOptions;
use tcsense_infer::decode::{check_codes, decode_batch};
use tcsense_infer::fitted::TapFitDecoder;
use tcsense_infer::registry::{DecoderSettings, Registry};
use tcsense_models::decoder::{Control, Decoded, Decoder, Tval3Decoder};
use tcsense_models::{runs, zoo, Device, Tval3Options};

use crate::codes::PyCodes;
use crate::sensor::PySensor;
use crate::{check_rank, err, existing, f32_array, merged, path_of, run_long};

/// A decoder: tap images in, cubes, depth or lifetimes out.
#[pyclass(name = "Decoder", module = "tcsense", frozen)]
pub struct PyDecoder {
    label: String,
    kind: String,
    inner: Mutex<Box<dyn Decoder>>,
    /// The sensor it was trained for and decodes with when `decode` is given none (runs and
    /// ONNX models); its codes are the only ones it decodes.
    sensor: Option<Py<PySensor>>,
    run: Option<PathBuf>,
}

/// The decoded batch as a dict of arrays, without the batch axis when the input had none.
fn decoded_dict<'py>(py: Python<'py>, d: Decoded, batched: bool) -> PyResult<Bound<'py, PyDict>> {
    let out = PyDict::new(py);
    let put = |name: &str, a: Option<Array4<f32>>| -> PyResult<()> {
        if let Some(a) = a {
            let a = if batched { a.into_dyn() } else { a.index_axis_move(Axis(0), 0).into_dyn() };
            out.set_item(name, a.into_pyarray(py))?;
        }
        Ok(())
    };
    put("cube", d.cube)?;
    put("depth", d.depth)?;
    put("confidence", d.confidence)?;
    put("lifetime", d.lifetime)?;
    put("intensity", d.intensity)?;
    Ok(out)
}

/// Decode `y` (`[M, H, W]` or `[B, M, H, W]`) with `decoder` on `sensor`
/// ([`tcsense_infer::decode::decode_batch`]: a calibrated sensor's raw frames are corrected
/// first, then decoded with its matrix).
fn decode_with<'py>(
    py: Python<'py>,
    decoder: &Mutex<Box<dyn Decoder>>,
    sensor: &PySensor,
    y: &Bound<'py, PyAny>,
    clip_level: Option<f32>,
) -> PyResult<Bound<'py, PyDict>> {
    let arr = f32_array(y, "y")?;
    check_rank(arr.shape(), &[3, 4], "y", "[M, H, W] or [B, M, H, W]")?;
    let v = arr.as_array();
    let batched = v.ndim() == 4;
    let v = if batched { v.into_dimensionality::<Ix4>() } else { v.insert_axis(Axis(0)).into_dimensionality::<Ix4>() }.map_err(err)?;
    // the pixels with a tap at the clip level, [B, H, W]: no range and no lifetime there
    let unread = match clip_level {
        Some(l) if l.is_finite() && l > 0.0 => Some(tcsense_sensor::measure::at_clip_level(&v, l)),
        Some(l) => return Err(err(format!("clip_level {l}: expected a positive level in the tap images' units"))),
        None => None,
    };
    let mut out = run_long(py, |cancel| {
        let mut d = decoder.lock().unwrap_or_else(|e| e.into_inner());
        decode_batch(d.as_mut(), &sensor.inner, v, &Control::quiet(cancel))
    })?
    .map_err(err)?;
    if let Some(u) = &unread {
        out.without_pixels(&u.view());
    }
    decoded_dict(py, out, batched)
}

#[pymethods]
impl PyDecoder {
    /// Decode tap images `y` (`[M, H, W]` or `[B, M, H, W]`, float32) with `sensor` (default:
    /// the decoder's own, for runs and ONNX models). Returns a dict of the arrays the decoder
    /// gives: `cube [T, H, W]`, `depth` and `confidence [K, H, W]` (m), `lifetime [4, H, W]`
    /// (τ_m, τ₁, τ₂ in s, α₁) with `confidence` and `intensity [1, H, W]` — with a leading batch
    /// axis when `y` had one. With `clip_level` (what a tap clipped at the full well reads),
    /// the pixels with a tap at it get no range and no lifetime. Runs with the GIL released;
    /// Ctrl-C stops it.
    #[pyo3(signature = (y, sensor = None, *, clip_level = None))]
    fn decode<'py>(
        &self,
        py: Python<'py>,
        y: &Bound<'py, PyAny>,
        sensor: Option<&Bound<'py, PySensor>>,
        clip_level: Option<f32>,
    ) -> PyResult<Bound<'py, PyDict>> {
        let own = self.sensor.as_ref().map(|s| s.bind(py).clone());
        let Some(s) = sensor.cloned().or(own) else {
            return Err(err(format!("{}: give the sensor the measurements come from: decode(y, sensor)", self.label)));
        };
        let s = s.get();
        let trained = self.sensor.as_ref().map(|t| t.get().inner.codes());
        check_codes(&self.label, trained, &s.inner).map_err(err)?;
        decode_with(py, &self.inner, s, y, clip_level)
    }

    /// `tval3`, `lifetime-fit`, `admm-net`, `unet`, `lifetime` or `onnx`.
    #[getter]
    fn kind(&self) -> &str {
        &self.kind
    }
    /// How it was opened (`admm-net:RUN`, `zoo:NAME`, `onnx:FILE`, `tval3`).
    #[getter]
    fn label(&self) -> &str {
        &self.label
    }
    /// The codes it was trained with (None for TVAL3 and the fit).
    #[getter]
    fn codes(&self) -> Option<PyCodes> {
        self.sensor.as_ref().map(|s| PyCodes { inner: s.get().inner.codes().clone() })
    }
    /// The sensor it decodes with by default (None for TVAL3 and the fit).
    #[getter]
    fn sensor<'py>(&self, py: Python<'py>) -> Option<Bound<'py, PySensor>> {
        self.sensor.as_ref().map(|s| s.bind(py).clone())
    }
    /// The run directory (None unless opened from a run).
    #[getter]
    fn run(&self) -> Option<PathBuf> {
        self.run.clone()
    }

    fn __repr__(&self) -> String {
        format!("Decoder({:?}, kind={:?})", self.label, self.kind)
    }
}

/// Open a trained run directory (or `zoo:NAME`) as a decoder, with its codes and sensor;
/// `calibration` (a `tcsense calibrate` directory) makes it decode a calibrated sensor's raw
/// frames (`tcsense reconstruct … --calibration`).
#[pyfunction]
#[pyo3(signature = (run, *, calibration = None))]
fn open_run(py: Python<'_>, run: &Bound<'_, PyAny>, calibration: Option<&Bound<'_, PyAny>>) -> PyResult<PyDecoder> {
    let spec: String = path_of(run)?.to_string_lossy().into_owned();
    let dir = zoo::resolve(&spec).map_err(err)?;
    existing(&dir, "run")?;
    let cal = calibration.map(path_of).transpose()?;
    if let Some(d) = &cal {
        existing(d, "calibration")?;
    }
    let r = run_long(py, |_| runs::open(&dir, &Device::flex()))?.map_err(err)?;
    let kind = r.spec.model.name().to_string();
    let sensor = match &cal {
        Some(d) => r.sensor.calibrated_from(d).map_err(err)?,
        None => r.sensor,
    };
    Ok(PyDecoder { label: spec, kind, inner: Mutex::new(r.decoder), sensor: Some(Py::new(py, PySensor::of(sensor))?), run: Some(r.dir) })
}

/// Open a decoder by its command-line name: `tval3`, `lifetime-fit`, `depth-fit`, `admm-net:RUN`,
/// `unet:RUN`, `lifetime:RUN`, `zoo:NAME` or `onnx:MODEL.onnx` (through ONNX Runtime); a
/// decoder of cubes followed by `+fit` also gives `depth`, the cube's peaks refined in the tap
/// domain (`tval3+fit`, `zoo:admm-lidar-delay+fit`). `tval3` takes TVAL3's settings as keyword arguments (`mu`, `beta`, `maxit`, `tol`, …).
/// `onset_ns`: the decays' onset when known (a calibration), for `lifetime-fit`,
/// `lifetime-fit-pooled` and a lifetime network on the fit's evidence (`lifetime:RUN`,
/// `zoo:NAME`), which then fit only the IRF's width; any other decoder refuses it.
#[pyfunction(name = "open_decoder")]
#[pyo3(signature = (name, *, onset_ns=None, **tval3))]
fn open_decoder_py(py: Python<'_>, name: &str, onset_ns: Option<f64>, tval3: Option<&Bound<'_, PyDict>>) -> PyResult<PyDecoder> {
    let opts: Tval3Options = merged(&Tval3Options::default(), tval3, "tval3 settings")?;
    let tap_fit = TapFitOptions { onset_s: onset_ns.map(|t| t * 1e-9), ..Default::default() };
    let settings = DecoderSettings { tval3: opts, tap_fit, ..Default::default() };
    // `NAME+fit`: the decoder NAME (its kind, codes and sensor) with its ranges refined
    let base = name.strip_suffix("+fit").unwrap_or(name);
    if let Some(("onnx", file)) = base.split_once(':') {
        existing(std::path::Path::new(file), "onnx model")?;
    }
    let d = run_long(py, |_| Registry::builtin().open(name, &settings, &Device::flex()))?.map_err(err)?;
    // the kind: the network of a run or model, else the name (`tval3`, `lifetime-fit`, `depth-fit`)
    let kind = match base.split_once(':') {
        None => base.to_string(),
        Some(("onnx", _)) => "onnx".to_string(),
        Some(("depth-fit", _)) => "depth-fit".to_string(),
        Some(_) => d.decoder.name().trim_end_matches("+fit").to_string(),
    };
    let run = match base.split_once(':') {
        Some(("onnx" | "depth-fit", _)) | None => None,
        Some((_, dir)) => Some(zoo::resolve(if base.starts_with("zoo:") { base } else { dir }).map_err(err)?),
    };
    let sensor = d.sensor.map(|s| Py::new(py, PySensor::of(s))).transpose()?;
    Ok(PyDecoder { label: name.into(), kind, inner: Mutex::new(d.decoder), sensor, run })
}

/// TVAL3 (`tcsense reconstruct tval3`): y `[M, H, W]` or `[B, M, H, W]` → cube `[T, H, W]` or
/// `[B, T, H, W]`. Settings as keyword arguments (`mu`, `beta`, `maxit`, `tol`, `nonneg`, …).
#[pyfunction]
#[pyo3(signature = (y, sensor, **options))]
fn tval3<'py>(
    py: Python<'py>,
    y: &Bound<'py, PyAny>,
    sensor: &Bound<'py, PySensor>,
    options: Option<&Bound<'py, PyDict>>,
) -> PyResult<Bound<'py, PyAny>> {
    let opts: Tval3Options = merged(&Tval3Options::default(), options, "tval3 settings")?;
    let dec: Mutex<Box<dyn Decoder>> = Mutex::new(Box::new(Tval3Decoder::new(opts).map_err(err)?));
    let d = decode_with(py, &dec, sensor.get(), y, None)?;
    d.get_item("cube")?.ok_or_else(|| err("tval3 gave no cube"))
}

/// Lifetimes fitted to the tap images directly (`tcsense reconstruct lifetime-fit`): y
/// `[M, H, W]` or `[B, M, H, W]` → dict `lifetime [4, H, W]` (τ_m, τ₁, τ₂ in s, α₁),
/// `confidence`, `intensity [1, H, W]`; no lifetime where a tap reads `clip_level`.
#[pyfunction]
#[pyo3(signature = (y, sensor, *, clip_level = None))]
fn lifetime_fit<'py>(
    py: Python<'py>,
    y: &Bound<'py, PyAny>,
    sensor: &Bound<'py, PySensor>,
    clip_level: Option<f32>,
) -> PyResult<Bound<'py, PyDict>> {
    let dec: Mutex<Box<dyn Decoder>> = Mutex::new(Box::new(TapFitDecoder::new(TapFitOptions::default()).map_err(err)?));
    decode_with(py, &dec, sensor.get(), y, clip_level)
}

/// The zoo's entries as dicts: name, dir, decoder, domain, learned_codes, codes, epochs,
/// validation metrics, title, weights_bytes (`tcsense zoo list`).
#[pyfunction]
fn zoo_list<'py>(py: Python<'py>) -> PyResult<Bound<'py, PyList>> {
    let out = PyList::empty(py);
    for e in zoo::list().map_err(err)? {
        let d = PyDict::new(py);
        d.set_item("name", &e.name)?;
        d.set_item("dir", &e.dir)?;
        d.set_item("decoder", e.model.name())?;
        d.set_item("domain", e.domain)?;
        d.set_item("learned_codes", e.learned_codes)?;
        d.set_item("codes", &e.codes)?;
        d.set_item("epochs", e.epochs)?;
        let val = PyDict::new(py);
        for (k, v) in &e.validation {
            val.set_item(k, v)?;
        }
        d.set_item("validation", val)?;
        d.set_item("title", &e.title)?;
        d.set_item("weights_bytes", e.weights_bytes)?;
        out.append(d)?;
    }
    Ok(out)
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PyDecoder>()?;
    m.add_function(wrap_pyfunction!(open_run, m)?)?;
    m.add_function(wrap_pyfunction!(open_decoder_py, m)?)?;
    m.add_function(wrap_pyfunction!(tval3, m)?)?;
    m.add_function(wrap_pyfunction!(lifetime_fit, m)?)?;
    m.add_function(wrap_pyfunction!(zoo_list, m)?)?;
    Ok(())
}
