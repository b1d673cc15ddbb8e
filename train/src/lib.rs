//! `tcsense-train`: training of the learned decoders with burn (the only crate with autodiff).
//!
//! One loop ([`fit`]) trains every network that implements `tcsense_models::net::Network`
//! with Adam (lr 1e-3), batch 2, loss RMSE + MAE (LiDAR) or RMSE (FLIm) (paper Table 3).
//! Measurements are simulated on the fly by the sensor's `measure` with fresh shot and read
//! noise at every step (full well 20 000 e⁻, σ = 40 e⁻), seeded by `(seed, step)`; batches are
//! drawn in an order seeded by `(seed, epoch)`. So a run is a pure function of its config, and
//! a resumed run continues exactly where the checkpoint was taken.
//!
//! - [`config`]: the run's `config.json` ([`TrainConfig`]: network + sensor model + training
//!   settings) and the losses' names;
//! - [`fit`]: the loop, validation through the decoder contract, resume;
//! - [`augment`]: training-time augmentation (cyclic time shifts, flips, crops, brightness,
//!   noise level per item), applied before the sensor is simulated;
//! - [`loss`]: the losses;
//! - [`run_dir`]: checkpoints (atomic), progress state, `metrics.csv`;
//! - [`data`]: training cubes from a dataset;
//! - [`bench`]: step and inference timings for `tcsense bench train`;
//! - [`setup`]: the rules of starting, resuming and fine-tuning a run (architecture from the
//!   run, start codes, a measured sensor);
//! - [`request`]: a training as a front end asks for it (the flags, Python's keywords)
//!   resolved into a run's config, codes and sensor — what the binary, Python and the demo
//!   fill;
//! - [`deep_sensing`]: codes learned jointly with the decoder, then projected exactly onto
//!   the hardware's constraints.
//!
//! Opening a trained run for inference needs none of this: `tcsense_models::runs::open`.

pub mod augment;
pub mod bench;
pub mod config;
pub mod data;
pub mod deep_sensing;
pub mod fit;
pub mod loss;
pub mod request;
pub mod run_dir;
pub mod setup;

pub use augment::Augmentation;
pub use config::{ConfidenceLoss, LifetimeError, Loss, LrSchedule, Objective, TrainConfig};
pub use fit::{train, train_on, Progress, Quiet};
pub use run_dir::{EpochMetrics, RunState};

use std::path::{Path, PathBuf};

/// Errors of the training crate.
#[derive(Debug, thiserror::Error)]
pub enum TrainError {
    #[error(transparent)]
    Sensor(#[from] tcsense_sensor::SensorError),
    #[error(transparent)]
    Dataset(#[from] tcsense_datasets::DatasetError),
    #[error(transparent)]
    Model(#[from] tcsense_models::ModelError),
    #[error("{}: {msg}", path.display())]
    File { path: PathBuf, msg: String },
    #[error("invalid {field}: got {got}, expected {expected}")]
    InvalidParam { field: &'static str, got: String, expected: String },
    #[error("interrupted; the last checkpoint is kept, continue with --resume")]
    Cancelled,
    #[error("training diverged: the loss was {loss} at epoch {epoch}, step {step}; {}", if *kept { "the last checkpoint is kept (a lower --lr, or --resume from it)" } else { "nothing was written (try a lower --lr)" })]
    Diverged { loss: f64, epoch: usize, step: u64, kept: bool },
}

/// Result alias of the training crate.
pub type Result<T> = std::result::Result<T, TrainError>;

pub(crate) fn file_err(path: &Path, msg: impl ToString) -> TrainError {
    TrainError::File { path: path.to_path_buf(), msg: msg.to_string() }
}
