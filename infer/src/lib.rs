//! `tcsense-infer`: what users want from a reconstructed cube `x̂ [T, H, W]`.
//!
//! - [`products`]: peak detection with parabolic sub-bin refinement (several returns per
//!   pixel for multipath), depth maps `d = c·t/2`, point clouds (PLY), per-pixel lifetimes
//!   by an exponential fit of the decay after the peak, phasor coordinates, waveform plots.
//! - [`metrics`]: MSE, PSNR, depth RMSE/MAE per bounce with detection rate, lifetime MAE.

pub mod metrics;
pub mod products;
pub mod design;
pub mod chart;
pub mod eval;
