//! Reconstruction quality of a cube against its ground truth, as every decoder is scored
//! (training validation, `tcsense eval`, code selection).
//!
//! Cubes are compared as stored (the datasets scale each cube so that its largest voxel of
//! the ground truth is 1), so `MSE = mean((x̂ − x)²)` and `PSNR = 10·log₁₀(peak² / MSE)` with
//! `peak = max x`.

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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn values() {
        assert!((mse(&[1.0, 2.0], &[1.0, 4.0]) - 2.0).abs() < 1e-12);
        assert!((psnr(&[0.0, 0.9], &[0.0, 1.0]) - 10.0 * (1.0f64 / 0.005).log10()).abs() < 1e-4);
        assert_eq!(psnr(&[0.5, 1.0], &[0.5, 1.0]), f64::INFINITY);
    }
}
