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
    /// A value past [`crate::npy::MAX_VALUE`] in magnitude: sums of such values overflow `f32`.
    #[error("{what}: value {value:e} at index {index:?} is beyond ±1e30; inputs must stay within it (sums of them overflow f32)")]
    TooLarge { what: String, index: Vec<usize>, value: f32 },
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

/// An invalid parameter. A float that would print with many digits (`1e300` as 301 of them,
/// `2.5e-9` as `0.0000000025`) is named in scientific notation; integers as they are.
pub(crate) fn invalid(field: &'static str, got: impl ToString, expected: impl Into<String>) -> SensorError {
    let got = got.to_string();
    let got = match got.parse::<f64>() {
        Ok(v) if got.len() > 10 && v.is_finite() && got.parse::<i128>().is_err() => format!("{v:e}"),
        _ => got,
    };
    SensorError::InvalidParam { field, got, expected: expected.into() }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_absurd_number_is_named_in_scientific_notation() {
        assert_eq!(invalid("laser_fwhm", 1e300, "a duration").to_string(), "invalid laser_fwhm: got 1e300, expected a duration");
        assert_eq!(invalid("tap_tau", 2.5e-9, "a time").to_string(), "invalid tap_tau: got 2.5e-9, expected a time");
        assert_eq!(invalid("taps", 9, "1..=8").to_string(), "invalid taps: got 9, expected 1..=8");
        assert_eq!(invalid("frames", 123456789012u64, "x").to_string(), "invalid frames: got 123456789012, expected x");
        assert_eq!(invalid("level", 0.25, "x").to_string(), "invalid level: got 0.25, expected x");
        assert_eq!(invalid("units", "volts", "x").to_string(), "invalid units: got volts, expected x");
    }
}
