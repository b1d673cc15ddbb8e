//! The sensor crate's error type. Every message names what was wrong and what was expected.

use std::path::PathBuf;

/// Errors of the sensor crate.
#[derive(Debug, thiserror::Error)]
pub enum SensorError {
    /// A parameter outside its valid range.
    #[error("invalid {field}: got {got}, expected {expected}")]
    InvalidParam { field: &'static str, got: String, expected: String },
    /// A file whose content is malformed.
    #[error("{}: {msg}", path.display())]
    File { path: PathBuf, msg: String },
    /// An I/O failure on a file. The OS error is part of the message, not a source of its own,
    /// so that a chain printed whole (`{:#}`) says it once.
    #[error("{}: {cause}", path.display())]
    Io { path: PathBuf, cause: std::io::Error },
    /// An array of the wrong shape.
    #[error("{what}: shape {got:?} does not fit, expected {expected}")]
    Shape { what: String, got: Vec<usize>, expected: String },
    /// A NaN or infinity where finite values are required.
    #[error("{what}: non-finite value ({value}) at index {index:?}; inputs must be finite")]
    NonFinite { what: String, index: Vec<usize>, value: f32 },
    /// Codes that break the constraints they were declared with.
    #[error(
        "codes violate their declared constraints ({count} violation(s)); first: {first}. Run `tcsense codes check` for the full list"
    )]
    Infeasible { count: usize, first: String },
    /// Long work stopped by the user (Ctrl-C); nothing was written.
    #[error("interrupted: nothing written")]
    Cancelled,
}

impl SensorError {
    /// Attach a path to an error about a file's content.
    pub fn file(path: impl Into<PathBuf>, msg: impl Into<String>) -> Self {
        SensorError::File { path: path.into(), msg: msg.into() }
    }

    /// Attach a path to an I/O error.
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        SensorError::Io { path: path.into(), cause: source }
    }

    /// Prefix an error with the file it came from (for errors raised while checking a file's content).
    pub fn in_file(self, path: &std::path::Path) -> Self {
        match self {
            e @ (SensorError::File { .. } | SensorError::Io { .. }) => e,
            other => SensorError::file(path, other.to_string()),
        }
    }
}

/// Result alias of the sensor crate.
pub type Result<T> = std::result::Result<T, SensorError>;

pub(crate) fn invalid(field: &'static str, got: impl ToString, expected: impl Into<String>) -> SensorError {
    SensorError::InvalidParam { field, got: got.to_string(), expected: expected.into() }
}
