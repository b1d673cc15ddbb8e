//! Fluorescence-lifetime (FLIm) samples, paper eq. (5):
//!
//! `I_{X,Y}(t) = S(X,Y) · Σ_{i=1}^{3} P_i(X,Y) / Σ_j P_j(X,Y) · exp(−t/τ_i)`
//!
//! with three procedurally drawn channels `P_i ∈ [0, 1]` — nucleus-like blobs, membranes
//! (cell outlines) and filaments — and per-sample lifetimes `τ_1 ~ U[0.5, 1.5] ns`,
//! `τ_2 ~ U[1.5, 2.5] ns`, `τ_3 ~ U[2.5, 3.5] ns`. `S = min(1, Σ_j P_j)` keeps the
//! background dark (eq. 5 alone normalises every pixel to unit amplitude; the database
//! images it was applied to have a dark background).
//!
//! The excitation repeats every code cycle `P = L·T_c`, so each decay is the periodic
//! steady state `Σ_k exp(−(t − t_0 + kP)/τ)`, starting at the onset `t_0`, and each bin holds
//! the exact bin average of `I(t)`. The fine grid of the heterodyne mode (`K = 8`,
//! `Δ ≈ 206 ps` at 607 MHz) is the default.
//!
//! Ground truth: cube `[T, H, W]`, lifetimes `[3]` (s), weights `P_i/ΣP_j` `[3, H, W]`,
//! amplitude-weighted mean lifetime `[H, W]` (s; NaN in the background).

use crate::error::{invalid, Result};
use crate::grid::TimeGrid;
use ndarray::{Array1, Array2, Array3};
use rand::rngs::StdRng;
use rand::{RngExt, SeedableRng};
use serde::{Deserialize, Serialize};

/// Lifetime ranges of the three channels (s), as in the paper.
pub const TAU_RANGES: [(f64, f64); 3] = [(0.5e-9, 1.5e-9), (1.5e-9, 2.5e-9), (2.5e-9, 3.5e-9)];

/// Below this total channel value a pixel counts as background (no lifetime).
pub const BACKGROUND: f32 = 1e-3;

/// FLIm generator settings.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct FlimParams {
    pub height: usize,
    pub width: usize,
    /// Decay onset `t_0` (s).
    pub onset_s: f64,
    /// Cells per image (upper bound; at least 1).
    pub max_cells: usize,
}

impl Default for FlimParams {
    fn default() -> Self {
        FlimParams { height: 64, width: 64, onset_s: 2e-9, max_cells: 8 }
    }
}

/// One FLIm sample.
#[derive(Debug, Clone)]
pub struct FlimSample {
    /// Transient cube `[T, H, W]`.
    pub x: Array3<f32>,
    /// Lifetimes `[3]` (s).
    pub tau: Array1<f32>,
    /// Weights `P_i / Σ_j P_j`: `[3, H, W]`.
    pub weights: Array3<f32>,
    /// Amplitude-weighted mean lifetime `[H, W]` (s), NaN in the background.
    pub lifetime: Array2<f32>,
    /// Intensity scale `S` `[H, W]`.
    pub intensity: Array2<f32>,
}

impl FlimParams {
    /// Check ranges.
    pub fn validate(&self, grid: &TimeGrid) -> Result<()> {
        if self.height == 0 || self.width == 0 || self.height > 4096 || self.width > 4096 {
            return Err(invalid("size", format!("{}x{}", self.height, self.width), "1..=4096 on each side"));
        }
        if !(self.onset_s >= 0.0 && self.onset_s < grid.cycle_s()) {
            return Err(invalid("onset", self.onset_s, format!("a time in [0, {:.3e}) s (the code cycle)", grid.cycle_s())));
        }
        if self.max_cells == 0 || self.max_cells > 256 {
            return Err(invalid("max_cells", self.max_cells, "1..=256"));
        }
        Ok(())
    }

    /// The three channels `P_i` `[3, H, W]` and lifetimes of item `index`.
    pub fn channels(&self, seed: u64, index: u64) -> (Array3<f32>, [f64; 3]) {
        let mut rng = StdRng::seed_from_u64(tcsense_sensor::noise::derive_seed(seed, index));
        let tau = TAU_RANGES.map(|(lo, hi)| rng.random_range(lo..hi));
        let (h, w) = (self.height, self.width);
        let scale = h.min(w) as f64;
        let mut p = Array3::<f32>::zeros((3, h, w));
        let n_cells = rng.random_range(1..=self.max_cells);
        for _ in 0..n_cells {
            let cy = rng.random_range(0.0..h as f64);
            let cx = rng.random_range(0.0..w as f64);
            let rn = rng.random_range(0.04..0.09) * scale; // nucleus radius
            let rm = rn * rng.random_range(1.8..2.8); // membrane radius
            let ecc = rng.random_range(0.7..1.3);
            let rot: f64 = rng.random_range(0.0..std::f64::consts::PI);
            let amp_n = rng.random_range(0.5..1.0);
            let amp_m = rng.random_range(0.4..1.0);
            let width_m = rng.random_range(0.6..1.5);
            let (cr, sr) = (rot.cos(), rot.sin());
            for r in 0..h {
                for c in 0..w {
                    let (dy, dx) = (r as f64 + 0.5 - cy, c as f64 + 0.5 - cx);
                    let (u, v) = (cr * dx + sr * dy, (-sr * dx + cr * dy) * ecc);
                    let rad = (u * u + v * v).sqrt();
                    let nucleus = amp_n * (-(rad / rn).powi(2)).exp();
                    let membrane = amp_m * (-((rad - rm) / width_m).powi(2)).exp();
                    p[(0, r, c)] += nucleus as f32;
                    p[(1, r, c)] += membrane as f32;
                }
            }
        }
        // filaments: smooth random walks drawn with a Gaussian line profile
        let n_fil = rng.random_range(1..=(2 * self.max_cells).max(2));
        for _ in 0..n_fil {
            let (mut y, mut x) = (rng.random_range(0.0..h as f64), rng.random_range(0.0..w as f64));
            let mut ang: f64 = rng.random_range(0.0..std::f64::consts::TAU);
            let amp = rng.random_range(0.3..0.9);
            let steps = (scale * rng.random_range(0.5..1.5)) as usize;
            for _ in 0..steps {
                ang += rng.random_range(-0.3..0.3);
                y += ang.sin() * 0.7;
                x += ang.cos() * 0.7;
                let (r0, c0) = (y.floor() as isize, x.floor() as isize);
                for dr in -2..=2 {
                    for dc in -2..=2 {
                        let (r, c) = (r0 + dr, c0 + dc);
                        if r < 0 || c < 0 || r >= h as isize || c >= w as isize {
                            continue;
                        }
                        let d2 = (r as f64 + 0.5 - y).powi(2) + (c as f64 + 0.5 - x).powi(2);
                        let v = &mut p[(2, r as usize, c as usize)];
                        *v = v.max((amp * (-d2 / 0.8).exp()) as f32);
                    }
                }
            }
        }
        p.mapv_inplace(|v| v.clamp(0.0, 1.0));
        (p, tau)
    }

    /// Render item `index` on `grid`.
    pub fn sample(&self, grid: &TimeGrid, seed: u64, index: u64) -> FlimSample {
        let (p, tau) = self.channels(seed, index);
        render(&p, tau, self.onset_s, grid)
    }
}

/// Bin averages of the periodic unit decay `Σ_k exp(−(t − t0 + kP)/τ)` over `T` bins.
pub fn decay_bins(grid: &TimeGrid, tau: f64, t0: f64) -> Vec<f64> {
    let (dt, period) = (grid.bin_width_s(), grid.cycle_s());
    let norm = 1.0 / (1.0 - (-period / tau).exp());
    // ∫_a^b e^{−(t−s)/τ} dt for a ≥ s
    let integral = |a: f64, b: f64, s: f64| tau * ((-(a - s) / tau).exp() - (-(b - s) / tau).exp());
    (0..grid.bins())
        .map(|j| {
            let (a, b) = (j as f64 * dt, (j + 1) as f64 * dt);
            let mut acc = 0.0;
            // part at or after the onset: decay of this cycle's pulse
            if b > t0 {
                acc += integral(a.max(t0), b, t0);
            }
            // part before the onset: tail of the previous cycle's pulse
            if a < t0 {
                acc += integral(a, b.min(t0), t0 - period);
            }
            acc * norm / dt
        })
        .collect()
}

/// Render eq. (5) from channels `p` `[3, H, W]`.
pub fn render(p: &Array3<f32>, tau: [f64; 3], t0: f64, grid: &TimeGrid) -> FlimSample {
    let (_, h, w) = p.dim();
    let t = grid.bins();
    let decays: Vec<Vec<f64>> = tau.iter().map(|&ti| decay_bins(grid, ti, t0)).collect();
    let mut x = Array3::<f32>::zeros((t, h, w));
    let mut weights = Array3::<f32>::zeros((3, h, w));
    let mut lifetime = Array2::<f32>::from_elem((h, w), f32::NAN);
    let mut intensity = Array2::<f32>::zeros((h, w));
    for r in 0..h {
        for c in 0..w {
            let total: f32 = (0..3).map(|i| p[(i, r, c)]).sum();
            if total < BACKGROUND {
                continue;
            }
            let s = total.min(1.0);
            intensity[(r, c)] = s;
            let wts: [f64; 3] = std::array::from_fn(|i| (p[(i, r, c)] / total) as f64);
            for i in 0..3 {
                weights[(i, r, c)] = wts[i] as f32;
            }
            lifetime[(r, c)] = (0..3).map(|i| wts[i] * tau[i]).sum::<f64>() as f32;
            for j in 0..t {
                let v: f64 = (0..3).map(|i| wts[i] * decays[i][j]).sum();
                x[(j, r, c)] = (s as f64 * v) as f32;
            }
        }
    }
    FlimSample { x, tau: Array1::from_iter(tau.iter().map(|&v| v as f32)), weights, lifetime, intensity }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tcsense_sensor::Sampling;

    fn het() -> TimeGrid {
        TimeGrid { length: 32, clock_hz: 607e6, sampling: Sampling::Heterodyne(8) }
    }

    #[test]
    fn decays_recover_their_lifetimes_by_a_fit() {
        let g = het();
        let params = FlimParams { height: 16, width: 16, ..Default::default() };
        let s = params.sample(&g, 1, 0);
        let dt = g.bin_width_s();
        let first = (params.onset_s / dt).ceil() as usize + 1;
        // pixels dominated by one channel: fit log-linear over 30 bins after the onset
        for i in 0..3 {
            let tau_true = s.tau[i] as f64;
            let mut p = Array3::<f32>::zeros((3, 1, 1));
            p[(i, 0, 0)] = 1.0;
            let one = render(&p, [s.tau[0] as f64, s.tau[1] as f64, s.tau[2] as f64], params.onset_s, &g);
            let ys: Vec<f64> = (first..first + 30).map(|j| (one.x[(j, 0, 0)] as f64).ln()).collect();
            let xs: Vec<f64> = (first..first + 30).map(|j| j as f64 * dt).collect();
            let (mx, my) = (xs.iter().sum::<f64>() / 30.0, ys.iter().sum::<f64>() / 30.0);
            let slope = xs.iter().zip(&ys).map(|(x, y)| (x - mx) * (y - my)).sum::<f64>() / xs.iter().map(|x| (x - mx).powi(2)).sum::<f64>();
            let tau_fit = -1.0 / slope;
            assert!((tau_fit / tau_true - 1.0).abs() < 1e-3, "channel {i}: fit {tau_fit:e} true {tau_true:e}");
            assert!(tau_true >= TAU_RANGES[i].0 && tau_true < TAU_RANGES[i].1);
        }
        // mean lifetime is the weighted mean of the channel lifetimes
        let (r, c) = (0..16).flat_map(|r| (0..16).map(move |c| (r, c))).find(|&(r, c)| !s.lifetime[(r, c)].is_nan()).unwrap();
        let want: f32 = (0..3).map(|i| s.weights[(i, r, c)] * s.tau[i]).sum();
        assert!((s.lifetime[(r, c)] - want).abs() < 1e-12);
    }

    #[test]
    fn decay_is_periodic_and_bin_averaged() {
        let g = TimeGrid { length: 8, clock_hz: 607e6, sampling: Sampling::Oversample(1) };
        // the average over a whole cycle of the periodic decay is τ/P
        let tau = 3e-9;
        let d = decay_bins(&g, tau, 4.3e-9);
        let mean = d.iter().sum::<f64>() / d.len() as f64;
        assert!((mean - tau / g.cycle_s()).abs() < 1e-9);
    }

    #[test]
    fn same_seed_same_sample() {
        let g = het();
        let p = FlimParams { height: 8, width: 8, ..Default::default() };
        assert_eq!(p.sample(&g, 4, 2).x, p.sample(&g, 4, 2).x);
        assert_ne!(p.sample(&g, 4, 2).x, p.sample(&g, 4, 3).x);
    }
}
