//! Datasets: generate the randomised LiDAR and FLIm sets, open one, read a split's field, and
//! iterate its items as dicts of arrays.

use std::sync::atomic::{AtomicUsize, Ordering};

use ndarray::{ArrayD, Axis};
use numpy::IntoPyArray;
use pyo3::prelude::*;
use pyo3::types::PyDict;
use tcsense_datasets::flim::FlimParams;
use tcsense_datasets::lidar::LidarParams;
use tcsense_datasets::store::{self, Generator, WriteOptions, DEFAULT_SHARD};
use tcsense_datasets::{Dataset, TimeGrid};
use tcsense_sensor::npy::read_npy;

use crate::{err, existing, merged, path_of, run_long, to_python};

/// A dataset directory (`manifest.json` + `.npy` shards per split and field).
#[pyclass(name = "Dataset", module = "tcsense", frozen)]
pub struct PyDataset {
    inner: Dataset,
}

#[pymethods]
impl PyDataset {
    /// Open the dataset in `path` (checks its manifest).
    #[new]
    fn py_new(path: &Bound<'_, PyAny>) -> PyResult<Self> {
        let p = path_of(path)?;
        existing(&p, "path")?;
        Ok(PyDataset { inner: Dataset::open(&p).map_err(err)? })
    }

    /// `manifest.json` as a dict.
    #[getter]
    fn manifest<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        to_python(py, &serde_json::to_value(&self.inner.manifest).map_err(err)?)
    }

    /// `lidar` or `flim`.
    #[getter]
    fn kind(&self) -> PyResult<String> {
        Ok(serde_json::to_value(self.inner.manifest.kind).map_err(err)?.as_str().unwrap_or("?").to_lowercase())
    }

    /// Items per split, `{name: count}`.
    #[getter]
    fn splits<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let d = PyDict::new(py);
        for s in &self.inner.manifest.splits {
            d.set_item(&s.name, s.count)?;
        }
        Ok(d)
    }

    /// Per-item field shapes, `{name: shape}` (x `[T, H, W]`, depth `[K, H, W]`, …).
    #[getter]
    fn fields<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let d = PyDict::new(py);
        for (k, v) in &self.inner.manifest.fields {
            d.set_item(k, v.clone())?;
        }
        Ok(d)
    }

    /// Width of a time bin (s).
    #[getter]
    fn bin_width_s(&self) -> f64 {
        self.inner.manifest.bin_width_s
    }

    /// One field of a whole split, `[count, …item shape]`.
    fn load<'py>(&self, py: Python<'py>, split: &str, field: &str) -> PyResult<Bound<'py, PyAny>> {
        let a = run_long(py, |_| self.inner.load(split, field))?.map_err(err)?;
        Ok(a.into_pyarray(py).into_any())
    }

    /// Item `index` of `split` as a dict of arrays (every field).
    fn item<'py>(&self, py: Python<'py>, split: &str, index: usize) -> PyResult<Bound<'py, PyDict>> {
        let d = PyDict::new(py);
        for field in self.inner.manifest.fields.keys() {
            let a = self.inner.item(split, index, field).map_err(err)?;
            d.set_item(field, a.into_pyarray(py))?;
        }
        Ok(d)
    }

    /// Iterate the items of `split` in order as dicts of arrays, reading one shard at a time.
    #[pyo3(signature = (split = "train"))]
    fn items(slf: Bound<'_, Self>, split: &str) -> PyResult<ItemIter> {
        let count = slf.get().inner.split(split).map_err(err)?.count;
        Ok(ItemIter { dataset: slf.unbind(), split: split.into(), shard: 0, offset: 0, count, seen: 0, cached: Vec::new() })
    }

    fn __len__(&self) -> usize {
        self.inner.manifest.splits.iter().map(|s| s.count).sum()
    }

    fn __repr__(&self) -> String {
        let m = &self.inner.manifest;
        let splits: Vec<String> = m.splits.iter().map(|s| format!("{}={}", s.name, s.count)).collect();
        format!("Dataset({:?}, {}x{}, T={}, {})", self.inner.dir.display().to_string(), m.size[0], m.size[1], m.bins, splits.join(", "))
    }
}

/// Items of a split, shard by shard.
#[pyclass(module = "tcsense")]
pub struct ItemIter {
    dataset: Py<PyDataset>,
    split: String,
    shard: usize,
    offset: usize,
    count: usize,
    seen: usize,
    /// The current shard's fields.
    cached: Vec<(String, ArrayD<f32>)>,
}

#[pymethods]
impl ItemIter {
    fn __iter__(slf: PyRef<'_, Self>) -> PyRef<'_, Self> {
        slf
    }

    fn __next__<'py>(&mut self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyDict>>> {
        if self.seen >= self.count {
            return Ok(None);
        }
        let ds = self.dataset.bind(py).get();
        let split = ds.inner.split(&self.split).map_err(err)?;
        while self.cached.is_empty() || self.offset >= split.shards[self.shard].count {
            if !self.cached.is_empty() {
                self.shard += 1;
                self.offset = 0;
            }
            let Some(sh) = split.shards.get(self.shard) else { return Ok(None) };
            let mut fields = Vec::new();
            for (name, rel) in &sh.files {
                let path = ds.inner.dir.join(rel);
                fields.push((name.clone(), py.detach(|| read_npy(&path)).map_err(err)?));
            }
            self.cached = fields;
        }
        let d = PyDict::new(py);
        for (name, a) in &self.cached {
            d.set_item(name, a.index_axis(Axis(0), self.offset).to_owned().into_pyarray(py))?;
        }
        self.offset += 1;
        self.seen += 1;
        Ok(Some(d))
    }
}

/// Generate a dataset of `count` scenes into `out` (`tcsense dataset lidar|flim`): `kind`
/// "lidar" or "flim", frames `size (H, W)`, `length` L masks at `clock_hz`, `heterodyne` or
/// `oversample` K, `params` a dict of generator settings over the defaults (LiDAR: walls,
/// objects, sheets, ambient …; FLIm: lifetimes, onsets, cells …). Item i is a pure function of
/// `(seed, i)`. Written atomically; Ctrl-C leaves nothing.
#[pyfunction]
#[pyo3(signature = (kind, out, count, *, size = (64, 64), seed = 0, length = 32, clock_hz = tcsense_sensor::codes::DEFAULT_CLOCK_HZ, heterodyne = None, oversample = None, params = None, force = false))]
#[allow(clippy::too_many_arguments)]
fn generate_dataset(
    py: Python<'_>,
    kind: &str,
    out: &Bound<'_, PyAny>,
    count: usize,
    size: (usize, usize),
    seed: u64,
    length: usize,
    clock_hz: f64,
    heterodyne: Option<usize>,
    oversample: Option<usize>,
    params: Option<&Bound<'_, PyDict>>,
    force: bool,
) -> PyResult<PyDataset> {
    let dir = path_of(out)?;
    let sampling = tcsense_sensor::Sampling::from_factors(oversample, heterodyne, tcsense_sensor::Sampling::Oversample(1)).map_err(err)?;
    let grid = TimeGrid { length, clock_hz, sampling };
    let (h, w) = size;
    let gen = match kind {
        "lidar" => Generator::Lidar(merged(&LidarParams { height: h, width: w, ..Default::default() }, params, "params")?),
        "flim" => Generator::Flim(merged(&FlimParams { height: h, width: w, ..Default::default() }, params, "params")?),
        other => return Err(err(format!("kind {other:?}: expected \"lidar\" or \"flim\""))),
    };
    let done = AtomicUsize::new(0);
    let progress = || {
        done.fetch_add(1, Ordering::Relaxed);
    };
    run_long(py, |cancel| {
        store::generate(&gen, &grid, count, seed, &dir, &WriteOptions { shard_size: DEFAULT_SHARD, force, progress: &progress, cancel })
    })?
    .map_err(err)?;
    Ok(PyDataset { inner: Dataset::open(&dir).map_err(err)? })
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PyDataset>()?;
    m.add_class::<ItemIter>()?;
    m.add_function(wrap_pyfunction!(generate_dataset, m)?)?;
    Ok(())
}
