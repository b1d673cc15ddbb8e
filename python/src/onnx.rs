//! ONNX: export a trained run (with a calibration built in, optionally) and run exported
//! models through ONNX Runtime (the library of the `onnxruntime` wheel, found by the package).

use std::path::Path;
use std::sync::Mutex;

use ndarray::{Axis, Ix4};
use numpy::{IntoPyArray, PyUntypedArrayMethods};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};
use tcsense_infer::onnx::{export_to, ExportOptions};
use tcsense_infer::runtime::OnnxModel;
use tcsense_models::{runs, zoo, Device};

use crate::codes::PyCodes;
use crate::{check_rank, err, existing, f32_array, path_of, run_long};

pub fn open_model(path: &Path, threads: usize) -> PyResult<OnnxModel> {
    existing(path, "model")?;
    OnnxModel::open(path, threads).map_err(err)
}

/// Export a trained run (a directory or `zoo:NAME`) to an ONNX file (opset 17, IR 9):
/// `matrix_input` takes the sensor matrix as a second input; `calibration` (a `tcsense
/// calibrate` directory) builds its dark and gain correction and measured matrix into the
/// graph; `from_taps` writes a U-Net on the range fit's evidence as one graph from the tap
/// images (`tcsense export onnx --from-taps`). Returns the bytes written (`tcsense export onnx`).
#[pyfunction]
#[pyo3(signature = (run, out, *, matrix_input = false, calibration = None, from_taps = false))]
fn export_onnx(
    py: Python<'_>,
    run: &Bound<'_, PyAny>,
    out: &Bound<'_, PyAny>,
    matrix_input: bool,
    calibration: Option<&Bound<'_, PyAny>>,
    from_taps: bool,
) -> PyResult<usize> {
    let spec = path_of(run)?.to_string_lossy().into_owned();
    let dir = zoo::resolve(&spec).map_err(err)?;
    existing(&dir, "run")?;
    let out = path_of(out)?;
    let cal_dir = calibration.map(path_of).transpose()?;
    if let Some(d) = &cal_dir {
        existing(d, "calibration")?;
    }
    run_long(py, |_| -> PyResult<usize> {
        let loaded = runs::load(&dir, &Device::flex()).map_err(err)?;
        let calibrated = cal_dir.as_ref().map(|d| loaded.sensor.clone().calibrated_from(d)).transpose().map_err(err)?;
        let cal = calibrated.as_ref().and_then(|s| s.calibration()).cloned();
        export_to(&loaded, ExportOptions { matrix_input, calibration: cal.as_ref(), from_taps }, &out).map_err(err)
    })?
}

/// The version of the ONNX Runtime library in use (loads it).
#[pyfunction]
fn onnxruntime_version() -> PyResult<String> {
    tcsense_infer::runtime::runtime_version().map_err(err)
}

/// An exported model opened in ONNX Runtime with `threads` intra-op threads (0: one per core).
#[pyclass(name = "OnnxModel", module = "tcsense", frozen)]
pub struct PyOnnxModel {
    inner: Mutex<OnnxModel>,
}

#[pymethods]
impl PyOnnxModel {
    #[new]
    #[pyo3(signature = (path, threads = 0))]
    fn py_new(path: &Bound<'_, PyAny>, threads: usize) -> PyResult<Self> {
        Ok(PyOnnxModel { inner: Mutex::new(open_model(&path_of(path)?, threads)?) })
    }

    /// The model's raw outputs for tap images `y [B, M, H, W]` (or `[M, H, W]`): a list of
    /// arrays `[B, C, H, W]` in the order of `outputs` (checked against the metadata first).
    fn run<'py>(&self, py: Python<'py>, y: &Bound<'py, PyAny>) -> PyResult<Bound<'py, PyList>> {
        let arr = f32_array(y, "y")?;
        check_rank(arr.shape(), &[3, 4], "y", "[M, H, W] or [B, M, H, W]")?;
        let v = arr.as_array();
        let v = if v.ndim() == 4 { v.into_dimensionality::<Ix4>() } else { v.insert_axis(Axis(0)).into_dimensionality::<Ix4>() }
            .map_err(err)?;
        let outs = run_long(py, |_| self.inner.lock().unwrap_or_else(|e| e.into_inner()).run(v))?.map_err(err)?;
        let list = PyList::empty(py);
        for o in outs {
            list.append(o.into_pyarray(py))?;
        }
        Ok(list)
    }

    /// Output names, in the order `run` returns them.
    #[getter]
    fn outputs(&self) -> Vec<String> {
        self.inner.lock().unwrap_or_else(|e| e.into_inner()).meta.outputs().iter().map(|s| s.to_string()).collect()
    }

    /// The tcsense metadata: decoder, taps, bins, block, frame multiple, returns, range, bin
    /// width, clock, sampling, whether the matrix is an input, the calibration's size.
    #[getter]
    fn metadata<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let m = &self.inner.lock().unwrap_or_else(|e| e.into_inner()).meta;
        let d = PyDict::new(py);
        d.set_item("decoder", &m.decoder)?;
        d.set_item("taps", m.taps)?;
        d.set_item("bins", m.bins)?;
        d.set_item("block", m.block)?;
        d.set_item("frame_multiple", m.frame_multiple)?;
        d.set_item("returns", m.returns)?;
        d.set_item("range_m", m.range_m)?;
        d.set_item("bin_s", m.bin_s)?;
        d.set_item("clock_hz", m.clock_hz)?;
        d.set_item("sampling", format!("{:?}", m.sampling))?;
        d.set_item("matrix_input", m.matrix_input)?;
        d.set_item("calibration_size", m.calibration.as_ref().map(|c| c.size))?;
        d.set_item("refined_in_graph", m.refined_in_graph)?;
        Ok(d)
    }

    /// The codes in the metadata.
    #[getter]
    fn codes(&self) -> PyCodes {
        PyCodes { inner: self.inner.lock().unwrap_or_else(|e| e.into_inner()).meta.codes.clone() }
    }
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PyOnnxModel>()?;
    m.add_function(wrap_pyfunction!(export_onnx, m)?)?;
    m.add_function(wrap_pyfunction!(onnxruntime_version, m)?)?;
    Ok(())
}
