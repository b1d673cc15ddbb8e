//! The one physics entry (DESIGN §3, deepinv's `physics(x)`):
//!
//! `y = measure(x) = quantise(clip(noise(A x)))`
//!
//! — the block-diagonal forward operator ([`crate::operator`]) followed, when noise is on,
//! by the noise model ([`crate::noise`]: scale to electrons, Poisson shot noise, Gaussian read
//! noise, clipping at full well, ADC quantisation), seeded. `tcsense simulate`, training and
//! evaluation all measure through here, so they simulate the same sensor.
//!
//! ```
//! use ndarray::Array4;
//! use tcsense_sensor::codes::{CodeShape, Constraints};
//! use tcsense_sensor::generate::random_codes;
//! use tcsense_sensor::measure::measure_batch;
//! use tcsense_sensor::{MeasurementMatrix, NoiseParams, SensorParams};
//!
//! let shape = CodeShape { bh: 2, bw: 2, taps: 4, length: 8, drain: false };
//! let codes = random_codes(shape, 607e6, Constraints { tap: true, ..Default::default() }, 1).unwrap();
//! let a = MeasurementMatrix::synthesize(&codes, &SensorParams::from_codes(&codes).validate().unwrap()).unwrap();
//! let plan = a.plan(4, 4).unwrap();
//! let x = Array4::<f32>::from_elem((2, 8, 4, 4), 0.5); // [B, T, H, W]
//! let clean = measure_batch(&plan, &x.view(), None, 0).unwrap(); // [B, M, H, W]
//! let noisy = measure_batch(&plan, &x.view(), Some(&NoiseParams::default()), 7).unwrap();
//! assert_eq!(clean.dim(), (2, 4, 4, 4));
//! assert_eq!(noisy, measure_batch(&plan, &x.view(), Some(&NoiseParams::default()), 7).unwrap());
//! ```

use ndarray::{Array, Array4, ArrayD, ArrayView, ArrayView4, ArrayViewD, Axis, Ix3, Ix4, RemoveAxis};

use crate::error::{invalid, Result};
use crate::noise::{add_noise, Exposure, NoisyMeasurement};
use crate::operator::FramePlan;
use crate::params::NoiseParams;

/// Simulated tap images.
#[derive(Debug, Clone)]
pub enum Measurement {
    /// `A x`, noise off.
    Noiseless(ArrayD<f32>),
    /// `quantise(clip(noise(A x)))`, in electrons, with the scale used.
    Noisy(NoisyMeasurement),
}

impl Measurement {
    /// The tap images in the units of `A x` (noise rescaled back by the electrons per unit).
    pub fn into_input_units(self) -> ArrayD<f32> {
        match self {
            Measurement::Noiseless(y) => y,
            Measurement::Noisy(n) => n.in_input_units(),
        }
    }

    /// The pixels with a tap clipped at the full well `full_well_e` (electrons; noiseless
    /// measurements clip nothing): a pixel none of whose taps can be read.
    ///
    /// # Shapes
    /// - `[M, H, W]` → `[H, W]`, or `[B, M, H, W]` → `[B, H, W]`
    pub fn clipped(&self, full_well_e: f64) -> Option<ArrayD<bool>> {
        match self {
            Measurement::Noiseless(_) => None,
            Measurement::Noisy(n) => Some(clipped_pixels(&n.electrons.view(), full_well_e)),
        }
    }
}

/// The pixels of electron counts `e` with a tap at the full well `full_well_e` or above.
///
/// # Shapes
/// - `e`: `[M, H, W]` → `[H, W]`, or `[B, M, H, W]` → `[B, H, W]`
pub fn clipped_pixels(e: &ArrayViewD<'_, f32>, full_well_e: f64) -> ArrayD<bool> {
    at_clip_level(e, full_well_e as f32)
}

/// The pixels of tap images `y` with a tap at `level` or above (within a millionth: a clip,
/// quantised or rescaled, lands there), in `y`'s units: what no decoder can read.
///
/// # Shapes
/// - `y`: `[M, H, W]` → `[H, W]`, or `[B, M, H, W]` → `[B, H, W]`
pub fn at_clip_level<D: RemoveAxis>(y: &ArrayView<'_, f32, D>, level: f32) -> Array<bool, D::Smaller> {
    let level = level * (1.0 - 1e-6);
    let taps = Axis(y.ndim() - 3);
    y.map_axis(taps, |t| t.iter().any(|&v| v >= level))
}

/// Measure cubes `x` (`[T, H, W]` or a batch `[B, T, H, W]`) with `plan`'s sensor; with
/// `noise`, seeded by `seed` and scaled to electrons by `exposure` (for a batch, `Auto`
/// scales the brightest tap of the whole batch).
///
/// # Shapes
/// - `x`: `[T, H, W]` → `[M, H, W]`, or `[B, T, H, W]` → `[B, M, H, W]`
pub fn measure(
    plan: &FramePlan,
    x: &ArrayViewD<'_, f32>,
    noise: Option<&NoiseParams>,
    exposure: Exposure,
    seed: u64,
) -> Result<Measurement> {
    let y = match x.ndim() {
        3 => plan
            .forward(&x.view().into_dimensionality::<Ix3>().map_err(|e| invalid("cube", format!("{:?}", x.shape()), e.to_string()))?)?
            .into_dyn(),
        4 => plan
            .forward_batch(&x.view().into_dimensionality::<Ix4>().map_err(|e| invalid("cube", format!("{:?}", x.shape()), e.to_string()))?)?
            .into_dyn(),
        _ => return Err(invalid("cube", format!("{:?}", x.shape()), "[T, H, W] or [B, T, H, W]")),
    };
    match noise {
        None => Ok(Measurement::Noiseless(y)),
        Some(n) => Ok(Measurement::Noisy(add_noise(&y.view(), n, exposure, seed)?)),
    }
}

/// [`measure`] for a batch, in the units of `A x`, with the brightest tap of the batch at the
/// noise model's `signal_fraction` of full well: what training and evaluation feed decoders.
///
/// # Shapes
/// - `x`: `[B, T, H, W]` → `[B, M, H, W]`
pub fn measure_batch(plan: &FramePlan, x: &ArrayView4<'_, f32>, noise: Option<&NoiseParams>, seed: u64) -> Result<Array4<f32>> {
    measure_batch_at(plan, x, noise, Exposure::Auto, seed)
}

/// [`measure_batch`] with the exposure given (e.g. [`signal_exposure`] of the cube before
/// ambient light was added to it).
///
/// # Shapes
/// - `x`: `[B, T, H, W]` → `[B, M, H, W]`
pub fn measure_batch_at(
    plan: &FramePlan,
    x: &ArrayView4<'_, f32>,
    noise: Option<&NoiseParams>,
    exposure: Exposure,
    seed: u64,
) -> Result<Array4<f32>> {
    let y = measure(plan, &x.view().into_dyn(), noise, exposure, seed)?.into_input_units();
    y.into_dimensionality::<Ix4>().map_err(|e| invalid("measurements", "a batch".to_string(), e.to_string()))
}

/// The exposure that brings the brightest tap of `A x` to `noise`'s `signal_fraction` of full
/// well: the signal's own, kept when ambient light is then added to `x` (ambient light adds
/// photons and their shot noise; it does not dim the signal). What `eval --sbr` and training's
/// ambient light measure with.
///
/// # Shapes
/// - `x`: `[B, T, H, W]`
pub fn signal_exposure(plan: &FramePlan, x: &ArrayView4<'_, f32>, noise: &NoiseParams) -> Result<Exposure> {
    let peak = plan.forward_batch(x)?.fold(0f32, |m, &v| m.max(v));
    Ok(Exposure::ElectronsPerUnit(Exposure::Auto.electrons_per_unit(peak, noise)?))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::codes::{CodeShape, Constraints};
    use crate::generate::random_codes;
    use crate::{MeasurementMatrix, SensorParams};
    use ndarray::{Array3, Axis};

    #[test]
    fn noiseless_is_a_x_and_noise_is_seeded_per_call() {
        let shape = CodeShape { bh: 2, bw: 2, taps: 4, length: 8, drain: false };
        let codes = random_codes(shape, 607e6, Constraints { tap: true, ..Default::default() }, 5).unwrap();
        let a = MeasurementMatrix::synthesize(&codes, &SensorParams::from_codes(&codes).validate().unwrap()).unwrap();
        let plan = a.plan(4, 6).unwrap();
        let x = Array3::from_shape_fn((8, 4, 6), |(j, r, c)| ((j * 5 + r * 3 + c) % 7) as f32 / 7.0);
        let clean = measure(&plan, &x.view().into_dyn(), None, Exposure::Auto, 0).unwrap().into_input_units();
        assert_eq!(clean, plan.forward(&x.view()).unwrap().into_dyn());
        let noise = NoiseParams::default();
        let xb = x.clone().insert_axis(Axis(0)); // [1, T, H, W]
        let a1 = measure_batch(&plan, &xb.view(), Some(&noise), 3).unwrap();
        let a2 = measure_batch(&plan, &xb.view(), Some(&noise), 3).unwrap();
        let b = measure_batch(&plan, &xb.view(), Some(&noise), 4).unwrap();
        assert_eq!(a1, a2, "same seed, same bytes");
        assert_ne!(a1, b, "another seed, other noise");
        // the noisy taps scatter around A x: relative error of a few percent at 80 % of full well
        let rel = (&a1.index_axis(Axis(0), 0) - &clean).mapv(|v| v * v).sum().sqrt() / clean.mapv(|v| v * v).sum().sqrt();
        assert!(rel > 1e-4 && rel < 0.1, "relative noise {rel}");
        // the same frame measured alone ([M, H, W]) gets the same noise as a batch of one
        let single = measure(&plan, &x.view().into_dyn(), Some(&noise), Exposure::Auto, 3).unwrap().into_input_units();
        assert_eq!(single, a1.index_axis(Axis(0), 0).into_dyn());
        assert!(measure(&plan, &ndarray::Array2::<f32>::zeros((8, 4)).view().into_dyn(), None, Exposure::Auto, 0).is_err());
    }

    /// A pixel with one tap at the full well (quantised there or clipped) is clipped; one just
    /// below it, or noiseless measurements, are not.
    #[test]
    fn the_clipped_pixels_are_those_with_a_tap_at_the_full_well() {
        let fw = 20_000.0;
        let mut e = ndarray::Array4::<f32>::from_elem((2, 4, 2, 3), 100.0); // [B, M, H, W]
        e[(0, 2, 0, 1)] = fw as f32;
        e[(1, 0, 1, 2)] = fw as f32 * (1.0 - 1e-7); // the clip through a rounding
        e[(1, 3, 0, 0)] = fw as f32 * 0.999;
        let c = clipped_pixels(&e.view().into_dyn(), fw);
        assert_eq!(c.shape(), &[2, 2, 3]);
        let set: Vec<usize> = c.iter().enumerate().filter(|(_, &v)| v).map(|(i, _)| i).collect();
        assert_eq!(set, vec![1, 6 + 5], "[0, 0, 1] and [1, 1, 2] of [2, 2, 3]");
        let frame = clipped_pixels(&e.index_axis(Axis(0), 0).into_dyn(), fw); // [M, H, W] → [H, W]
        assert_eq!(frame.shape(), &[2, 3]);
        assert!(Measurement::Noiseless(e.into_dyn()).clipped(fw).is_none());
    }
}
