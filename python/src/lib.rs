//! `tcsense._tcsense`: the Python module of tcsense, a thin front end like the binary over the
//! same crates. numpy float32 arrays in and out, in the axis order the crates document
//! (`x [T, H, W]` or `[B, T, H, W]`, `y [M, H, W]` or `[B, M, H, W]`, `A [N, M, T]`).
//!
//! - Inputs are borrowed as views (no copy; any strides); outputs move their buffer into numpy.
//! - Calls that take long (decoders, dataset generation, export, the demo) run on a worker
//!   thread with the GIL released; the calling thread waits without the GIL and turns Ctrl-C
//!   into the crates' cancel flag, then raises `KeyboardInterrupt`. Short calls (forward,
//!   adjoint) release the GIL without a worker.
//! - Errors are `tcsense.TcsenseError` with the message the command line prints; wrong dtypes
//!   are `TypeError`, missing files `FileNotFoundError`, each naming the argument or file.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Condvar, Mutex};
use std::time::Duration;

use numpy::{PyArrayDescrMethods, PyArrayDyn, PyArrayMethods, PyReadonlyArrayDyn, PyUntypedArray, PyUntypedArrayMethods};
use pyo3::exceptions::{PyException, PyFileNotFoundError, PyRuntimeError, PyTypeError};
use pyo3::prelude::*;
use pyo3::types::PyDict;

mod codes;
mod data;
mod decoders;
mod onnx;
mod pipeline;
mod products;
mod sensor;
mod training;

pyo3::create_exception!(
    tcsense,
    TcsenseError,
    PyException,
    "An error of tcsense: bad input (shape, values, a file's contents, mismatched codes) or a failed step; the message is the command line's."
);

/// A crate error as `TcsenseError`, with its message.
pub(crate) fn err(e: impl std::fmt::Display) -> PyErr {
    TcsenseError::new_err(e.to_string())
}

/// `FileNotFoundError` naming the argument and the path, unless `path` exists.
pub(crate) fn existing(path: &Path, what: &str) -> PyResult<()> {
    if path.exists() {
        Ok(())
    } else {
        Err(PyFileNotFoundError::new_err((2, format!("{what}: no such file or directory: {}", path.display()), path.display().to_string())))
    }
}

/// A float32 numpy array as a read-only view, with a `TypeError` naming the argument for
/// anything else. The view borrows numpy's buffer (no copy).
pub(crate) fn f32_array<'py>(obj: &Bound<'py, PyAny>, name: &str) -> PyResult<PyReadonlyArrayDyn<'py, f32>> {
    let Ok(untyped) = obj.cast::<PyUntypedArray>() else {
        let ty = obj.get_type().name().map(|n| n.to_string()).unwrap_or_else(|_| "?".into());
        return Err(PyTypeError::new_err(format!("{name}: expected a numpy array of float32, got {ty}")));
    };
    let dtype = untyped.dtype();
    if !dtype.is_equiv_to(&numpy::dtype::<f32>(obj.py())) {
        return Err(PyTypeError::new_err(format!(
            "{name}: expected a numpy array of float32, got dtype {dtype}; convert it with {name}.astype(numpy.float32)"
        )));
    }
    let arr = obj.cast::<PyArrayDyn<f32>>().map_err(|e| PyTypeError::new_err(format!("{name}: {e}")))?;
    arr.try_readonly().map_err(|e| PyRuntimeError::new_err(format!("{name}: {e}")))
}

/// `TcsenseError` unless the array has one of the ranks, naming the argument and its axes.
pub(crate) fn check_rank(shape: &[usize], ranks: &[usize], name: &str, axes: &str) -> PyResult<()> {
    if ranks.contains(&shape.len()) {
        Ok(())
    } else {
        Err(TcsenseError::new_err(format!("{name}: shape {shape:?}; expected {axes}")))
    }
}

/// A path argument: `str` or `os.PathLike`.
pub(crate) fn path_of(obj: &Bound<'_, PyAny>) -> PyResult<PathBuf> {
    obj.extract::<PathBuf>()
}

/// Run `f` on a worker thread with the GIL released; Ctrl-C (seen by this thread when it is
/// Python's main thread) sets the cancel flag `f` is given, waits for `f` to stop, and raises
/// `KeyboardInterrupt`. A panic becomes a `RuntimeError`.
pub(crate) fn run_long<T: Send>(py: Python<'_>, f: impl FnOnce(&AtomicBool) -> T + Send) -> PyResult<T> {
    let cancel = AtomicBool::new(false);
    let done = (Mutex::new(false), Condvar::new());
    std::thread::scope(|s| {
        let (cancel, done) = (&cancel, &done);
        let worker = s.spawn(move || {
            let out = f(cancel);
            *done.0.lock().unwrap_or_else(|e| e.into_inner()) = true;
            done.1.notify_all();
            out
        });
        loop {
            let finished = py.detach(|| {
                let guard = done.0.lock().unwrap_or_else(|e| e.into_inner());
                let (guard, _) = done.1.wait_timeout_while(guard, Duration::from_millis(100), |d| !*d).unwrap_or_else(|e| e.into_inner());
                *guard
            });
            if finished || worker.is_finished() {
                break;
            }
            if let Err(interrupt) = py.check_signals() {
                cancel.store(true, Ordering::SeqCst);
                let _ = py.detach(|| worker.join());
                return Err(interrupt);
            }
        }
        py.detach(|| worker.join())
            .map_err(|_| PyRuntimeError::new_err("tcsense: the worker thread panicked; please report this with the call that caused it"))
    })
}

/// Overrides from a Python dict onto `default`, through JSON: every key must be one of
/// `default`'s fields (a `TcsenseError` names the unknown ones and lists the fields).
pub(crate) fn merged<T: serde::Serialize + serde::de::DeserializeOwned>(
    default: &T,
    overrides: Option<&Bound<'_, PyDict>>,
    what: &str,
) -> PyResult<T> {
    let mut v = serde_json::to_value(default).map_err(err)?;
    if let Some(d) = overrides {
        let json = d.py().import("json")?.call_method1("dumps", (d,))?.extract::<String>()?;
        let o: serde_json::Value = serde_json::from_str(&json).map_err(err)?;
        let (Some(base), Some(over)) = (v.as_object_mut(), o.as_object()) else {
            return Err(err(format!("{what}: expected a dict of settings")));
        };
        let unknown: Vec<&String> = over.keys().filter(|k| !base.contains_key(*k)).collect();
        if !unknown.is_empty() {
            let fields: Vec<&String> = base.keys().collect();
            return Err(err(format!("{what}: unknown setting(s) {unknown:?}; expected some of {fields:?}")));
        }
        for (k, x) in over {
            base.insert(k.clone(), x.clone());
        }
    }
    serde_json::from_value(v).map_err(|e| err(format!("{what}: {e}")))
}

/// A JSON value as the Python object `json.loads` makes of it.
pub(crate) fn to_python<'py>(py: Python<'py>, v: &serde_json::Value) -> PyResult<Bound<'py, PyAny>> {
    py.import("json")?.call_method1("loads", (v.to_string(),))
}

#[pymodule]
fn _tcsense(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("TcsenseError", m.py().get_type::<TcsenseError>())?;
    m.add("DEFAULT_CLOCK_HZ", tcsense_sensor::codes::DEFAULT_CLOCK_HZ)?;
    codes::register(m)?;
    sensor::register(m)?;
    decoders::register(m)?;
    data::register(m)?;
    products::register(m)?;
    onnx::register(m)?;
    pipeline::register(m)?;
    training::register(m)?;
    Ok(())
}
