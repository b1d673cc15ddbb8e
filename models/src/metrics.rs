//! Reconstruction quality against the ground truth, as every decoder is scored (training
//! validation, `tcsense eval`, code selection): MSE and PSNR of cubes, and depth errors per
//! return with the detection rate.
//!
//! Cubes are compared as stored (the datasets scale each cube so that its largest voxel of
//! the ground truth is 1), so `MSE = mean((x̂ − x)²)` and `PSNR = 10·log₁₀(peak² / MSE)` with
//! `peak = max x`.

use ndarray::ArrayView3;
use serde::Serialize;

/// Mean squared error.
pub fn mse(est: &[f32], truth: &[f32]) -> f64 {
    let n = truth.len().max(1) as f64;
    est.iter().zip(truth).map(|(a, b)| ((a - b) as f64).powi(2)).sum::<f64>() / n
}

/// Peak signal-to-noise ratio (dB) against the truth's maximum; infinite for a perfect match.
pub fn psnr(est: &[f32], truth: &[f32]) -> f64 {
    let peak = truth.iter().fold(0f32, |m, &v| m.max(v)) as f64;
    let e = mse(est, truth);
    if e <= 0.0 {
        f64::INFINITY
    } else {
        10.0 * (peak * peak / e).log10()
    }
}

/// Depth errors of one bounce.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct DepthErrors {
    /// Pixels with a ground-truth return.
    pub truth: usize,
    /// Of those, pixels with an estimated return.
    pub detected: usize,
    pub rmse_m: f64,
    pub mae_m: f64,
    /// Pixels without a ground-truth return.
    pub empty: usize,
    /// Of those, pixels with an estimated return (a false alarm: e.g. a sheet that is not there).
    pub false_alarms: usize,
}

impl DepthErrors {
    /// Fraction of ground-truth returns that were detected.
    pub fn detection_rate(&self) -> f64 {
        if self.truth == 0 {
            0.0
        } else {
            self.detected as f64 / self.truth as f64
        }
    }

    /// Fraction of the pixels without a ground-truth return that got one.
    pub fn false_alarm_rate(&self) -> f64 {
        if self.empty == 0 {
            0.0
        } else {
            self.false_alarms as f64 / self.empty as f64
        }
    }
}

/// Depth errors per bounce between estimated and true range maps `[K, H, W]` (NaN = none).
/// Errors are over pixels where both have a return; an estimate where the truth has none is a
/// false alarm.
pub fn depth_errors(est: &ArrayView3<'_, f32>, truth: &ArrayView3<'_, f32>) -> Vec<DepthErrors> {
    let k = truth.dim().0.min(est.dim().0);
    (0..k)
        .map(|b| {
            let mut e = DepthErrors::default();
            let (mut se, mut ae) = (0f64, 0f64);
            for (t, x) in truth.index_axis(ndarray::Axis(0), b).iter().zip(est.index_axis(ndarray::Axis(0), b).iter()) {
                if t.is_finite() {
                    e.truth += 1;
                    if x.is_finite() {
                        e.detected += 1;
                        let d = (x - t) as f64;
                        se += d * d;
                        ae += d.abs();
                    }
                } else {
                    e.empty += 1;
                    e.false_alarms += usize::from(x.is_finite());
                }
            }
            if e.detected > 0 {
                e.rmse_m = (se / e.detected as f64).sqrt();
                e.mae_m = ae / e.detected as f64;
            }
            e
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn values() {
        assert!((mse(&[1.0, 2.0], &[1.0, 4.0]) - 2.0).abs() < 1e-12);
        assert!((psnr(&[0.0, 0.9], &[0.0, 1.0]) - 10.0 * (1.0f64 / 0.005).log10()).abs() < 1e-4);
        assert_eq!(psnr(&[0.5, 1.0], &[0.5, 1.0]), f64::INFINITY);
    }

    #[test]
    fn depth_errors_count_misses_and_false_alarms() {
        let nan = f32::NAN;
        // 2 bounces of 1×4 pixels
        let truth = ndarray::Array3::from_shape_vec((2, 1, 4), vec![1.0, 2.0, 3.0, nan, nan, nan, 5.0, nan]).unwrap();
        let est = ndarray::Array3::from_shape_vec((2, 1, 4), vec![1.5, nan, 2.0, 4.0, 6.0, nan, 5.5, 7.0]).unwrap();
        let e = depth_errors(&est.view(), &truth.view());
        assert_eq!((e[0].truth, e[0].detected, e[0].empty, e[0].false_alarms), (3, 2, 1, 1));
        assert!((e[0].mae_m - 0.75).abs() < 1e-12 && (e[0].rmse_m - (1.25f64 / 2.0).sqrt()).abs() < 1e-12);
        assert_eq!((e[1].truth, e[1].detected, e[1].empty, e[1].false_alarms), (1, 1, 3, 2));
        assert!((e[1].false_alarm_rate() - 2.0 / 3.0).abs() < 1e-12 && (e[1].mae_m - 0.5).abs() < 1e-12);
    }
}
