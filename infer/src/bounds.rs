//! The Cramér–Rao bounds of [`tcsense_sensor::identify`] against the empirical spread of the
//! project's own estimators on noisy simulated pixels:
//!
//! - the range fit in the tap domain ([`tcsense_fits::range::refine_ranges`], its default
//!   3×3 window, started at the true range) on a flat frame whose every pixel has one return at
//!   the same delay;
//! - the fit to the taps ([`tcsense_fits::lifetime_taps::fit_taps`], its 3×3 window, the onset given) on a
//!   flat frame of one lifetime.
//!
//! The frames are noiseless `A x` in electrons (the bounds' `photons` and `ambient`) through the
//! sensor's noise model (Poisson shot noise and Gaussian read noise, no clipping nor ADC), so
//! the only difference between bound and spread is the estimator. Pixels within a window's
//! reach of the border are left out; each pixel is compared with the bound of its own window
//! (the numbers of each subpixel type it holds), and the table gives the root-mean-square of
//! both over the frame.

use ndarray::{Array3, Array4, Axis};
use tcsense_fits::range::{refine_ranges, RangeFitOptions};
use tcsense_sensor::identify::{self, Columns, Light};
use tcsense_sensor::noise::{add_noise, Exposure};
use tcsense_sensor::waveform::{decay_unit_sum, Cycle};
use tcsense_sensor::{MeasurementMatrix, NoiseParams, C};

use crate::Result;
use tcsense_fits::lifetime_taps::{fit_taps, TapFitOptions};

/// Window of both estimators.
const WINDOW: usize = 3;

/// One row of a validation: the bound and the estimator's spread at one delay or lifetime.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Check {
    /// The delay (bins) or lifetime (s) simulated.
    pub at: f64,
    /// RMS over the pixels of the bound of each pixel's window (bins or s).
    pub bound: f64,
    /// RMS deviation of the estimates from the truth (bins or s).
    pub spread: f64,
    /// Mean deviation (bias) of the estimates.
    pub bias: f64,
    /// Pixels compared.
    pub pixels: usize,
}

impl Check {
    /// `spread / bound`: 1 for an efficient estimator.
    pub fn ratio(&self) -> f64 {
        self.spread / self.bound
    }
}

fn noise_of(light: &Light) -> NoiseParams {
    NoiseParams { full_well_e: 1e12, read_noise_e: light.read_noise_e, signal_fraction: 1.0, adc_bits: 0 }
}

/// `y = A x` of a flat `size × size` frame whose every pixel holds the transient `x [T]`,
/// through the sensor's operator.
///
/// # Shapes
/// - `x`: `[T]` → `[M, size, size]`
fn flat_frame(a: &MeasurementMatrix, x: &[f64], size: usize) -> Result<Array3<f32>> {
    let cube = Array4::from_shape_fn((1, x.len(), size, size), |(_, j, _, _)| x[j] as f32);
    Ok(a.plan(size, size)?.forward_batch(&cube.view())?.index_axis_move(Axis(0), 0))
}

/// The inner pixels `(i, j)` of a frame, with the bound weights of their window.
fn inner(size: usize, block: (usize, usize)) -> Vec<(usize, usize, Vec<f64>)> {
    let r = WINDOW / 2;
    (r..size - r)
        .flat_map(|i| (r..size - r).map(move |j| (i, j)))
        .map(|(i, j)| (i, j, identify::window_weights(block, WINDOW, tcsense_sensor::waveform::subpixel(i, j, block))))
        .collect()
}

fn summarise(at: f64, pairs: &[(f64, f64)]) -> Check {
    let n = pairs.len().max(1) as f64;
    let bound = (pairs.iter().map(|p| p.0 * p.0).sum::<f64>() / n).sqrt();
    let spread = (pairs.iter().map(|p| p.1 * p.1).sum::<f64>() / n).sqrt();
    let bias = pairs.iter().map(|p| p.1).sum::<f64>() / n;
    Check { at, bound, spread, bias, pixels: pairs.len() }
}

/// The range bound against the range fit at each delay of `delays_bins`, on `size × size`
/// frames (one per delay, noise seeded from `seed` and the delay's index).
pub fn validate_range(a: &MeasurementMatrix, light: &Light, delays_bins: &[f64], size: usize, seed: u64) -> Result<Vec<Check>> {
    let cols = Columns::new(a, 1);
    let t = a.bins();
    let metres_per_bin = C * a.bin_width_s() / 2.0;
    let pixels = inner(size, a.block());
    let mut out = Vec::new();
    for (di, &tau) in delays_bins.iter().enumerate() {
        // the datasets' sub-bin impulse at τ plus the ambient level
        let u = tau - 0.5;
        let t0 = u.floor();
        let f = u - t0;
        let t0 = (t0 as i64).rem_euclid(t as i64) as usize;
        let mut x = vec![light.ambient / t as f64; t];
        x[t0] += light.photons * (1.0 - f);
        x[(t0 + 1) % t] += light.photons * f;
        let y = flat_frame(a, &x, size)?;
        let noisy = add_noise(
            &y.view().into_dyn(),
            &noise_of(light),
            Exposure::ElectronsPerUnit(1.0),
            tcsense_sensor::noise::derive_seed(seed, di as u64),
        )?;
        let y4 = noisy
            .electrons
            .into_dimensionality::<ndarray::Ix3>()
            .map_err(|e| crate::InferError::InvalidParam { field: "frame", got: e.to_string(), expected: "[M, H, W]".into() })?
            .insert_axis(Axis(0));
        let mut depth = Array4::from_elem((1, 1, size, size), (tau * metres_per_bin) as f32);
        refine_ranges(y4.view(), a, &mut depth, &RangeFitOptions::default());
        let pairs: Vec<(f64, f64)> = pixels
            .iter()
            .map(|(i, j, w)| {
                let est = depth[(0, 0, *i, *j)] as f64 / metres_per_bin;
                let mut e = (est - tau).rem_euclid(t as f64);
                if e > t as f64 / 2.0 {
                    e -= t as f64;
                }
                (identify::range_bound_at(&cols, light, tau, w), e)
            })
            .collect();
        out.push(summarise(tau, &pairs));
    }
    Ok(out)
}

/// The lifetime bound (onset known) against the fit to the taps for each lifetime of `taus_s`,
/// decays starting at `onset_s`, on `size × size` frames.
pub fn validate_lifetime(
    a: &MeasurementMatrix,
    k: usize,
    light: &Light,
    taus_s: &[f64],
    onset_s: f64,
    size: usize,
    seed: u64,
) -> Result<Vec<Check>> {
    let cols = Columns::new(a, k);
    let t = a.bins();
    let pixels = inner(size, a.block());
    let opts = TapFitOptions {
        onset_s: Some(onset_s),
        irf_fwhm_s: vec![0.0],
        window: WINDOW,
        points: 192,
        tau_range_s: [0.05e-9, 30e-9],
        ..Default::default()
    };
    let mut out = Vec::new();
    for (ti, &tau) in taus_s.iter().enumerate() {
        let d = decay_unit_sum(Cycle::new(t, a.bin_width_s()), tau, onset_s);
        let x: Vec<f64> = d.iter().map(|v| light.photons * v + light.ambient / t as f64).collect();
        let y = flat_frame(a, &x, size)?;
        let noisy = add_noise(
            &y.view().into_dyn(),
            &noise_of(light),
            Exposure::ElectronsPerUnit(1.0),
            tcsense_sensor::noise::derive_seed(seed, ti as u64),
        )?;
        let y3 = noisy.electrons.into_dimensionality::<ndarray::Ix3>().map_err(|e| crate::InferError::InvalidParam {
            field: "frame",
            got: e.to_string(),
            expected: "[M, H, W]".into(),
        })?;
        let fit = fit_taps(&y3.view(), a, &opts);
        let pairs: Vec<(f64, f64)> = pixels
            .iter()
            .map(|(i, j, w)| (identify::lifetime_bound_at(&cols, light, tau, onset_s, w).0, fit.lifetime[(*i, *j)] as f64 - tau))
            .collect();
        out.push(summarise(tau, &pairs));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use tcsense_sensor::{generate, Irf, Sampling, SensorParams};

    const PHYSICAL: Irf = Irf::Physical { laser_fwhm_s: 2.55e-9, tap_tau_s: 0.3e-9 };

    fn matrix(sampling: Sampling) -> MeasurementMatrix {
        // codes with no alias near the delays tested (the zoo's learned LiDAR codes are 0.54
        // apart at best; seed 4's are fine for a local fit started at the truth)
        let codes = generate::prototype_codes(4).unwrap();
        let spec = SensorParams { irf: PHYSICAL, sampling, ..SensorParams::from_codes(&codes) }.validate().unwrap();
        MeasurementMatrix::synthesize(&codes, &spec).unwrap()
    }

    /// The range fit at a high photon count is within 25 % of the bound: the bound and the
    /// estimator agree on what the taps hold (a wrong derivative, a missing nuisance
    /// parameter or a wrong noise model would each move the ratio far from 1).
    #[test]
    fn range_fit_spread_is_near_the_bound() {
        let a = matrix(Sampling::Oversample(1));
        let light = Light { photons: 20_000.0, ambient: 500.0, read_noise_e: 40.0 };
        let checks = validate_range(&a, &light, &[7.3, 16.8], 24, 5).unwrap();
        for c in &checks {
            assert!((0.75..1.25).contains(&c.ratio()), "{c:?} ratio {}", c.ratio());
        }
    }

    #[test]
    fn tap_fit_spread_is_near_the_lifetime_bound() {
        let a = matrix(Sampling::Heterodyne(8));
        let light = Light { photons: 20_000.0, ambient: 500.0, read_noise_e: 40.0 };
        let checks = validate_lifetime(&a, 8, &light, &[1.5e-9, 4e-9], 3e-9, 24, 5).unwrap();
        for c in &checks {
            assert!((0.75..1.25).contains(&c.ratio()), "{c:?} ratio {}", c.ratio());
        }
    }
}
