//! The decoder contract (DESIGN §5, deepinv's `model(y, physics)`): every decoder maps tap
//! images `y [B, M, H, W]` plus the [`Sensor`] (its `A [N, M, T]`, codes and spec) to transient cubes `[B, T, H, W]`
//! and/or the range of `K` returns `[B, K, H, W]`.
//!
//! Evaluation, `reconstruct`, inference and the demo see only [`Decoder`], so TVAL3, ADMM-Net
//! and the next decoders are interchangeable there. The sensor is an argument, not part of
//! the decoder: a learned decoder's data-consistency steps run on whatever `A` it is given (a
//! recalibrated, measured `A` included); its own training `A` comes with its run directory
//! ([`crate::runs`]).
//!
//! ```
//! use ndarray::Array4;
//! use std::sync::atomic::AtomicBool;
//! use tcsense_models::decoder::{Control, Decoder, Tval3Decoder};
//! use tcsense_models::Tval3Options;
//! use tcsense_sensor::codes::{CodeShape, Constraints};
//! use tcsense_sensor::generate::random_codes;
//! use tcsense_sensor::{Irf, Sampling, Sensor};
//!
//! let shape = CodeShape { bh: 2, bw: 2, taps: 4, length: 8, drain: false };
//! let codes = random_codes(shape, 607e6, Constraints { tap: true, ..Default::default() }, 1).unwrap();
//! let sensor = Sensor::ideal(codes, Sampling::Oversample(1), Irf::Ideal).unwrap();
//! let y = Array4::<f32>::from_elem((1, 4, 4, 4), 1.0); // [B, M, H, W]
//! let mut tval3 = Tval3Decoder::new(Tval3Options { maxit: 5, ..Default::default() }).unwrap();
//! let out = tval3.decode(y.view(), &sensor, &Control::quiet(&AtomicBool::new(false))).unwrap();
//! assert_eq!(out.cube.unwrap().dim(), (1, 8, 4, 4)); // [B, T, H, W]
//! ```

use ndarray::{Array, Array4, ArrayView, ArrayView4, Axis, Dimension};
use std::sync::atomic::{AtomicBool, Ordering};
use tcsense_sensor::{MeasurementMatrix, Sensor, SensorError};

use crate::tval3::{tval3, Tval3Options};
use crate::{ModelError, Result};

/// What a decoder returns for a batch.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Decoded {
    /// Transient cubes `[B, T, H, W]` (TVAL3, ADMM-Net).
    pub cube: Option<Array4<f32>>,
    /// Range of the `K` returns in metres, in arrival order, `[B, K, H, W]`; NaN where none
    /// (decoders that estimate depth directly).
    pub depth: Option<Array4<f32>>,
    /// Confidence in `[0, 1]`: of each return, `[B, K, H, W]`, next to `depth`; that the pixel
    /// holds a fluorophore, `[B, 1, H, W]`, next to `lifetime`.
    pub confidence: Option<Array4<f32>>,
    /// Lifetimes `[B, 4, H, W]`: the amplitude-weighted mean `τ_m`, the components `τ₁ ≤ τ₂`
    /// (s) and the amplitude fraction `α₁` of `τ₁`; NaN where the confidence is below one half
    /// (decoders that estimate lifetimes directly).
    pub lifetime: Option<Array4<f32>>,
    /// Intensity `[B, 1, H, W]`: the photo-charge of all taps, next to `lifetime`.
    pub intensity: Option<Array4<f32>>,
}

impl Decoded {
    /// No range and no lifetime where `unread` is set (a pixel with a tap clipped at the full
    /// well: no decoder can read it): its ranges and lifetimes NaN, their confidences 0. Cubes
    /// and intensities stay as decoded.
    ///
    /// # Shapes
    /// - `unread`: `[B, H, W]`, as the decoded maps
    pub fn without_pixels(&mut self, unread: &ndarray::ArrayView3<'_, bool>) {
        // (each frame's mask over every channel: [B, 1, H, W])
        let unread = unread.view().insert_axis(Axis(1));
        let blank = |maps: &mut Option<Array4<f32>>, value: f32| {
            if let Some(m) = maps {
                set_where(m, &unread, value);
            }
        };
        blank(&mut self.depth, f32::NAN);
        blank(&mut self.lifetime, f32::NAN);
        if self.depth.is_some() || self.lifetime.is_some() {
            blank(&mut self.confidence, 0.0);
        }
    }
}

/// `maps` set to `value` where `unread`, which spans their trailing axes (a frame's `[H, W]`
/// over `[C, H, W]` maps; `[B, 1, H, W]` over `[B, C, H, W]`).
pub fn set_where<D: Dimension, E: Dimension>(maps: &mut Array<f32, D>, unread: &ArrayView<'_, bool, E>, value: f32) {
    maps.zip_mut_with(unread, |v, &u| {
        if u {
            *v = value;
        }
    });
}

/// Where a decoder is in a batch, for progress display.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Step {
    /// Frame of the batch being decoded.
    pub frame: usize,
    /// Frames in the batch.
    pub frames: usize,
    /// Work done on this frame (iterations, stages …) out of `total`.
    pub done: usize,
    pub total: usize,
}

/// Progress reports and cancellation for a running decoder.
#[derive(Clone, Copy)]
pub struct Control<'a> {
    /// Set (e.g. by Ctrl-C) to stop; the decoder returns [`ModelError::Cancelled`].
    pub cancel: &'a AtomicBool,
    /// Called as the work advances.
    pub progress: &'a (dyn Fn(Step) + Sync),
}

impl<'a> Control<'a> {
    /// No progress display.
    pub fn quiet(cancel: &'a AtomicBool) -> Self {
        Control { cancel, progress: &|_| {} }
    }

    /// `Err(Cancelled)` once cancellation was asked for.
    pub fn check(&self) -> Result<()> {
        if self.cancel.load(Ordering::Relaxed) {
            Err(ModelError::Cancelled)
        } else {
            Ok(())
        }
    }
}

/// A decoder: tap images plus the sensor in, cubes and/or depth out.
pub trait Decoder: Send {
    /// A short name for tables and messages (`tval3`, `admm-net`).
    fn name(&self) -> &str;

    /// Reconstruct a batch. Implementations check `y` with [`check_measurements`] first.
    ///
    /// # Shapes
    /// - `y`: `[B, M, H, W]`, `sensor.matrix()`: `A [N, M, T]` → cube `[B, T, H, W]` and/or
    ///   depth and confidence `[B, K, H, W]`
    fn decode(&mut self, y: ArrayView4<'_, f32>, sensor: &Sensor, ctl: &Control<'_>) -> Result<Decoded>;
}

/// The checks every decoder makes on its input: `M` tap images for this sensor, a frame that
/// is a non-empty multiple of the block, at least one frame, finite values.
///
/// # Shapes
/// - `y`: `[B, M, H, W]`
pub fn check_measurements(y: &ArrayView4<'_, f32>, sensor: &MeasurementMatrix) -> Result<()> {
    let (b, m, h, w) = y.dim();
    let (bh, bw) = sensor.block();
    if b == 0 || m != sensor.taps() || h == 0 || w == 0 || h % bh != 0 || w % bw != 0 {
        return Err(ModelError::Sensor(SensorError::Shape {
            what: "measurements y".into(),
            got: y.shape().to_vec(),
            expected: format!("[B, M, H, W] with B ≥ 1, M = {} taps and H, W non-zero multiples of the {bh}x{bw} block", sensor.taps()),
        }));
    }
    tcsense_sensor::npy::ensure_usable(&y.view().into_dyn(), "measurements y")?;
    Ok(())
}

/// TVAL3 ([`crate::tval3`]) behind the contract, frame by frame.
#[derive(Debug, Clone)]
pub struct Tval3Decoder {
    pub options: Tval3Options,
}

impl Tval3Decoder {
    /// A TVAL3 decoder with checked options.
    pub fn new(options: Tval3Options) -> Result<Self> {
        options.validate()?;
        Ok(Tval3Decoder { options })
    }
}

impl Decoder for Tval3Decoder {
    fn name(&self) -> &str {
        "tval3"
    }

    fn decode(&mut self, y: ArrayView4<'_, f32>, sensor: &Sensor, ctl: &Control<'_>) -> Result<Decoded> {
        let sensor = sensor.matrix();
        check_measurements(&y, sensor)?;
        let (b, _, h, w) = y.dim();
        let plan = sensor.plan(h, w)?;
        let mut cube = Array4::zeros((b, sensor.bins(), h, w));
        for (i, mut out) in cube.outer_iter_mut().enumerate() {
            let progress = |it: usize, total: usize| (ctl.progress)(Step { frame: i, frames: b, done: it, total });
            let (x, _) = tval3(sensor, &plan, &y.index_axis(Axis(0), i), &self.options, &progress, ctl.cancel)?;
            out.assign(&x);
        }
        Ok(Decoded { cube: Some(cube), ..Default::default() })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The unread pixels lose their ranges, lifetimes and confidences, in every frame and
    /// channel; the others, the cube and the intensity keep theirs.
    #[test]
    fn unread_pixels_get_no_range_and_no_lifetime() {
        let maps = |c: usize| Some(Array4::from_shape_fn((2, c, 2, 2), |(b, k, i, j)| (b * 8 + k * 4 + i * 2 + j) as f32 + 1.0));
        let mut out = Decoded { cube: maps(3), depth: maps(2), confidence: maps(2), lifetime: None, intensity: maps(1) };
        let before = out.clone();
        let unread = ndarray::Array3::from_shape_fn((2, 2, 2), |(b, i, j)| (b, i, j) == (0, 1, 0) || (b, i, j) == (1, 0, 1));
        out.without_pixels(&unread.view());
        for ((b, k, i, j), &v) in out.depth.as_ref().unwrap().indexed_iter() {
            let c = out.confidence.as_ref().unwrap()[(b, k, i, j)];
            if unread[(b, i, j)] {
                assert!(v.is_nan() && c == 0.0, "{:?}", (b, k, i, j));
            } else {
                assert_eq!((v, c), (before.depth.as_ref().unwrap()[(b, k, i, j)], before.confidence.as_ref().unwrap()[(b, k, i, j)]));
            }
        }
        assert_eq!((&out.cube, &out.intensity), (&before.cube, &before.intensity));
        // lifetimes: all four channels
        let mut out = Decoded { lifetime: maps(4), confidence: maps(1), ..Default::default() };
        out.without_pixels(&unread.view());
        let l = out.lifetime.unwrap();
        assert!((0..4).all(|k| l[(0, k, 1, 0)].is_nan() && l[(1, k, 0, 1)].is_nan()) && l[(0, 0, 0, 0)] == 1.0);
        assert_eq!(out.confidence.unwrap()[(1, 0, 0, 1)], 0.0);
    }
}
