//! The pipeline's errors: the crates' errors it runs into, and its own checks.

use std::path::PathBuf;

/// What can go wrong in a pipeline.
#[derive(Debug, thiserror::Error)]
pub enum PipelineError {
    #[error(transparent)]
    Sensor(#[from] tcsense_sensor::SensorError),
    #[error(transparent)]
    Dataset(#[from] tcsense_datasets::DatasetError),
    #[error(transparent)]
    Model(#[from] tcsense_models::ModelError),
    #[error(transparent)]
    Train(#[from] tcsense_train::TrainError),
    #[error(transparent)]
    Infer(#[from] tcsense_infer::InferError),
    /// The OS error and the JSON error are parts of the message, not sources of their own, so
    /// that a chain printed whole (`{:#}`) says them once.
    #[error("{}: {cause}", path.display())]
    Io { path: PathBuf, cause: std::io::Error },
    #[error("{what}: {cause}")]
    Json { what: String, cause: serde_json::Error },
    #[error(transparent)]
    Shape(#[from] ndarray::ShapeError),
    /// A setting out of range, a directory that holds something else, an interrupted run: the
    /// message says which and how to go on.
    #[error("{0}")]
    Invalid(String),
}

pub type Result<T> = std::result::Result<T, PipelineError>;

/// `return Err(PipelineError::Invalid(format!(…)))`.
macro_rules! bail {
    ($($t:tt)*) => { return Err($crate::error::PipelineError::Invalid(format!($($t)*))) };
}
pub(crate) use bail;

/// Context for an error, as `what: cause` (how the binary prints a chain).
pub(crate) trait Context<T> {
    fn with_context(self, what: impl FnOnce() -> String) -> Result<T>;
}

impl<T, E: std::fmt::Display> Context<T> for std::result::Result<T, E> {
    fn with_context(self, what: impl FnOnce() -> String) -> Result<T> {
        self.map_err(|e| PipelineError::Invalid(format!("{}: {e}", what())))
    }
}

impl From<serde_json::Error> for PipelineError {
    fn from(source: serde_json::Error) -> Self {
        PipelineError::Json { what: "JSON".into(), cause: source }
    }
}
