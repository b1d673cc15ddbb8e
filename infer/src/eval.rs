//! Evaluation of a decoder's reconstructions against a dataset's ground truth: one row per
//! decoder with the mean MSE and PSNR, depth errors per bounce (LiDAR), lifetime MAE (FLIm)
//! and the time per frame.

use crate::metrics::{depth_errors, lifetime_mae, mse, psnr, DepthErrors};
use crate::products::{depth_map, lifetime_map, PeakOptions};
use ndarray::{ArrayView2, ArrayView3};
use serde::Serialize;

/// Accumulates metrics over items.
#[derive(Debug, Clone, Default, Serialize)]
pub struct EvalRow {
    pub decoder: String,
    pub items: usize,
    pub mse: f64,
    pub psnr_db: f64,
    /// Per bounce (LiDAR).
    pub depth: Vec<DepthErrors>,
    /// Mean absolute lifetime error (s), FLIm.
    pub lifetime_mae_s: Option<f64>,
    pub seconds_per_frame: f64,
    #[serde(skip)]
    depth_sums: Vec<(usize, usize, f64, f64)>,
    #[serde(skip)]
    lt_sum: (f64, usize),
    #[serde(skip)]
    time_sum: f64,
}

impl EvalRow {
    pub fn new(decoder: &str) -> Self {
        EvalRow { decoder: decoder.to_string(), ..Default::default() }
    }

    /// Add one item: reconstruction `x̂`, truth `x` (both `[T, H, W]`), optional true range
    /// `[K, H, W]` and lifetime `[H, W]`, bin width and the decoder's time for it.
    pub fn add(&mut self, xh: &ArrayView3<'_, f32>, x: &ArrayView3<'_, f32>, depth: Option<&ArrayView3<'_, f32>>, lifetime: Option<&ArrayView2<'_, f32>>, bin_width_s: f64, seconds: f64) {
        let (a, b) = (xh.as_standard_layout(), x.as_standard_layout());
        let (a, b) = (a.as_slice().unwrap_or(&[]), b.as_slice().unwrap_or(&[]));
        let m = mse(a, b);
        let n = self.items as f64;
        self.mse = (self.mse * n + m) / (n + 1.0);
        self.psnr_db = (self.psnr_db * n + psnr(a, b)) / (n + 1.0);
        self.time_sum += seconds;
        self.items += 1;
        self.seconds_per_frame = self.time_sum / self.items as f64;
        if let Some(d) = depth {
            let (est, _) = depth_map(xh, bin_width_s, &PeakOptions { max_peaks: d.dim().0, ..Default::default() });
            let errs = depth_errors(&est.view(), d);
            if self.depth_sums.len() < errs.len() {
                self.depth_sums.resize(errs.len(), (0, 0, 0.0, 0.0));
            }
            for (s, e) in self.depth_sums.iter_mut().zip(&errs) {
                s.0 += e.truth;
                s.1 += e.detected;
                s.2 += e.rmse_m * e.rmse_m * e.detected as f64;
                s.3 += e.mae_m * e.detected as f64;
            }
            self.depth = self
                .depth_sums
                .iter()
                .map(|&(t, d, se, ae)| DepthErrors { truth: t, detected: d, rmse_m: if d > 0 { (se / d as f64).sqrt() } else { f64::NAN }, mae_m: if d > 0 { ae / d as f64 } else { f64::NAN } })
                .collect();
        }
        if let Some(lt) = lifetime {
            let (tau, _) = lifetime_map(xh, bin_width_s, 0.05, 0.02);
            let t = lt.as_standard_layout();
            let (mae, k) = lifetime_mae(tau.as_slice().unwrap_or(&[]), t.as_slice().unwrap_or(&[]));
            if k > 0 {
                self.lt_sum.0 += mae * k as f64;
                self.lt_sum.1 += k;
                self.lifetime_mae_s = Some(self.lt_sum.0 / self.lt_sum.1 as f64);
            }
        }
    }

    /// One line of a table.
    pub fn line(&self) -> String {
        let mut s = format!("{:<24} {:>5} {:>11.4e} {:>8.2}", self.decoder, self.items, self.mse, self.psnr_db);
        for (b, d) in self.depth.iter().enumerate().filter(|(_, d)| d.truth > 0) {
            s.push_str(&format!("  b{}: rmse {:.3} m mae {:.3} m det {:.0}%", b + 1, d.rmse_m, d.mae_m, 100.0 * d.detection_rate()));
        }
        if let Some(l) = self.lifetime_mae_s {
            s.push_str(&format!("  lifetime MAE {:.3} ns", l * 1e9));
        }
        s.push_str(&format!("  {:.1} ms/frame", self.seconds_per_frame * 1e3));
        s
    }
}
