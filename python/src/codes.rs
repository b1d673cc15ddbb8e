//! `tcsense.Codes`: exposure codes — generate under the hardware constraints, check, project
//! logits exactly onto the constraints, and the sensor's code memory.

use ndarray::{Array3, Ix3};
use numpy::{IntoPyArray, PyArray3, PyReadonlyArray3, PyUntypedArrayMethods};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};
use tcsense_sensor::codes::{CodeShape, Codes, Constraints, DEFAULT_CLOCK_HZ};
use tcsense_sensor::{export, generate, project};

use crate::{check_rank, err, existing, f32_array, path_of, to_python};

/// Exposure codes of a multitap sensor: `N = bh·bw` subpixels × `M` taps × `L` masks per cycle,
/// designed under the constraints they record (tap, Hamming `H`, window `W`).
#[pyclass(name = "Codes", module = "tcsense", frozen)]
#[derive(Clone)]
pub struct PyCodes {
    pub inner: Codes,
}

fn constraints(tap_constraint: bool, hamming: Option<usize>, window: Option<usize>) -> Constraints {
    Constraints { tap: tap_constraint, hamming, window }
}

/// Codes from a `Codes` object or a path to a codes JSON file.
pub fn codes_of(obj: &Bound<'_, PyAny>) -> PyResult<Codes> {
    if let Ok(c) = obj.cast::<PyCodes>() {
        return Ok(c.get().inner.clone());
    }
    let path = path_of(obj)
        .map_err(|_| pyo3::exceptions::PyTypeError::new_err("codes: expected a tcsense.Codes or the path of a codes JSON file"))?;
    existing(&path, "codes")?;
    Codes::load(&path).map_err(err)
}

#[pymethods]
impl PyCodes {
    /// Random codes under the constraints, seeded (`tcsense codes generate`).
    #[staticmethod]
    #[pyo3(signature = (taps = 4, block = (2, 2), length = 32, *, tap_constraint = false, hamming = None, window = None, drain = false, clock_hz = DEFAULT_CLOCK_HZ, seed = 0))]
    #[allow(clippy::too_many_arguments)]
    fn generate(
        taps: usize,
        block: (usize, usize),
        length: usize,
        tap_constraint: bool,
        hamming: Option<usize>,
        window: Option<usize>,
        drain: bool,
        clock_hz: f64,
        seed: u64,
    ) -> PyResult<Self> {
        let shape = CodeShape { bh: block.0, bw: block.1, taps, length, drain };
        let inner = generate::random_codes(shape, clock_hz, constraints(tap_constraint, hamming, window), seed).map_err(err)?;
        Ok(PyCodes { inner })
    }

    /// Codes from their bits, `uint8`/`bool` `[N, M, L]` with `N = bh·bw`; the constraints are
    /// recorded, not enforced (see `violations`).
    #[staticmethod]
    #[pyo3(signature = (bits, block = (2, 2), *, tap_constraint = false, hamming = None, window = None, drain = false, clock_hz = DEFAULT_CLOCK_HZ))]
    #[allow(clippy::too_many_arguments)]
    fn from_bits(
        bits: &Bound<'_, PyAny>,
        block: (usize, usize),
        tap_constraint: bool,
        hamming: Option<usize>,
        window: Option<usize>,
        drain: bool,
        clock_hz: f64,
    ) -> PyResult<Self> {
        let np = bits.py().import("numpy")?;
        let b: PyReadonlyArray3<'_, u8> =
            np.call_method1("asarray", (bits, "uint8"))?.extract().map_err(|_| err("bits: expected an array [N, M, L] of 0/1"))?;
        let b = b.as_array();
        let (n, m, l) = b.dim();
        if n != block.0 * block.1 {
            return Err(err(format!(
                "bits: shape [{n}, {m}, {l}]; expected N = bh·bw = {} subpixels for the {}x{} block",
                block.0 * block.1,
                block.0,
                block.1
            )));
        }
        let shape = CodeShape { bh: block.0, bw: block.1, taps: m, length: l, drain };
        let mut codes = Codes::zeros(shape, clock_hz, constraints(tap_constraint, hamming, window)).map_err(err)?;
        for ((i, j, k), &v) in b.indexed_iter() {
            if v > 1 {
                return Err(err(format!("bits[{i}, {j}, {k}] = {v}; expected 0 or 1")));
            }
            codes.set(i, j, k, v == 1);
        }
        Ok(PyCodes { inner: codes })
    }

    /// Exact projection of logits `[N, C, L]` (`C = M`, or `M + 1` with a drain under the tap
    /// constraint) onto the constraints: the feasible codes of the highest total logit
    /// (`tcsense codes project`).
    #[staticmethod]
    #[pyo3(signature = (logits, block = (2, 2), *, tap_constraint = false, hamming = None, window = None, drain = false, clock_hz = DEFAULT_CLOCK_HZ))]
    #[allow(clippy::too_many_arguments)]
    fn project(
        py: Python<'_>,
        logits: &Bound<'_, PyAny>,
        block: (usize, usize),
        tap_constraint: bool,
        hamming: Option<usize>,
        window: Option<usize>,
        drain: bool,
        clock_hz: f64,
    ) -> PyResult<Self> {
        let arr = f32_array(logits, "logits")?;
        check_rank(arr.shape(), &[3], "logits", "[N, C, L]")?;
        let view = arr.as_array().into_dimensionality::<Ix3>().map_err(err)?;
        let (_, c, l) = view.dim();
        let taps = if tap_constraint && drain { c.saturating_sub(1) } else { c };
        let shape = CodeShape { bh: block.0, bw: block.1, taps, length: l, drain };
        let p = crate::run_long(py, |_| project::project(shape, clock_hz, constraints(tap_constraint, hamming, window), &view))?
            .map_err(err)?;
        Ok(PyCodes { inner: p.codes })
    }

    /// Read a codes JSON file (checked against its constraints).
    #[staticmethod]
    fn load(path: &Bound<'_, PyAny>) -> PyResult<Self> {
        let p = path_of(path)?;
        existing(&p, "path")?;
        Ok(PyCodes { inner: Codes::load(&p).map_err(err)? })
    }

    /// Codes from their JSON text.
    #[staticmethod]
    fn from_json(text: &str) -> PyResult<Self> {
        Ok(PyCodes { inner: Codes::from_json(text).map_err(err)? })
    }

    /// Read a code-memory directory back (`tcsense codes import`).
    #[staticmethod]
    fn from_code_memory(dir: &Bound<'_, PyAny>) -> PyResult<Self> {
        let d = path_of(dir)?;
        existing(&d, "dir")?;
        Ok(PyCodes { inner: export::import(&d).map_err(err)? })
    }

    /// Write the codes JSON file.
    fn save(&self, path: &Bound<'_, PyAny>) -> PyResult<()> {
        self.inner.save(&path_of(path)?).map_err(err)
    }

    /// The codes as JSON text.
    fn to_json(&self) -> String {
        self.inner.to_json()
    }

    /// Write the sensor's code memory (`chCC.bin`, `codes.bin`, `registers.json`) into `dir`;
    /// returns the registers as a dict (`tcsense codes export`).
    fn to_code_memory<'py>(&self, py: Python<'py>, dir: &Bound<'py, PyAny>) -> PyResult<Bound<'py, PyAny>> {
        let regs = export::export(&self.inner, &path_of(dir)?).map_err(err)?;
        to_python(py, &serde_json::to_value(&regs).map_err(err)?)
    }

    /// The constraints the codes break, as dicts `{kind, mask, subpixel, channel, detail}`
    /// (empty: feasible; `tcsense codes check`).
    fn violations<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyList>> {
        let out = PyList::empty(py);
        for v in self.inner.violations() {
            out.append(to_python(py, &serde_json::to_value(&v).map_err(err)?)?)?;
        }
        Ok(out)
    }

    /// Whether the codes meet their constraints.
    #[getter]
    fn feasible(&self) -> bool {
        self.inner.violations().is_empty()
    }

    /// The bits `[N, M, L]` as uint8.
    #[getter]
    fn bits<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray3<u8>> {
        let (n, m, l) = (self.inner.subpixels(), self.inner.taps(), self.inner.length());
        Array3::from_shape_fn((n, m, l), |(i, j, k)| u8::from(self.inner.get(i, j, k))).into_pyarray(py)
    }

    #[getter]
    fn taps(&self) -> usize {
        self.inner.taps()
    }
    #[getter]
    fn subpixels(&self) -> usize {
        self.inner.subpixels()
    }
    #[getter]
    fn length(&self) -> usize {
        self.inner.length()
    }
    #[getter]
    fn block(&self) -> (usize, usize) {
        self.inner.block()
    }
    #[getter]
    fn drain(&self) -> bool {
        self.inner.drain()
    }
    #[getter]
    fn clock_hz(&self) -> f64 {
        self.inner.clock_hz
    }
    /// `{tap, hamming, window}`.
    #[getter]
    fn constraints<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let d = PyDict::new(py);
        d.set_item("tap", self.inner.constraints.tap)?;
        d.set_item("hamming", self.inner.constraints.hamming)?;
        d.set_item("window", self.inner.constraints.window)?;
        Ok(d)
    }
    /// The digest that sidecars, runs and exported models record.
    #[getter]
    fn digest(&self) -> String {
        self.inner.digest()
    }

    fn __eq__(&self, other: &Bound<'_, PyAny>) -> bool {
        // the same codes: shape, bits, clock and constraints (not the free-form provenance)
        let same = |a: &Codes, b: &Codes| {
            a.shape() == b.shape() && a.digest() == b.digest() && a.clock_hz == b.clock_hz && a.constraints == b.constraints
        };
        other.cast::<PyCodes>().map(|o| same(&o.get().inner, &self.inner)).unwrap_or(false)
    }

    fn __repr__(&self) -> String {
        let (bh, bw) = self.inner.block();
        format!(
            "Codes(taps={}, block=({bh}, {bw}), length={}, constraints={:?}, digest={:?})",
            self.inner.taps(),
            self.inner.length(),
            self.inner.constraints.label(),
            self.inner.digest()
        )
    }
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PyCodes>()
}
