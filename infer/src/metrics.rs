//! Evaluation metrics: the cube metrics every decoder is scored with (MSE, PSNR, from
//! `tcsense_models::metrics`), depth errors per bounce with the detection rate, and the
//! lifetime error.

pub use tcsense_models::metrics::{depth_errors, mse, psnr, DepthErrors};

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
