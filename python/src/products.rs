//! Products of a reconstructed cube: depth and multi-bounce peaks, point clouds, lifetimes
//! and phasors (the crates' `tcsense_infer::products` and `lifetime`).

use ndarray::{Ix1, Ix3};
use numpy::{IntoPyArray, PyUntypedArrayMethods};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};
use tcsense_fits::lifetime_cube::{fit_cube, Components, FitOptions, IrfModel};
use tcsense_infer::products::{self, PeakOptions};

use crate::{check_rank, err, f32_array, path_of, run_long};

fn cube<'py>(x: &Bound<'py, PyAny>, name: &str) -> PyResult<numpy::PyReadonlyArrayDyn<'py, f32>> {
    let a = f32_array(x, name)?;
    check_rank(a.shape(), &[3], name, "a cube [T, H, W]")?;
    Ok(a)
}

fn peak_options(max_peaks: usize, min_rel: f32, min_sep: usize) -> PyResult<PeakOptions> {
    if max_peaks == 0 || !(0.0..=1.0).contains(&min_rel) {
        return Err(err(format!("max_peaks {max_peaks}, min_rel {min_rel}: expected at least one peak and a fraction in [0, 1]")));
    }
    Ok(PeakOptions { max_peaks, min_rel, min_sep })
}

/// Range of up to `max_peaks` returns per pixel from a cube (peaks refined to a fraction of a
/// bin by parabolic interpolation): x `[T, H, W]` → `(depth [K, H, W]` in m, NaN where no
/// return, `amplitude [K, H, W])`.
#[pyfunction]
#[pyo3(signature = (x, bin_width_s, *, max_peaks = 2, min_rel = 0.1, min_sep = 2))]
fn depth_map<'py>(
    py: Python<'py>,
    x: &Bound<'py, PyAny>,
    bin_width_s: f64,
    max_peaks: usize,
    min_rel: f32,
    min_sep: usize,
) -> PyResult<(Bound<'py, PyAny>, Bound<'py, PyAny>)> {
    let a = cube(x, "x")?;
    let v = a.as_array().into_dimensionality::<Ix3>().map_err(err)?;
    let opts = peak_options(max_peaks, min_rel, min_sep)?;
    let (d, amp) = py.detach(|| products::depth_map(&v, bin_width_s, &opts));
    Ok((d.into_pyarray(py).into_any(), amp.into_pyarray(py).into_any()))
}

/// Peaks of one waveform `[T]`: a list of `(position, amplitude)`, position in bins (bin j
/// centred at j), strongest first up to `max_peaks`.
#[pyfunction]
#[pyo3(signature = (wave, *, max_peaks = 2, min_rel = 0.1, min_sep = 2))]
fn find_peaks<'py>(
    py: Python<'py>,
    wave: &Bound<'py, PyAny>,
    max_peaks: usize,
    min_rel: f32,
    min_sep: usize,
) -> PyResult<Bound<'py, PyList>> {
    let a = f32_array(wave, "wave")?;
    check_rank(a.shape(), &[1], "wave", "a waveform [T]")?;
    let v = a.as_array().into_dimensionality::<Ix1>().map_err(err)?;
    let out = PyList::empty(py);
    for p in products::find_peaks(&v, &peak_options(max_peaks, min_rel, min_sep)?) {
        out.append((p.position, p.amplitude))?;
    }
    Ok(out)
}

/// Fluorescence lifetimes fitted to a cube (`tcsense lifetime`): a convolved one- or
/// two-exponential model with a Gaussian IRF (fitted, or `irf_fwhm_s`) or a measured IRF
/// (`irf`, one value per bin), and a background. x `[T, H, W]` → dict `lifetimes [4, H, W]`
/// (τ_m, τ₁, τ₂ in s, α₁; NaN where no fit), `background [H, W]`, `phasor [2, H, W]`,
/// `onset_s`, `irf_fwhm_s`.
#[pyfunction]
#[pyo3(signature = (x, bin_width_s, *, components = "auto", irf_fwhm_s = None, irf = None, min_intensity = 0.02))]
#[allow(clippy::too_many_arguments)]
fn fit_lifetimes<'py>(
    py: Python<'py>,
    x: &Bound<'py, PyAny>,
    bin_width_s: f64,
    components: &str,
    irf_fwhm_s: Option<f64>,
    irf: Option<&Bound<'py, PyAny>>,
    min_intensity: f32,
) -> PyResult<Bound<'py, PyDict>> {
    let a = cube(x, "x")?;
    let v = a.as_array().into_dimensionality::<Ix3>().map_err(err)?;
    let t = v.dim().0;
    let components = match components {
        "1" => Components::One,
        "2" => Components::Two,
        "auto" => Components::Auto,
        other => return Err(err(format!("components {other:?}: expected \"1\", \"2\" or \"auto\""))),
    };
    if !(0.0..1.0).contains(&min_intensity) {
        return Err(err(format!("min_intensity {min_intensity}: expected a fraction in [0, 1)")));
    }
    let irf = match (irf, irf_fwhm_s) {
        (Some(i), _) => {
            let i = f32_array(i, "irf")?;
            let iv = i.as_array();
            if iv.shape() != [t] || iv.iter().any(|x| !x.is_finite() || *x < 0.0) || iv.iter().all(|&x| x == 0.0) {
                return Err(err(format!(
                    "irf: shape {:?}; expected [{t}] non-negative finite values, not all zero (one per bin of the cube)",
                    iv.shape()
                )));
            }
            IrfModel::Measured(iv.iter().map(|&x| x as f64).collect())
        }
        (None, Some(w)) if w.is_finite() && w >= 0.0 => IrfModel::Gaussian(Some(w)),
        (None, Some(w)) => return Err(err(format!("irf_fwhm_s {w}: expected a width ≥ 0"))),
        (None, None) => IrfModel::Gaussian(None),
    };
    let opts = FitOptions { irf, components, min_intensity, ..Default::default() };
    let fit = run_long(py, |_| fit_cube(&v, bin_width_s, &opts))?;
    let d = PyDict::new(py);
    d.set_item("lifetimes", fit.lifetimes.into_pyarray(py))?;
    d.set_item("background", fit.background.into_pyarray(py))?;
    d.set_item("phasor", fit.phasor.into_pyarray(py))?;
    d.set_item("onset_s", fit.onset_s)?;
    d.set_item("irf_fwhm_s", fit.irf_fwhm_s)?;
    Ok(d)
}

/// First-harmonic phasors of each pixel's decay, background removed and the phase referenced
/// to the frame's onset (single exponentials fall on the universal semicircle): x `[T, H, W]`
/// → `[2, H, W]` (g, s; NaN below `min_intensity` of the brightest pixel).
#[pyfunction]
#[pyo3(signature = (x, *, min_intensity = 0.02))]
fn phasors<'py>(py: Python<'py>, x: &Bound<'py, PyAny>, min_intensity: f32) -> PyResult<Bound<'py, PyAny>> {
    let a = cube(x, "x")?;
    let v = a.as_array().into_dimensionality::<Ix3>().map_err(err)?;
    Ok(py.detach(|| products::referenced_phasors(&v, min_intensity)).into_pyarray(py).into_any())
}

/// Points of a range map `[K, H, W]` (m) seen through a pinhole camera with horizontal field
/// of view `fov_deg`: `[P, 4]` (x, y, z in m, bounce index); NaN ranges give no point.
#[pyfunction]
#[pyo3(signature = (depth, *, fov_deg = 40.0))]
fn point_cloud<'py>(py: Python<'py>, depth: &Bound<'py, PyAny>, fov_deg: f64) -> PyResult<Bound<'py, PyAny>> {
    let a = f32_array(depth, "depth")?;
    check_rank(a.shape(), &[3], "depth", "a range map [K, H, W]")?;
    let v = a.as_array().into_dimensionality::<Ix3>().map_err(err)?;
    let pts = products::point_cloud(&v, fov_deg);
    let flat: Vec<f32> = pts.iter().flatten().copied().collect();
    let arr = ndarray::Array2::from_shape_vec((pts.len(), 4), flat).map_err(err)?;
    Ok(arr.into_pyarray(py).into_any())
}

/// Write an ASCII PLY point cloud (x y z in m, bounce, amplitude) of a range map `[K, H, W]`
/// and its amplitudes `[K, H, W]`; returns the number of points.
#[pyfunction]
#[pyo3(signature = (path, depth, amplitude, *, fov_deg = 40.0))]
fn write_ply(path: &Bound<'_, PyAny>, depth: &Bound<'_, PyAny>, amplitude: &Bound<'_, PyAny>, fov_deg: f64) -> PyResult<usize> {
    let d = f32_array(depth, "depth")?;
    let a = f32_array(amplitude, "amplitude")?;
    check_rank(d.shape(), &[3], "depth", "a range map [K, H, W]")?;
    if a.shape() != d.shape() {
        return Err(err(format!("amplitude: shape {:?}; expected the depth's {:?}", a.shape(), d.shape())));
    }
    let dv = d.as_array().into_dimensionality::<Ix3>().map_err(err)?;
    let av = a.as_array().into_dimensionality::<Ix3>().map_err(err)?;
    products::write_ply(&path_of(path)?, &dv, &av, fov_deg).map_err(err)
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(depth_map, m)?)?;
    m.add_function(wrap_pyfunction!(find_peaks, m)?)?;
    m.add_function(wrap_pyfunction!(fit_lifetimes, m)?)?;
    m.add_function(wrap_pyfunction!(phasors, m)?)?;
    m.add_function(wrap_pyfunction!(point_cloud, m)?)?;
    m.add_function(wrap_pyfunction!(write_ply, m)?)?;
    Ok(())
}
