//! Evaluation metrics: the cube metrics every decoder is scored with (MSE, PSNR, from
//! `tcsense_models::metrics`), depth errors per bounce with the detection rate, and the
//! lifetime error.

use ndarray::ArrayView3;
pub use tcsense_models::metrics::{mse, psnr};
use serde::Serialize;

/// Depth errors of one bounce.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct DepthErrors {
    /// Pixels with a ground-truth return.
    pub truth: usize,
    /// Of those, pixels with an estimated return.
    pub detected: usize,
    pub rmse_m: f64,
    pub mae_m: f64,
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
}

/// Depth errors per bounce between estimated and true range maps `[K, H, W]` (NaN = none).
/// Errors are over pixels where both have a return.
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

/// Mean absolute lifetime error (s) over pixels where both are finite; `(mae, pixels)`.
pub fn lifetime_mae(est: &[f32], truth: &[f32]) -> (f64, usize) {
    let (mut s, mut n) = (0f64, 0usize);
    for (a, b) in est.iter().zip(truth) {
        if a.is_finite() && b.is_finite() {
            s += ((a - b) as f64).abs();
            n += 1;
        }
    }
    (if n > 0 { s / n as f64 } else { f64::NAN }, n)
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array3;

    #[test]
    fn values() {
        let mut t = Array3::<f32>::from_elem((2, 1, 3), f32::NAN);
        let mut e = Array3::<f32>::from_elem((2, 1, 3), f32::NAN);
        t[(0, 0, 0)] = 1.0;
        t[(0, 0, 1)] = 2.0;
        e[(0, 0, 0)] = 1.5;
        t[(1, 0, 2)] = 3.0;
        e[(1, 0, 2)] = 2.0;
        let d = depth_errors(&e.view(), &t.view());
        assert_eq!((d[0].truth, d[0].detected), (2, 1));
        assert!((d[0].rmse_m - 0.5).abs() < 1e-6 && (d[1].mae_m - 1.0).abs() < 1e-6);
        assert!((d[0].detection_rate() - 0.5).abs() < 1e-12);
        assert_eq!(lifetime_mae(&[1.0, f32::NAN], &[1.5, 2.0]), (0.5, 1));
    }
}
