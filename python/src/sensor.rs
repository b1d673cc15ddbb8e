//! `tcsense.Sensor`: the measurement model `y = A x` of a code set (IRF, sampling, an optional
//! calibration), its adjoint, and `measure` (noise and non-idealities).

use std::sync::{Arc, Mutex};

use ndarray::{ArrayD, Axis, Ix3, Ix4};
use numpy::{IntoPyArray, PyArray3, PyArrayDyn, PyReadwriteArrayDyn, PyUntypedArrayMethods};
use pyo3::prelude::*;
use pyo3::types::PyDict;
use tcsense_sensor::calibration::{check_measurements_file, Calibration};
use tcsense_sensor::measure::{measure, Measurement};
use tcsense_sensor::noise::Exposure;
use tcsense_sensor::nonideal::NonIdeal;
use tcsense_sensor::npy::{ensure_finite, read_npy, write_npy};
use tcsense_sensor::params::{DEFAULT_LASER_FWHM_S, DEFAULT_TAP_TAU_S};
use tcsense_sensor::sidecar::Sidecar;
use tcsense_sensor::{Codes, FramePlan, Irf, MeasurementMatrix, NoiseParams, Sampling, SensorParams, SensorSpec};

use crate::codes::{codes_of, PyCodes};
use crate::{check_rank, err, existing, f32_array, merged, path_of, to_python};

/// The sensor as a decoder knows it: codes, the checked spec, the nominal `A [N, M, T]`, and a
/// calibration (measured `A`, dark and gain maps) when one was given.
#[pyclass(name = "Sensor", module = "tcsense", frozen)]
pub struct PySensor {
    pub codes: Codes,
    pub spec: SensorSpec,
    pub nominal: MeasurementMatrix,
    pub calibration: Option<Calibration>,
    irf_label: String,
    /// The last frame size's plan (forward/adjoint coefficients), reused while the size stays.
    plan: Mutex<Option<Arc<FramePlan>>>,
}

impl PySensor {
    pub fn new(codes: Codes, spec: SensorSpec, nominal: MeasurementMatrix, calibration: Option<Calibration>, irf_label: String) -> Self {
        PySensor { codes, spec, nominal, calibration, irf_label, plan: Mutex::new(None) }
    }

    /// The matrix the sensor decodes with: the calibration's, else the nominal one.
    pub fn matrix_ref(&self) -> &MeasurementMatrix {
        self.calibration.as_ref().map_or(&self.nominal, |c| &c.matrix)
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

    /// `(y − d) / G` of a calibrated sensor; `y` as is otherwise.
    ///
    /// # Shapes
    /// - `y`: `[B, M, H, W]`
    pub fn corrected(&self, y: ndarray::ArrayView4<'_, f32>) -> PyResult<ndarray::Array4<f32>> {
        match &self.calibration {
            Some(c) => c.correct(&y).map_err(err),
            None => Ok(y.to_owned()),
        }
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
        return match s.as_str() {
            "ideal" => Ok(IrfArg::Named(Irf::Ideal, s)),
            "physical" => Ok(IrfArg::Named(Irf::Physical { laser_fwhm_s: laser_fwhm_ns * 1e-9, tap_tau_s: tap_tau_ns * 1e-9 }, s)),
            p if p.ends_with(".npy") => Ok(IrfArg::File(p.into())),
            other => Err(err(format!("irf {other:?}: expected \"ideal\", \"physical\", a measured matrix file \"A.npy\" or an array [N, M, T]"))),
        };
    }
    if obj.cast::<numpy::PyUntypedArray>().is_ok() {
        let a = f32_array(obj, "irf")?;
        check_rank(a.shape(), &[3], "irf", "a measured matrix A [N, M, T]")?;
        return Ok(IrfArg::Array(a.as_array().into_dimensionality::<Ix3>().map_err(err)?.to_owned()));
    }
    let p = path_of(obj).map_err(|_| pyo3::exceptions::PyTypeError::new_err("irf: expected \"ideal\", \"physical\", a path to A.npy or a float32 array [N, M, T]"))?;
    Ok(IrfArg::File(p))
}

/// The spec and nominal matrix of `codes` under these settings (what `--irf`, `--oversample`,
/// `--heterodyne`, `--laser-fwhm-ns` and `--tap-tau-ns` give on the command line).
pub fn build(codes: &Codes, irf: IrfArgOwned, oversample: Option<usize>, heterodyne: Option<usize>) -> PyResult<(SensorSpec, MeasurementMatrix, String)> {
    let sampling = Sampling::from_factors(oversample, heterodyne, Sampling::Oversample(1)).map_err(err)?;
    let (irf_spec, label) = match &irf.0 {
        IrfArg::Named(i, s) => (*i, s.clone()),
        IrfArg::File(p) => (Irf::Ideal, p.display().to_string()),
        IrfArg::Array(_) => (Irf::Ideal, "array".to_string()),
    };
    let spec = SensorParams { sampling, irf: irf_spec, ..SensorParams::from_codes(codes) }.validate().map_err(err)?;
    let a = match irf.0 {
        IrfArg::Named(..) => MeasurementMatrix::synthesize(codes, &spec).map_err(err)?,
        IrfArg::File(p) => {
            existing(&p, "irf")?;
            MeasurementMatrix::load(&p, &spec).map_err(err)?
        }
        IrfArg::Array(a) => MeasurementMatrix::from_array(a, &spec).map_err(err)?,
    };
    Ok((spec, a, label))
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
fn into_out(py: Python<'_>, out: &Bound<'_, PyAny>, want: &[usize], f: impl FnOnce(&mut ndarray::ArrayViewMut4<'_, f32>) -> tcsense_sensor::Result<()> + Send) -> PyResult<()> {
    f32_array(out, "out")?;
    let mut rw: PyReadwriteArrayDyn<'_, f32> = out.extract().map_err(|e| err(format!("out: {e}")))?;
    if rw.shape() != want {
        return Err(err(format!("out: shape {:?}; expected {want:?}", rw.shape())));
    }
    let view = rw.as_array_mut();
    let mut v4 = if want.len() == 4 { view.into_dimensionality::<Ix4>() } else { view.insert_axis(Axis(0)).into_dimensionality::<Ix4>() }.map_err(err)?;
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
    fn py_new(codes: &Bound<'_, PyAny>, irf: Option<&Bound<'_, PyAny>>, oversample: Option<usize>, heterodyne: Option<usize>, laser_fwhm_ns: f64, tap_tau_ns: f64, calibration: Option<&Bound<'_, PyAny>>) -> PyResult<Self> {
        let codes = codes_of(codes)?;
        let irf = match irf {
            Some(i) => IrfArgOwned::parse(i, laser_fwhm_ns, tap_tau_ns)?,
            None => IrfArgOwned(IrfArg::Named(Irf::Ideal, "ideal".into())),
        };
        let (spec, a, label) = build(&codes, irf, oversample, heterodyne)?;
        let cal = match calibration {
            Some(dir) => {
                let d = path_of(dir)?;
                existing(&d, "calibration")?;
                Some(Calibration::load(&d, &a, &codes).map_err(err)?)
            }
            None => None,
        };
        Ok(PySensor::new(codes, spec, a, cal, label))
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
    /// `tail_tau_s`, `shift_s`, `seed`). `units`: "input" (units of A x), "electrons" or "adc".
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
        if !["input", "electrons", "adc"].contains(&units) {
            return Err(err(format!("units {units:?}: expected \"input\", \"electrons\" or \"adc\"")));
        }
        let ni: NonIdeal = merged(&NonIdeal::default(), nonideal, "nonideal")?;
        let ni = ni.validate().map_err(|e| err(format!("nonideal: {e}")))?;
        let arr = f32_array(x, "x")?;
        let (batched, v) = batch_view(&arr, "x", "[T, H, W] or [B, T, H, W]")?;
        ensure_finite(&v.view().into_dyn(), "x").map_err(err)?;
        let (_, t, h, w) = v.dim();
        if t != self.spec.bins() {
            return Err(err(format!("x: {t} time bins, but the sensor grid has T = L·K = {} bins", self.spec.bins())));
        }
        let exposure = match electrons_per_unit {
            Some(s) => Exposure::ElectronsPerUnit(s),
            None => Exposure::Auto,
        };
        let a = self.matrix_ref();
        let plan = self.plan(h, w)?;
        let measured = py
            .detach(|| -> tcsense_sensor::Result<Measurement> {
                if ni.is_ideal() {
                    let xd = if batched { v.view().into_dyn() } else { v.index_axis(Axis(0), 0).into_dyn() };
                    measure(&plan, &xd, noise.then_some(&params), exposure, seed)
                } else {
                    let real = ni.realise(a, h, w)?;
                    let mut e = real.measure(&v, &params, noise, exposure, seed)?;
                    if !batched {
                        e.electrons = e.electrons.index_axis_move(Axis(0), 0);
                    }
                    Ok(Measurement::Noisy(e))
                }
            })
            .map_err(err)?;
        let y = match measured {
            Measurement::Noiseless(y) => y,
            Measurement::Noisy(n) => match units {
                "electrons" => n.electrons,
                "adc" => n.in_adc_codes(&params),
                _ => n.in_input_units(),
            },
        };
        Ok(y.into_pyarray(py))
    }

    /// `(y − d) / G`: raw tap images of a calibrated sensor corrected by its dark and gain maps.
    /// y `[M, H, W]` or `[B, M, H, W]`, in the sweep's units.
    fn correct<'py>(&self, py: Python<'py>, y: &Bound<'py, PyAny>) -> PyResult<Bound<'py, PyArrayDyn<f32>>> {
        if self.calibration.is_none() {
            return Err(err("correct: this sensor has no calibration; pass calibration=DIR to Sensor(…)"));
        }
        let arr = f32_array(y, "y")?;
        let (batched, v) = batch_view(&arr, "y", "[M, H, W] or [B, M, H, W]")?;
        Ok(unbatch(batched, self.corrected(v)?).into_pyarray(py))
    }

    /// Write `y` to `path` (.npy) with its sidecar (`NAME.meta.json` beside it), which names this
    /// sensor, the noise settings and the units, as `tcsense simulate` does.
    #[pyo3(signature = (path, y, *, noise = None, seed = None, units = "input"))]
    fn save_measurements(&self, path: &Bound<'_, PyAny>, y: &Bound<'_, PyAny>, noise: Option<&Bound<'_, PyDict>>, seed: Option<u64>, units: &str) -> PyResult<()> {
        let p = path_of(path)?;
        let arr = f32_array(y, "y")?;
        check_rank(arr.shape(), &[3, 4], "y", "[M, H, W] or [B, M, H, W]")?;
        let noise = noise.map(|d| merged(&NoiseParams::default(), Some(d), "noise")).transpose()?;
        let sidecar = Sidecar::new(&self.codes, &self.nominal, self.spec.sampling(), noise, seed, units);
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
        let y = read_npy(&p).map_err(err)?;
        check_measurements_file(&p, &self.nominal, &self.codes, self.calibration.as_ref()).map_err(err)?;
        if !(y.ndim() == 3 || y.ndim() == 4) || y.shape()[y.ndim() - 3] != self.nominal.taps() {
            return Err(err(format!("{}: measurements have shape {:?}, expected [M, H, W] or [B, M, H, W] with M = {} taps", p.display(), y.shape(), self.nominal.taps())));
        }
        Ok(y.into_pyarray(py))
    }

    /// The matrix it decodes with, `A [N, M, T]` (the calibration's when calibrated).
    fn matrix<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray3<f32>> {
        self.matrix_ref().a().to_owned().into_pyarray(py)
    }

    /// The nominal (synthesised or given) `A [N, M, T]`.
    fn nominal_matrix<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray3<f32>> {
        self.nominal.a().to_owned().into_pyarray(py)
    }

    #[getter]
    fn codes(&self) -> PyCodes {
        PyCodes { inner: self.codes.clone() }
    }
    #[getter]
    fn taps(&self) -> usize {
        self.nominal.taps()
    }
    #[getter]
    fn bins(&self) -> usize {
        self.nominal.bins()
    }
    #[getter]
    fn subpixels(&self) -> usize {
        self.nominal.subpixels()
    }
    #[getter]
    fn block(&self) -> (usize, usize) {
        self.nominal.block()
    }
    /// Width of one time bin (s).
    #[getter]
    fn bin_width_s(&self) -> f64 {
        self.spec.bin_width_s()
    }
    /// One code cycle (s).
    #[getter]
    fn cycle_s(&self) -> f64 {
        self.spec.cycle_s()
    }
    /// `("oversample" | "heterodyne", K)`.
    #[getter]
    fn sampling(&self) -> (&'static str, usize) {
        match self.spec.sampling() {
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
        self.calibration.as_ref().map(|c| to_python(py, &serde_json::to_value(&c.meta).map_err(err)?)).transpose()
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
            if self.calibration.is_some() { ", calibrated" } else { "" }
        )
    }
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PySensor>()
}
