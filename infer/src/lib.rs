//! `tcsense-infer`: from decoders to what users want — evaluation of any decoder through the
//! contract, the products of a reconstructed cube, and code selection.
//!
//! - [`registry`]: every decoder opened by name (`tval3`, `depth-fit`, `admm-net:RUN`,
//!   `onnx:MODEL.onnx` …), the one table that `reconstruct`, `eval`, the demo and Python use.
//! - [`decode`]: decoding a file of tap images with any decoder, the one path `reconstruct`
//!   and Python share.
//! - [`stream`]: the streaming `infer` — frames from a file or directory through an exported
//!   model to products on disk, in bounded memory.
//! - [`bounds`]: the Cramér–Rao bounds against the spread of the project's own estimators.
//! - [`calibration_report`]: the report page of a calibration.
//! - [`eval`]: decoders evaluated side by side
//!   on a dataset split with the same measurements ([`eval::evaluate`]), one [`eval::EvalRow`]
//!   per decoder; [`curves`]: the photon-efficiency curves of a light ladder
//!   ([`eval::evaluate_ladder`]) beside the codes' Cramér–Rao bound, for `eval --plot` and the
//!   demo's report.
//! - [`products`]: peak detection with parabolic sub-bin refinement (several returns per
//!   pixel for multipath), depth maps `d = c·t/2`, point clouds (PLY), waveform plots.
//! - [`fitted`]: the fits of `tcsense_fits` behind the decoder contract — `depth-fit`,
//!   `lifetime-fit`, and ranges from any cube decoder, its peaks refined by the fit in the tap
//!   domain (`NAME+fit`).
//! - [`metrics`]: MSE, PSNR, depth RMSE/MAE per bounce with detection rate, lifetime MAE.
//! - [`selection`]: code selection — the TVAL3 MSE of a code set over a dataset, the best of
//!   random candidates, and the constraint settings of the paper's Table 1.
//! - [`figures`]: the figures (plotters, bundled font): charts, maps with colour bars, codes,
//!   waveforms, point clouds, phasors; [`report`]: the HTML report of `tcsense demo`.
//! - [`speed`]: frames/s of decoders on a stream at the sensor's frame size, beside their
//!   accuracy on a light ladder (`tcsense bench decoders`).
//! - [`timing`]: time per frame of exported models (ONNX Runtime) and their runs (burn).
//! - [`onnx`]: export of trained runs to ONNX (hand-built graphs, opset 17) with their codes
//!   and sensor model in the metadata.
//! - [`runtime`]: exported models through ONNX Runtime (`ort`, the library loaded at run
//!   time), also behind the decoder contract.
//!
//! Errors are [`InferError`]; this crate never depends on the training crate.

pub mod bounds;
pub mod calibration_report;
pub mod curves;
pub mod decode;
pub mod error;
pub mod eval;
pub mod figures;
pub mod fitted;
pub mod metrics;
pub mod onnx;
pub mod products;
pub mod registry;
pub mod report;
pub mod runtime;
pub mod selection;
pub mod speed;
pub mod stream;
pub mod timing;

pub use error::{InferError, Result};
