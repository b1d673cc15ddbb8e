//! `tcsense-models`: the decoders that recover transient cubes `x̂ [B, T, H, W]` (or depth
//! `[B, K, H, W]`) from tap images `y [B, M, H, W]` and the sensor, behind one contract.
//!
//! - [`decoder`]: the contract ([`Decoder`]: `(y, A) → cube and/or depth`), its input
//!   checks, and TVAL3 behind it ([`decoder::Tval3Decoder`]).
//! - [`tval3`]: TV minimisation by augmented Lagrangian with alternating shrinkage and a
//!   nonmonotone Barzilai–Borwein line search (Li, Yin, Jiang, Zhang), 3-D TV over
//!   `(x, y, t)` with per-axis weights — the paper's iterative baseline.
//! - [`admm`]: ADMM-Net, `S` unrolled stages with an exact per-pixel data-consistency step
//!   and a residual CNN prior (burn modules; trained by `tcsense-train`).
//! - [`unet`]: Aᵀ + U-Net, a light decoder that outputs the depth of `K` returns (and a
//!   confidence per return) directly.
//! - [`net`]: what a trainable network provides ([`net::Network`]) and the wrapper that puts
//!   any network behind the contract ([`net::NetDecoder`]).
//! - [`sensor_tensors`]: the sensor as tensors for one frame size — `A`, `Aᵀ`, the
//!   back-projection, the data-consistency solve — on the kernels of `tcsense-kernels`, with
//!   a reference composed from burn ops.
//! - [`runs`]: run directories (`config.json`, `codes.json`, `model.bpk`) opened as decoders
//!   with one call, [`runs::open`].
//! - [`lifetime`]: the lifetime network, tap images straight to lifetimes (FLI-Net-like).
//! - [`learned_codes`]: learnable exposure codes for deep sensing (relaxed, then projected
//!   onto the hardware's constraints).
//! - [`device`]: where the learned decoders run (CPU `flex` or GPU `wgpu`).
//! - [`zoo`]: the trained decoders shipped with the toolkit, `zoo:NAME`.
//! - [`metrics`]: MSE and PSNR of a cube against its truth.
//! - [`bench`]: the kernels timed against burn-flex's generic paths.
//!
//! Devices are chosen at run time (`Device::flex()` by default); nothing here assumes the CPU.

pub mod admm;
pub mod bench;
pub mod decoder;
pub mod depth_evidence;
pub mod device;
mod evidence_tensors;
pub mod learned_codes;
pub mod lifetime;
pub mod lifetime_evidence;
pub mod metrics;
pub mod net;
pub mod range_evidence;
pub mod runs;
pub mod sensor_tensors;
pub mod tval3;
pub mod unet;
pub mod zoo;

pub use admm::{AdmmNet, AdmmNetConfig, Prior};
/// The burn device type (CPU `Device::flex()` by default).
pub use burn::tensor::Device;
pub use decoder::{Control, Decoded, Decoder};
pub use lifetime::{LifetimeInput, LifetimeNet, LifetimeNetConfig};
pub use sensor_tensors::SensorTensors;
pub use tval3::{tval3, TvNorm, Tval3Options, Tval3Report};
pub use unet::{Unet, UnetConfig, UnetHead, UnetInput};

use std::path::PathBuf;

/// Errors of the models crate.
#[derive(Debug, thiserror::Error)]
pub enum ModelError {
    #[error(transparent)]
    Sensor(#[from] tcsense_sensor::SensorError),
    /// A run-directory file that is missing or does not fit.
    #[error("{}: {msg}", path.display())]
    File { path: PathBuf, msg: String },
    #[error("invalid {field}: got {got}, expected {expected}")]
    InvalidParam { field: &'static str, got: String, expected: String },
    #[error("interrupted")]
    Cancelled,
}

/// Result alias of the models crate.
pub type Result<T> = std::result::Result<T, ModelError>;
