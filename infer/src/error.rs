//! The inference crate's error type.

use std::path::PathBuf;

/// Errors of the inference crate.
#[derive(Debug, thiserror::Error)]
pub enum InferError {
    #[error(transparent)]
    Sensor(#[from] tcsense_sensor::SensorError),
    #[error(transparent)]
    Dataset(#[from] tcsense_datasets::DatasetError),
    #[error(transparent)]
    Model(#[from] tcsense_models::ModelError),
    /// A file whose content does not fit.
    #[error("{}: {msg}", path.display())]
    File { path: PathBuf, msg: String },
    /// A parameter outside its valid range.
    #[error("invalid {field}: got {got}, expected {expected}")]
    InvalidParam { field: &'static str, got: String, expected: String },
    /// Settings of a decoder or a fit that it cannot use; `msg` names the setting, the value and
    /// what was expected.
    #[error("{what} settings: {msg}")]
    Settings { what: &'static str, msg: String },
    /// A decoder name that names none.
    #[error("decoder {name:?}: unknown decoder; expected one of {known}")]
    UnknownDecoder { name: String, known: String },
    /// The ONNX Runtime shared library cannot be found or loaded.
    #[error("ONNX Runtime 1.31.1: {0}; install it with `scripts/setup.sh` (the PyPI wheel onnxruntime==1.31.1 into .venv) or set ORT_DYLIB_PATH to libonnxruntime.so")]
    OrtMissing(String),
    #[error("interrupted")]
    Cancelled,
}

/// Result alias of the inference crate.
pub type Result<T> = std::result::Result<T, InferError>;
