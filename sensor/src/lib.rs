//! `tcsense-sensor`: the physics of ultrafast time-compressive CMOS image sensors.
//!
//! A multitap charge modulator multiplies the light arriving at each subpixel by binary
//! exposure codes `g[n][m][l]` and integrates it into `M` taps. On the reconstruction grid
//! of `T = L·K` bins this is, per pixel, `y = A x` with a small `M × T` matrix `A[n]` that
//! repeats over the pixel blocks (paper eqs. 1–4):
//!
//! `y[m, X, Y] = Σ_j A[n(X,Y)][m][j] · x[j, X, Y]`, `n(X, Y) = (X mod bh)·bw + (Y mod bw)`.
//!
//! Modules: [`params`] (checked sensor parameters), [`codes`] (exposure codes, JSON, the
//! constraint checker), [`generate`] (random codes under constraints), [`matrix`] (ideal,
//! physical, heterodyne or measured `A`, and its Gram matrices `AAᵀ`), [`operator`] (fast
//! forward/adjoint), [`noise`] (shot, read, clipping, ADC), [`measure`] (the one physics
//! entry, `y = quantise(clip(noise(A x)))`), [`export`] (the sensor's code memory), [`show`]
//! (PNG pictures of codes), [`npy`] (`.npy` I/O and atomic writes), [`output`] (a command's
//! outputs written all or none), [`waveform`] (the subpixel index, the periodic decay, the IRF
//! kernel, `erf` and IRF descriptions every crate shares).
//!
//! The sensor as one object and its life: [`sensor`] (`Sensor`: codes, spec, nominal `A`,
//! calibration, non-idealities, built once from one description), [`nonideal`] (a real
//! sensor's departures from the model), [`sweep`] (laser-delay sweeps), [`calibration`]
//! (dark and gain maps and the measured `A` from a sweep), [`sidecar`] (`y.meta.json`: the
//! sensor that took a file of tap images). Codes judged and made: [`identify`]
//! (identifiability and Cramér–Rao bounds in closed form), [`design`] (codes designed by
//! identifiability), [`project`] (learned code probabilities projected exactly onto the
//! constraints). Plumbing: [`digest`] (stable fingerprints), [`json`] (strict JSON reading),
//! [`mem`] (up-front memory checks), [`error`].

pub mod calibration;
pub mod codes;
pub mod design;
pub mod digest;
pub mod error;
pub mod export;
pub mod generate;
pub mod identify;
pub mod json;
pub mod matrix;
pub mod measure;
pub mod mem;
pub mod noise;
pub mod nonideal;
pub mod npy;
pub mod operator;
pub mod output;
pub mod params;
pub mod project;
pub mod sensor;
pub mod show;
pub mod sidecar;
pub mod sweep;
pub mod waveform;

pub use codes::{CodeShape, Codes, Constraints, Violation};
pub use error::{Result, SensorError};
pub use matrix::MeasurementMatrix;
pub use operator::FramePlan;
pub use params::{Irf, NoiseParams, Sampling, SensorParams, SensorSpec, C};
pub use sensor::{Sensor, SensorModel, Units};
