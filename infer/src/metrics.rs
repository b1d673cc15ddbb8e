//! Evaluation metrics: the cube metrics every decoder is scored with (MSE, PSNR, from
//! `tcsense_models::metrics`), depth errors per bounce with the detection rate, and the
//! lifetime error.

use ndarray::ArrayView2;
use tcsense_datasets::flim::holds_fluorophore;
pub use tcsense_models::metrics::{depth_errors, mse, psnr, DepthErrors};

/// Errors of a mean-lifetime map against the truth, summed over items: over the pixels that
/// hold a fluorophore ([`holds_fluorophore`] with the true intensity; without it every pixel
/// with a true lifetime), the absolute error where a lifetime was estimated, the same weighted
/// by the true intensity, and how many are within 0.2 ns (a pixel without a lifetime is a miss).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct LifetimeErrors {
    /// Σ|τ̂ − τ| (s) and Σ I·|τ̂ − τ| over the estimated pixels, Σ I over them.
    pub abs_sum: f64,
    pub weighted_sum: f64,
    pub intensity_sum: f64,
    /// Pixels estimated, within 0.2 ns, and holding a fluorophore.
    pub estimated: usize,
    pub within: usize,
    pub truth: usize,
    /// Pixels without any fluorophore, and those of them that got a lifetime anyway.
    pub background: usize,
    pub false_estimates: usize,
}

impl LifetimeErrors {
    /// Add one item: estimate and truth `[H, W]` (s), true intensity `[H, W]`.
    pub fn add(&mut self, est: &ArrayView2<'_, f32>, truth: &ArrayView2<'_, f32>, intensity: Option<&ArrayView2<'_, f32>>) {
        let peak = intensity.map_or(0.0, |i| i.iter().fold(0f32, |m, &v| m.max(v)));
        for ((idx, &t), &e) in truth.indexed_iter().zip(est.iter()) {
            let inten = intensity.map_or(1.0, |i| i[idx]);
            let counts = match intensity {
                Some(_) => holds_fluorophore(t, inten, peak),
                None => t.is_finite(),
            };
            if !t.is_finite() {
                self.background += 1;
                self.false_estimates += e.is_finite() as usize;
            }
            if !counts {
                continue;
            }
            self.truth += 1;
            if e.is_finite() {
                let err = (e as f64 - t as f64).abs();
                self.abs_sum += err;
                self.weighted_sum += inten as f64 * err;
                self.intensity_sum += inten as f64;
                self.estimated += 1;
                if err <= 0.2e-9 {
                    self.within += 1;
                }
            }
        }
    }

    /// Mean absolute error (s) over the estimated pixels.
    pub fn mae(&self) -> Option<f64> {
        (self.estimated > 0).then(|| self.abs_sum / self.estimated as f64)
    }

    /// The intensity-weighted mean absolute error (s).
    pub fn weighted_mae(&self) -> Option<f64> {
        (self.intensity_sum > 0.0).then(|| self.weighted_sum / self.intensity_sum)
    }

    /// Share of the fluorophore pixels within 0.2 ns.
    pub fn within_share(&self) -> Option<f64> {
        (self.truth > 0).then(|| self.within as f64 / self.truth as f64)
    }

    /// Share of the fluorophore pixels that got a lifetime.
    pub fn coverage(&self) -> Option<f64> {
        (self.truth > 0).then(|| self.estimated as f64 / self.truth as f64)
    }

    /// Share of the pixels without a fluorophore that got a lifetime anyway.
    pub fn false_share(&self) -> Option<f64> {
        (self.background > 0).then(|| self.false_estimates as f64 / self.background as f64)
    }
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
        let mut l = LifetimeErrors::default();
        let (est, truth) = (ndarray::arr2(&[[1.0f32, f32::NAN]]), ndarray::arr2(&[[1.5f32, 2.0]]));
        l.add(&est.view(), &truth.view(), None);
        assert_eq!((l.mae(), l.estimated, l.truth, l.coverage()), (Some(0.5), 1, 2, Some(0.5)));
        // with intensities: the dim pixel (below 2 % of the brightest) does not count
        let mut l = LifetimeErrors::default();
        let (est, truth, inten) =
            (ndarray::arr2(&[[1.1e-9f32, 9e-9, 1e-9]]), ndarray::arr2(&[[1e-9f32, 2e-9, 3e-9]]), ndarray::arr2(&[[1.0f32, 3.0, 0.01]]));
        l.add(&est.view(), &truth.view(), Some(&inten.view()));
        assert_eq!((l.truth, l.estimated, l.within), (2, 2, 1));
        assert!((l.mae().unwrap() - 3.55e-9).abs() < 1e-12 && (l.weighted_mae().unwrap() - (0.1e-9 + 21e-9) / 4.0).abs() < 1e-12);
        assert_eq!(l.false_share(), None, "no pixel without a fluorophore");
        // pixels without a fluorophore: one of three got a lifetime anyway
        let (est, truth) = (ndarray::arr2(&[[1e-9f32, f32::NAN, f32::NAN, 2e-9]]), ndarray::arr2(&[[f32::NAN, f32::NAN, f32::NAN, 2e-9]]));
        let mut l = LifetimeErrors::default();
        l.add(&est.view(), &truth.view(), None);
        assert_eq!((l.background, l.false_estimates, l.truth, l.coverage()), (3, 1, 1, Some(1.0)));
        assert!((l.false_share().unwrap() - 1.0 / 3.0).abs() < 1e-12);
    }
}
