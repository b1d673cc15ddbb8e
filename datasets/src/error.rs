//! The datasets crate's error type.

use std::path::PathBuf;

/// Errors of the datasets crate.
#[derive(Debug, thiserror::Error)]
pub enum DatasetError {
    /// An error from the sensor crate (I/O, npy, parameters).
    #[error(transparent)]
    Sensor(#[from] tcsense_sensor::SensorError),
    /// A generator or import parameter out of range.
    #[error("invalid {field}: got {got}, expected {expected}")]
    InvalidParam { field: &'static str, got: String, expected: String },
    /// A malformed file.
    #[error("{}: {msg}", path.display())]
    File { path: PathBuf, msg: String },
    /// The user interrupted the work; nothing was written.
    #[error("interrupted; no output was written")]
    Cancelled,
}

/// Result alias of the datasets crate.
pub type Result<T> = std::result::Result<T, DatasetError>;

pub(crate) fn invalid(field: &'static str, got: impl ToString, expected: impl Into<String>) -> DatasetError {
    DatasetError::InvalidParam { field, got: got.to_string(), expected: expected.into() }
}

pub(crate) fn file_err(path: impl Into<PathBuf>, msg: impl Into<String>) -> DatasetError {
    DatasetError::File { path: path.into(), msg: msg.into() }
}
