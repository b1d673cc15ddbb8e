//! Pipelines that run the toolkit's crates end to end, as library calls, so the binary and
//! the Python module are two thin front ends over the same work.
//!
//! - [`demo`]: the paper's prototype from nothing to `report.html` — datasets, code design
//!   (random selection by TVAL3 and deep sensing), code-memory export, training of ADMM-Net
//!   and the Aᵀ + U-Net within a time budget, ONNX export, ONNX Runtime, metric tables in the
//!   style of the paper's Tables 4 and 5, timing at 188×212, and the figures; the sensor's
//!   bring-up as its last part.
//! - [`bringup`]: a real sensor from its delay sweep to deployed decoders — calibration,
//!   fine-tuning of zoo decoders to the measured matrix, ONNX export with the calibration in
//!   the graph, and the check of both on the sensor's own frames.
//! - [`identifiability`]: the identifiability table of code sets (alias, bounds) for the report.
//! - [`observer`]: where a pipeline's log lines and progress go.
//!
//! Each pipeline takes a cancel flag and an observer (where its log lines and progress go)
//! and returns its results as values; errors are [`PipelineError`]s carrying the message the
//! command line prints.

pub mod bringup;
pub mod demo;
pub mod error;
pub mod identifiability;
pub mod observer;

pub use demo::{DemoOptions, DemoSummary};
pub use error::{PipelineError, Result};
pub use observer::Observer;

/// Write `v` as pretty JSON (atomically, with a final newline).
pub(crate) fn write_json(path: &std::path::Path, v: &serde_json::Value) -> Result<()> {
    tcsense_sensor::npy::write_bytes(path, (serde_json::to_string_pretty(v)? + "\n").as_bytes())?;
    Ok(())
}
