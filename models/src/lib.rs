//! `tcsense-models`: decoders that recover the transient cube `x̂ [T, H, W]` from tap images
//! `y [M, H, W]` and the sensor model.
//!
//! - [`tval3`]: TV minimisation by augmented Lagrangian with alternating shrinkage and a
//!   nonmonotone Barzilai–Borwein line search (Li, Yin, Jiang, Zhang), 3-D TV over
//!   `(x, y, t)` with per-axis weights — the paper's iterative baseline.
//! - [`admm`]: ADMM-Net, `S` unrolled stages with an exact per-pixel data-consistency step
//!   and a residual CNN prior (burn modules; trained by `tcsense-train`).
//! - [`conv`], [`conv_op`]: the prior's 3×3 convolution as im2col GEMM kernels, forward and
//!   both gradients, registered as a burn backend extension with a handwritten backward.
//! - [`pixel`]: the per-pixel sensor operators (`A`, `Aᵀ`, back-projection, data consistency)
//!   as fused frame-layout kernels, also burn extension ops with handwritten backward passes.
//! - [`bench`]: those kernels timed against burn-flex's generic paths.

pub mod admm;
pub mod bench;
pub mod conv;
pub mod conv_op;
pub mod pixel;
pub mod tval3;

pub use admm::{AdmmNet, AdmmNetConfig, SensorTensors};
/// The burn device type (CPU `Device::flex()` by default).
pub use burn::tensor::Device;
pub use tval3::{tval3, TvNorm, Tval3Options, Tval3Report};

/// Errors of the models crate.
#[derive(Debug, thiserror::Error)]
pub enum ModelError {
    #[error(transparent)]
    Sensor(#[from] tcsense_sensor::SensorError),
    #[error("invalid {field}: got {got}, expected {expected}")]
    InvalidParam { field: &'static str, got: String, expected: String },
    #[error("interrupted")]
    Cancelled,
}

/// Result alias of the models crate.
pub type Result<T> = std::result::Result<T, ModelError>;
