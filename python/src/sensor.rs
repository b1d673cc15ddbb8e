//! `tcsense.Sensor`: the measurement model `y = A x` of a code set (IRF, sampling, an optional
//! calibration), its adjoint, and `measure` (noise and non-idealities).

use std::sync::{Arc, Mutex};

use ndarray::{ArrayD, Axis, Ix3, Ix4};
use numpy::{IntoPyArray, PyArray3, PyArrayDyn, PyReadwriteArrayDyn, PyUntypedArrayMethods};
use pyo3::prelude::*;
use pyo3::types::PyDict;
use std::path::PathBuf;
use tcsense_sensor::noise::Exposure;
use tcsense_sensor::nonideal::NonIdeal;
use tcsense_sensor::npy::{ensure_finite, write_npy};
use tcsense_sensor::params::{DEFAULT_LASER_FWHM_S, DEFAULT_TAP_TAU_S};
use tcsense_sensor::{Codes, FramePlan, Irf, MeasurementMatrix, NoiseParams, Sampling, Sensor, SensorModel, SensorParams, Units};

use crate::codes::{codes_of, PyCodes};
use crate::{check_rank, err, existing, f32_array, merged, path_of, to_python};

/// The crate's [`Sensor`] (codes, spec, nominal `A [N, M, T]`, a calibration when one was
/// given), with the name its IRF was given under and a cached plan.
#[pyclass(name = "Sensor", module = "tcsense", frozen)]
pub struct PySensor {
    pub inner: Sensor,
    irf_label: String,
    /// The last frame size's plan (forward/adjoint coefficients), reused while the size stays.
    plan: Mutex<Option<Arc<FramePlan>>>,
}

impl PySensor {
    pub fn new(inner: Sensor, irf_label: String) -> Self {
        PySensor { inner, irf_label, plan: Mutex::new(None) }
    }

    /// The label of a sensor's IRF: `ideal` or `physical`.
    pub fn of(inner: Sensor) -> Self {
        let label = match inner.spec().irf() {
            Irf::Ideal => "ideal",
            Irf::Physical { .. } => "physical",
        };
        PySensor::new(inner, label.into())
    }

    /// The matrix the sensor decodes with: the calibration's, else the nominal one.
    pub fn matrix_ref(&self) -> &MeasurementMatrix {
        self.inner.matrix()
    }

    /// The plan for `h × w` frames, cached while the size stays the same.
    pub fn plan(&self, h: usize, w: usize) -> PyResult<Arc<FramePlan>> {
        let mut cached = self.plan.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(p) = cached.as_ref().filter(|p| p.height() == h && p.width() == w) {
            return Ok(p.clone());
        }
        let p = Arc::new(self.matrix_ref().plan(h, w).map_err(err)?);
        *cached = Some(p.clone());
        Ok(p)
    }

    /// `forward` and `adjoint` alike: `op` applied frame by frame with the GIL released, into
    /// `out` (checked to be `[C, H, W]` or `[B, C, H, W]`, `C = channels(plan)`) or a new array.
    #[allow(clippy::too_many_arguments)]
    fn apply<'py>(
        &self,
        py: Python<'py>,
        input: &Bound<'py, PyAny>,
        out: Option<&Bound<'py, PyAny>>,
        name: &str,
        axes: &str,
        channels: fn(&FramePlan) -> usize,
        op: fn(&FramePlan, &ndarray::ArrayView3<'_, f32>, &mut ndarray::ArrayViewMut3<'_, f32>) -> tcsense_sensor::Result<()>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let arr = f32_array(input, name)?;
        let (batched, v) = batch_view(&arr, name, axes)?;
        let (b, _, h, w) = v.dim();
        let plan = self.plan(h, w)?;
        let run = |dst: &mut ndarray::ArrayViewMut4<'_, f32>| -> tcsense_sensor::Result<()> {
            for (src, mut d) in v.outer_iter().zip(dst.outer_iter_mut()) {
                op(&plan, &src, &mut d)?;
            }
            Ok(())
        };
        let c = channels(&plan);
        if let Some(o) = out {
            into_out(py, o, &out_shape(batched, b, c, h, w), run)?;
            return Ok(o.clone());
        }
        let mut fresh = ndarray::Array4::<f32>::zeros((b, c, h, w));
        py.detach(|| run(&mut fresh.view_mut())).map_err(err)?;
        Ok(unbatch(batched, fresh).into_pyarray(py).into_any())
    }
}

/// `Sensor(…)`'s `irf`: a name, a path to `A.npy`, or an array.
enum IrfArg {
    Named(Irf, String),
    File(std::path::PathBuf),
    Array(ndarray::Array3<f32>),
}

fn irf_arg(obj: &Bound<'_, PyAny>, laser_fwhm_ns: f64, tap_tau_ns: f64) -> PyResult<IrfArg> {
    if let Ok(s) = obj.extract::<String>() {
        return match tcsense_sensor::waveform::parse_irf(&s, laser_fwhm_ns * 1e-9, tap_tau_ns * 1e-9, "irf") {
            Ok(tcsense_sensor::waveform::IrfSpec::Model(irf)) => Ok(IrfArg::Named(irf, s)),
            Ok(tcsense_sensor::waveform::IrfSpec::Measured(p)) => Ok(IrfArg::File(p)),
            Err(_) => Err(err(format!("irf {s:?}: expected {} or an array [N, M, T]", tcsense_sensor::waveform::IRF_CHOICES))),
        };
    }
    if obj.cast::<numpy::PyUntypedArray>().is_ok() {
        let a = f32_array(obj, "irf")?;
        check_rank(a.shape(), &[3], "irf", "a measured matrix A [N, M, T]")?;
        return Ok(IrfArg::Array(a.as_array().into_dimensionality::<Ix3>().map_err(err)?.to_owned()));
    }
    let p = path_of(obj).map_err(|_| {
        pyo3::exceptions::PyTypeError::new_err("irf: expected \"ideal\", \"physical\", a path to A.npy or a float32 array [N, M, T]")
    })?;
    Ok(IrfArg::File(p))
}

/// The sensor of `codes` under these settings (what `--irf`, `--oversample`, `--heterodyne`,
/// `--laser-fwhm-ns`, `--tap-tau-ns` and `--calibration` give on the command line).
pub fn build(
    codes: Codes,
    irf: IrfArgOwned,
    oversample: Option<usize>,
    heterodyne: Option<usize>,
    calibration: Option<PathBuf>,
) -> PyResult<PySensor> {
    let sampling = Sampling::from_factors(oversample, heterodyne, Sampling::Oversample(1)).map_err(err)?;
    if let Some(d) = &calibration {
        existing(d, "calibration")?;
    }
    let model = |irf: Irf, measured: Option<PathBuf>| SensorModel {
        sampling,
        irf,
        measured,
        calibration: calibration.clone(),
        ..Default::default()
    };
    let (sensor, label) = match irf.0 {
        IrfArg::Named(i, label) => (Sensor::build(codes, &model(i, None)), label),
        IrfArg::File(p) => {
            existing(&p, "irf")?;
            let label = p.display().to_string();
            (Sensor::build(codes, &model(Irf::Ideal, Some(p))), label)
        }
        IrfArg::Array(a) => {
            let spec = SensorParams { sampling, ..SensorParams::from_codes(&codes) }.validate().map_err(err)?;
            let nominal = MeasurementMatrix::from_array(a, &spec).map_err(err)?;
            let s = Sensor::with_matrix(codes, spec, nominal).and_then(|s| match &calibration {
                Some(d) => s.calibrated_from(d),
                None => Ok(s),
            });
            (s, "array".to_string())
        }
    };
    Ok(PySensor::new(sensor.map_err(err)?, label))
}

/// An `irf` argument resolved (kept opaque outside this module).
pub struct IrfArgOwned(IrfArg);

impl IrfArgOwned {
    pub fn parse(obj: &Bound<'_, PyAny>, laser_fwhm_ns: f64, tap_tau_ns: f64) -> PyResult<Self> {
        Ok(IrfArgOwned(irf_arg(obj, laser_fwhm_ns, tap_tau_ns)?))
    }
}

/// `[T, H, W]` or `[B, T, H, W]` (or taps) as a batch view, and whether it was batched.
fn batch_view<'a>(a: &'a numpy::PyReadonlyArrayDyn<'_, f32>, name: &str, axes: &str) -> PyResult<(bool, ndarray::ArrayView4<'a, f32>)> {
    check_rank(a.shape(), &[3, 4], name, axes)?;
    let v = a.as_array();
    let batched = v.ndim() == 4;
    let v = if batched { v.into_dimensionality::<Ix4>() } else { v.insert_axis(Axis(0)).into_dimensionality::<Ix4>() };
    Ok((batched, v.map_err(err)?))
}

/// The shape of an operator's output, `[C, H, W]` or `[B, C, H, W]`.
fn out_shape(batched: bool, b: usize, c: usize, h: usize, w: usize) -> Vec<usize> {
    if batched {
        vec![b, c, h, w]
    } else {
        vec![c, h, w]
    }
}

/// Write into the caller's float32 array `out` of shape `want` (checked) with the GIL
/// released: `f` gets it as `[B, C, H, W]`.
fn into_out(
    py: Python<'_>,
    out: &Bound<'_, PyAny>,
    want: &[usize],
    f: impl FnOnce(&mut ndarray::ArrayViewMut4<'_, f32>) -> tcsense_sensor::Result<()> + Send,
) -> PyResult<()> {
    f32_array(out, "out")?;
    let mut rw: PyReadwriteArrayDyn<'_, f32> = out.extract().map_err(|e| err(format!("out: {e}")))?;
    if rw.shape() != want {
        return Err(err(format!("out: shape {:?}; expected {want:?}", rw.shape())));
    }
    let view = rw.as_array_mut();
    let mut v4 = if want.len() == 4 { view.into_dimensionality::<Ix4>() } else { view.insert_axis(Axis(0)).into_dimensionality::<Ix4>() }
        .map_err(err)?;
    py.detach(|| f(&mut v4)).map_err(err)
}

fn unbatch(batched: bool, a: ndarray::Array4<f32>) -> ArrayD<f32> {
    if batched {
        a.into_dyn()
    } else {
        a.index_axis_move(Axis(0), 0).into_dyn()
    }
}

#[pymethods]
impl PySensor {
    /// The sensor of `codes` (a `Codes` or a codes JSON path): `irf` "ideal" (rectangular
    /// gates), "physical" (laser pulse ⋆ tap response) or a measured `A [N, M, T]` (array or
    /// `.npy`); `oversample` or `heterodyne` K (T = L·K); `calibration`, a directory written by
    /// `tcsense calibrate` (its matrix replaces the nominal one; `correct` applies its dark
    /// and gain maps).
    #[new]
    #[pyo3(signature = (codes, irf = None, *, oversample = None, heterodyne = None, laser_fwhm_ns = DEFAULT_LASER_FWHM_S * 1e9, tap_tau_ns = DEFAULT_TAP_TAU_S * 1e9, calibration = None))]
    fn py_new(
        codes: &Bound<'_, PyAny>,
        irf: Option<&Bound<'_, PyAny>>,
        oversample: Option<usize>,
        heterodyne: Option<usize>,
        laser_fwhm_ns: f64,
        tap_tau_ns: f64,
        calibration: Option<&Bound<'_, PyAny>>,
    ) -> PyResult<Self> {
        let codes = codes_of(codes)?;
        let irf = match irf {
            Some(i) => IrfArgOwned::parse(i, laser_fwhm_ns, tap_tau_ns)?,
            None => IrfArgOwned(IrfArg::Named(Irf::Ideal, "ideal".into())),
        };
        build(codes, irf, oversample, heterodyne, calibration.map(path_of).transpose()?)
    }

    /// `y = A x`: x `[T, H, W]` or `[B, T, H, W]` → y `[M, H, W]` or `[B, M, H, W]`. With
    /// `out` (a float32 array of y's shape) the result is written into it and `out` returned:
    /// no allocation, for loops over many frames.
    #[pyo3(signature = (x, out = None))]
    fn forward<'py>(&self, py: Python<'py>, x: &Bound<'py, PyAny>, out: Option<&Bound<'py, PyAny>>) -> PyResult<Bound<'py, PyAny>> {
        self.apply(py, x, out, "x", "[T, H, W] or [B, T, H, W]", FramePlan::taps, FramePlan::forward_into)
    }

    /// `x = Aᵀ y`: y `[M, H, W]` or `[B, M, H, W]` → x `[T, H, W]` or `[B, T, H, W]`; `out` as
    /// for `forward`.
    #[pyo3(signature = (y, out = None))]
    fn adjoint<'py>(&self, py: Python<'py>, y: &Bound<'py, PyAny>, out: Option<&Bound<'py, PyAny>>) -> PyResult<Bound<'py, PyAny>> {
        self.apply(py, y, out, "y", "[M, H, W] or [B, M, H, W]", FramePlan::bins, FramePlan::adjoint_into)
    }

    /// What the sensor reads out (`tcsense simulate`): `A x`, with `noise` shot and read noise,
    /// full-well clipping and ADC quantisation, seeded; `nonideal` a dict of the real sensor's
    /// non-idealities (`tap_gain`, `prnu`, `dark`, `dark_fpn`, `crosstalk`, `tail`,
    /// `tail_tau_s`, `shift_s`, `gate_skew_s`, `modulation_contrast`, `nonlinearity`, `seed`). `units`: "input" (units of A x), "electrons" or "adc".
    /// x `[T, H, W]` or `[B, T, H, W]` → y `[M, H, W]` or `[B, M, H, W]`.
    #[pyo3(signature = (x, noise = true, seed = 0, *, full_well = 20_000.0, read_noise = 40.0, signal_fraction = 0.8, adc_bits = 12, electrons_per_unit = None, units = "input", nonideal = None))]
    #[allow(clippy::too_many_arguments)]
    fn measure<'py>(
        &self,
        py: Python<'py>,
        x: &Bound<'py, PyAny>,
        noise: bool,
        seed: u64,
        full_well: f64,
        read_noise: f64,
        signal_fraction: f64,
        adc_bits: u32,
        electrons_per_unit: Option<f64>,
        units: &str,
        nonideal: Option<&Bound<'py, PyDict>>,
    ) -> PyResult<Bound<'py, PyArrayDyn<f32>>> {
        let params = NoiseParams { full_well_e: full_well, read_noise_e: read_noise, signal_fraction, adc_bits }.validate().map_err(err)?;
        let units = Units::parse(units).map_err(err)?;
        let ni: NonIdeal = merged(&NonIdeal::default(), nonideal, "nonideal")?;
        let real = self.inner.clone().with_nonideal(ni).map_err(|e| err(format!("nonideal: {e}")))?;
        let arr = f32_array(x, "x")?;
        check_rank(arr.shape(), &[3, 4], "x", "[T, H, W] or [B, T, H, W]")?;
        let v = arr.as_array();
        ensure_finite(&v, "x").map_err(err)?;
        let exposure = match electrons_per_unit {
            Some(s) => Exposure::ElectronsPerUnit(s),
            None => Exposure::Auto,
        };
        let measured = py.detach(|| real.measure(&v, &params, noise, exposure, seed)).map_err(err)?;
        Ok(measured.in_units(units, &params).into_pyarray(py))
    }

    /// `(y − d) / G`: raw tap images of a calibrated sensor corrected by its dark and gain maps.
    /// y `[M, H, W]` or `[B, M, H, W]`, in the sweep's units.
    fn correct<'py>(&self, py: Python<'py>, y: &Bound<'py, PyAny>) -> PyResult<Bound<'py, PyArrayDyn<f32>>> {
        if self.inner.calibration().is_none() {
            return Err(err("correct: this sensor has no calibration; pass calibration=DIR to Sensor(…)"));
        }
        let arr = f32_array(y, "y")?;
        let (batched, v) = batch_view(&arr, "y", "[M, H, W] or [B, M, H, W]")?;
        Ok(unbatch(batched, self.inner.correct(v).map_err(err)?).into_pyarray(py))
    }

    /// Write `y` to `path` (.npy) with its sidecar (`NAME.meta.json` beside it), which names this
    /// sensor, the noise settings and the units, as `tcsense simulate` does.
    #[pyo3(signature = (path, y, *, noise = None, seed = None, units = "input"))]
    fn save_measurements(
        &self,
        path: &Bound<'_, PyAny>,
        y: &Bound<'_, PyAny>,
        noise: Option<&Bound<'_, PyDict>>,
        seed: Option<u64>,
        units: &str,
    ) -> PyResult<()> {
        let p = path_of(path)?;
        let arr = f32_array(y, "y")?;
        check_rank(arr.shape(), &[3, 4], "y", "[M, H, W] or [B, M, H, W]")?;
        let noise = noise.map(|d| merged(&NoiseParams::default(), Some(d), "noise")).transpose()?;
        let sidecar = self.inner.sidecar(noise, seed, units);
        write_npy(&p, &arr.as_array()).map_err(err)?;
        sidecar.write_for(&p).map_err(err)?;
        Ok(())
    }

    /// Read tap images from `path` (.npy, `[M, H, W]` or `[B, M, H, W]`), checked against their
    /// sidecar when there is one (the codes, sampling and matrix must be this sensor's; with a
    /// calibration, the units must be the sweep's) — the rules of `tcsense reconstruct`.
    fn load_measurements<'py>(&self, py: Python<'py>, path: &Bound<'py, PyAny>) -> PyResult<Bound<'py, PyArrayDyn<f32>>> {
        let p = path_of(path)?;
        existing(&p, "path")?;
        let (batched, y) = tcsense_infer::decode::read_measurements(&p, &self.inner).map_err(err)?;
        Ok(unbatch(batched, y).into_pyarray(py))
    }

    /// The matrix it decodes with, `A [N, M, T]` (the calibration's when calibrated).
    fn matrix<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray3<f32>> {
        self.matrix_ref().a().to_owned().into_pyarray(py)
    }

    /// The nominal (synthesised or given) `A [N, M, T]`.
    fn nominal_matrix<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray3<f32>> {
        self.inner.nominal().a().to_owned().into_pyarray(py)
    }

    #[getter]
    fn codes(&self) -> PyCodes {
        PyCodes { inner: self.inner.codes().clone() }
    }
    #[getter]
    fn taps(&self) -> usize {
        self.inner.taps()
    }
    #[getter]
    fn bins(&self) -> usize {
        self.inner.bins()
    }
    #[getter]
    fn subpixels(&self) -> usize {
        self.inner.spec().subpixels()
    }
    #[getter]
    fn block(&self) -> (usize, usize) {
        self.inner.block()
    }
    /// Width of one time bin (s).
    #[getter]
    fn bin_width_s(&self) -> f64 {
        self.inner.bin_width_s()
    }
    /// One code cycle (s).
    #[getter]
    fn cycle_s(&self) -> f64 {
        self.inner.spec().cycle_s()
    }
    /// `("oversample" | "heterodyne", K)`.
    #[getter]
    fn sampling(&self) -> (&'static str, usize) {
        match self.inner.spec().sampling() {
            Sampling::Oversample(k) => ("oversample", k),
            Sampling::Heterodyne(k) => ("heterodyne", k),
        }
    }
    #[getter]
    fn irf(&self) -> String {
        self.irf_label.clone()
    }
    /// The calibration's `calibration.json` as a dict (None when not calibrated).
    #[getter]
    fn calibration<'py>(&self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyAny>>> {
        self.inner.calibration().map(|c| to_python(py, &serde_json::to_value(&c.meta).map_err(err)?)).transpose()
    }

    fn __repr__(&self) -> String {
        let (s, k) = self.sampling();
        format!(
            "Sensor(taps={}, block={:?}, bins={}, {s}={k}, irf={:?}, bin_width={:.1} ps{})",
            self.taps(),
            self.block(),
            self.bins(),
            self.irf_label,
            self.bin_width_s() * 1e12,
            if self.inner.calibration().is_some() { ", calibrated" } else { "" }
        )
    }
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PySensor>()
}
