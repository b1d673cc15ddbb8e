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
//! amplitude-weighted mean lifetime `[H, W]` (s; NaN in the background), onset `[1]` (s).
//!
//! **Domain randomisation** ([`FlimRandomization`], on by default; `None` is the paper's
//! generator above): a real instrument's delay, IRF, lifetimes, background and brightness are
//! not the generator's, so each scene draws them — the onset anywhere in the cycle; a
//! Gaussian instrument response of random FWHM (cyclic convolution of the bin averages with
//! the bin-integrated Gaussian); one to three distinct lifetimes over a wider, log-uniform
//! range (channels share them when fewer than three, so mixtures of 1–3 components); a
//! constant background offset; a brightness factor over two decades. The knobs are drawn
//! from their own random stream, so the cell structure of item `i` is the same with and
//! without randomisation.

use crate::error::{invalid, Result};
use crate::grid::TimeGrid;
use crate::knobs::{check_range, draw};
use ndarray::{Array1, Array2, Array3};
use rand::rngs::StdRng;
use rand::{RngExt, SeedableRng};
use serde::{Deserialize, Serialize};
use tcsense_sensor::waveform::{decay_bin_averages, IrfKernel};

/// Lifetime ranges of the three channels (s), as in the paper.
pub const TAU_RANGES: [(f64, f64); 3] = [(0.5e-9, 1.5e-9), (1.5e-9, 2.5e-9), (2.5e-9, 3.5e-9)];

/// Below this total channel value a pixel counts as background (no lifetime).
pub const BACKGROUND: f32 = 1e-3;

/// A pixel holds a fluorophore, for training and scoring lifetimes, where the truth has a
/// lifetime and its intensity is at least this fraction of the item's brightest pixel.
pub const SIGNAL_REL: f32 = 0.02;

/// Whether a pixel with true `lifetime` and `intensity` holds a fluorophore in an item whose
/// brightest pixel has intensity `peak` ([`SIGNAL_REL`]).
pub fn holds_fluorophore(lifetime: f32, intensity: f32, peak: f32) -> bool {
    lifetime.is_finite() && peak > 0.0 && intensity >= SIGNAL_REL * peak
}

/// Stream of the randomisation knobs, apart from the scene's own `(seed, index)` stream.
const KNOB_STREAM: u64 = 0x464C_494D_5241_4E44;

/// Ranges of the randomised FLIm knobs; every range is `[lo, hi]`, and `lo == hi` fixes the
/// knob to that value.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct FlimRandomization {
    /// Decay onset as a fraction of the code cycle, uniform.
    pub onset_cycle: [f64; 2],
    /// FWHM of the Gaussian instrument response (s), uniform; 0 = none.
    pub irf_fwhm_s: [f64; 2],
    /// Number of distinct lifetimes per scene, uniform over `lo..=hi` (1..=3).
    pub lifetimes: [usize; 2],
    /// Lifetimes (s), log-uniform.
    pub tau_s: [f64; 2],
    /// Constant background offset, as a fraction of the scene's peak, uniform.
    pub background: [f64; 2],
    /// Brightness factor of the whole cube, log-uniform.
    pub brightness: [f64; 2],
}

impl Default for FlimRandomization {
    /// Onsets over the whole cycle, IRF FWHM 0–1 ns, 1–3 lifetimes in 0.3–6 ns, background
    /// 0–5 % of the peak, brightness over two decades.
    fn default() -> Self {
        FlimRandomization {
            onset_cycle: [0.0, 1.0],
            irf_fwhm_s: [0.0, 1e-9],
            lifetimes: [1, 3],
            tau_s: [0.3e-9, 6e-9],
            background: [0.0, 0.05],
            brightness: [0.01, 1.0],
        }
    }
}

impl FlimRandomization {
    /// Check the ranges.
    pub fn validate(&self) -> Result<()> {
        check_range("onset_cycle", self.onset_cycle, 0.0, 1.0)?;
        check_range("irf_fwhm_s", self.irf_fwhm_s, 0.0, 1e-7)?;
        check_range("tau_s", self.tau_s, 1e-12, 1e-6)?;
        check_range("background", self.background, 0.0, 10.0)?;
        check_range("brightness", self.brightness, 1e-6, 1e6)?;
        if !(1 <= self.lifetimes[0] && self.lifetimes[0] <= self.lifetimes[1] && self.lifetimes[1] <= 3) {
            return Err(invalid("lifetimes", format!("{:?}", self.lifetimes), "1 ≤ lo ≤ hi ≤ 3"));
        }
        Ok(())
    }
}

/// The per-scene values of the knobs that [`render`] applies.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FlimKnobs {
    /// Lifetime of each channel (s).
    pub tau: [f64; 3],
    /// Decay onset `t_0` (s).
    pub onset_s: f64,
    /// FWHM of the Gaussian instrument response (s); 0 = none.
    pub irf_fwhm_s: f64,
    /// Background offset, as a fraction of the noise-free peak.
    pub background: f64,
    /// Brightness factor.
    pub brightness: f64,
}

/// FLIm generator settings.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct FlimParams {
    pub height: usize,
    pub width: usize,
    /// Decay onset `t_0` (s).
    pub onset_s: f64,
    /// Cells per image (upper bound; at least 1).
    pub max_cells: usize,
    /// Domain randomisation (`None`, and in manifests written before it existed: the paper's
    /// fixed onset and lifetime ranges).
    #[serde(default)]
    pub randomization: Option<FlimRandomization>,
}

impl Default for FlimParams {
    /// 64×64, up to 8 cells, randomised ([`FlimRandomization::default`]).
    fn default() -> Self {
        FlimParams { randomization: Some(FlimRandomization::default()), ..FlimParams::paper() }
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
    /// Intensity scale `S` `[H, W]` (times the brightness).
    pub intensity: Array2<f32>,
    /// Decay onset `[1]` (s).
    pub onset: Array1<f32>,
}

impl FlimParams {
    /// The paper's generator: 64×64, up to 8 cells, onset 2 ns, lifetimes from
    /// [`TAU_RANGES`], no IRF, background or brightness variation.
    pub fn paper() -> Self {
        FlimParams { height: 64, width: 64, onset_s: 2e-9, max_cells: 8, randomization: None }
    }

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
        if let Some(r) = &self.randomization {
            r.validate()?;
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

    /// The knobs of item `index`: the paper's fixed onset and drawn lifetimes `tau`, or a
    /// randomised draw from the knobs' own stream.
    pub fn knobs(&self, grid: &TimeGrid, tau: [f64; 3], seed: u64, index: u64) -> FlimKnobs {
        let Some(r) = &self.randomization else {
            return FlimKnobs { tau, onset_s: self.onset_s, irf_fwhm_s: 0.0, background: 0.0, brightness: 1.0 };
        };
        let mut rng = StdRng::seed_from_u64(tcsense_sensor::noise::derive_seed(seed ^ KNOB_STREAM, index));
        let onset_s = (draw(&mut rng, r.onset_cycle, false) * grid.cycle_s()).min(grid.cycle_s() * (1.0 - 1e-12));
        let irf_fwhm_s = draw(&mut rng, r.irf_fwhm_s, false);
        let k = rng.random_range(r.lifetimes[0]..=r.lifetimes[1]);
        let mut taus: Vec<f64> = (0..k).map(|_| draw(&mut rng, r.tau_s, true)).collect();
        taus.sort_by(f64::total_cmp);
        // channel i takes lifetime i of k, the longest shared when k < 3
        let tau = std::array::from_fn(|i| taus[i.min(k - 1)]);
        let background = draw(&mut rng, r.background, false);
        let brightness = draw(&mut rng, r.brightness, true);
        FlimKnobs { tau, onset_s, irf_fwhm_s, background, brightness }
    }

    /// Render item `index` on `grid`.
    pub fn sample(&self, grid: &TimeGrid, seed: u64, index: u64) -> FlimSample {
        let (p, tau) = self.channels(seed, index);
        render(&p, &self.knobs(grid, tau, seed, index), grid)
    }
}

/// Render eq. (5) from channels `p` `[3, H, W]` with the scene's knobs.
pub fn render(p: &Array3<f32>, knobs: &FlimKnobs, grid: &TimeGrid) -> FlimSample {
    let (_, h, w) = p.dim();
    let t = grid.bins();
    let (tau, t0) = (knobs.tau, knobs.onset_s);
    let irf = IrfKernel::gaussian(grid.cycle(), knobs.irf_fwhm_s);
    let decays: Vec<Vec<f64>> = tau.iter().map(|&ti| irf.apply(&decay_bin_averages(grid.cycle(), ti, t0))).collect();
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
    let b = knobs.brightness as f32;
    if knobs.background > 0.0 {
        let offset = knobs.background as f32 * x.iter().fold(0f32, |m, &v| m.max(v));
        x.mapv_inplace(|v| v + offset);
    }
    if b != 1.0 {
        x.mapv_inplace(|v| v * b);
        intensity.mapv_inplace(|v| v * b);
    }
    FlimSample {
        x,
        tau: Array1::from_iter(tau.iter().map(|&v| v as f32)),
        weights,
        lifetime,
        intensity,
        onset: Array1::from_elem(1, t0 as f32),
    }
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
        let params = FlimParams { height: 16, width: 16, ..FlimParams::paper() };
        let s = params.sample(&g, 1, 0);
        let dt = g.bin_width_s();
        let first = (params.onset_s / dt).ceil() as usize + 1;
        // pixels dominated by one channel: fit log-linear over 30 bins after the onset
        for i in 0..3 {
            let tau_true = s.tau[i] as f64;
            let mut p = Array3::<f32>::zeros((3, 1, 1));
            p[(i, 0, 0)] = 1.0;
            let knobs = FlimKnobs {
                tau: [s.tau[0] as f64, s.tau[1] as f64, s.tau[2] as f64],
                onset_s: params.onset_s,
                irf_fwhm_s: 0.0,
                background: 0.0,
                brightness: 1.0,
            };
            let one = render(&p, &knobs, &g);
            let ys: Vec<f64> = (first..first + 30).map(|j| (one.x[(j, 0, 0)] as f64).ln()).collect();
            let xs: Vec<f64> = (first..first + 30).map(|j| j as f64 * dt).collect();
            let (mx, my) = (xs.iter().sum::<f64>() / 30.0, ys.iter().sum::<f64>() / 30.0);
            let slope =
                xs.iter().zip(&ys).map(|(x, y)| (x - mx) * (y - my)).sum::<f64>() / xs.iter().map(|x| (x - mx).powi(2)).sum::<f64>();
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
        let d = decay_bin_averages(g.cycle(), tau, 4.3e-9);
        let mean = d.iter().sum::<f64>() / d.len() as f64;
        assert!((mean - tau / g.cycle_s()).abs() < 1e-9);
    }

    #[test]
    fn same_seed_same_sample() {
        let g = het();
        for p in [FlimParams { height: 8, width: 8, ..FlimParams::paper() }, FlimParams { height: 8, width: 8, ..Default::default() }] {
            assert_eq!(p.sample(&g, 4, 2).x, p.sample(&g, 4, 2).x);
            assert_ne!(p.sample(&g, 4, 2).x, p.sample(&g, 4, 3).x);
        }
    }

    #[test]
    fn randomised_knobs_cover_their_ranges() {
        let g = het();
        let p = FlimParams { height: 8, width: 8, ..Default::default() };
        let r = FlimRandomization::default();
        let knobs: Vec<FlimKnobs> = (0..400).map(|i| p.knobs(&g, [1e-9; 3], 9, i)).collect();
        // the onset histogram covers the whole cycle: every eighth of it gets items
        let mut hist = [0usize; 8];
        for k in &knobs {
            hist[((k.onset_s / g.cycle_s()) * 8.0) as usize] += 1;
        }
        assert!(hist.iter().all(|&n| n >= 25), "onset histogram {hist:?}");
        // one, two and three distinct lifetimes all occur, inside the log-uniform range
        for n in 1..=3 {
            assert!(
                knobs.iter().any(|k| {
                    let mut t = k.tau.to_vec();
                    t.dedup();
                    t.len() == n
                }),
                "{n} lifetimes"
            );
        }
        assert!(knobs.iter().all(|k| k.tau.iter().all(|&t| t >= r.tau_s[0] && t <= r.tau_s[1])));
        let taus: Vec<f64> = knobs.iter().map(|k| k.tau[0]).collect();
        assert!(taus.iter().any(|&t| t < 0.5e-9) && knobs.iter().any(|k| k.tau[2] > 3.5e-9), "wider than the paper's ranges");
        // brightness over two decades, log-uniform: about half of the draws below 0.1
        let dim = knobs.iter().filter(|k| k.brightness < 0.1).count();
        assert!((150..250).contains(&dim), "{dim} of 400 below 0.1");
        assert!(knobs.iter().any(|k| k.irf_fwhm_s > 0.8e-9) && knobs.iter().any(|k| k.background > 0.04));
        // the cells are the same with and without randomisation; the rendering is not
        let fixed = FlimParams { height: 8, width: 8, ..FlimParams::paper() };
        let (a, b) = (p.sample(&g, 9, 3), fixed.sample(&g, 9, 3));
        assert_eq!(a.weights, b.weights);
        assert_ne!(a.x, b.x);
        assert_eq!(a.onset[0], knobs[3].onset_s as f32);
        // a background offset lifts every voxel, the brightness scales the cube
        let k = FlimKnobs { tau: [1e-9, 2e-9, 3e-9], onset_s: 1e-9, irf_fwhm_s: 0.0, background: 0.0, brightness: 1.0 };
        let (ch, _) = fixed.channels(9, 3);
        let plain = render(&ch, &k, &g).x;
        let peak = plain.iter().fold(0f32, |m, &v| m.max(v));
        let lifted = render(&ch, &FlimKnobs { background: 0.1, brightness: 0.5, ..k }, &g).x;
        for (l, v) in lifted.iter().zip(plain.iter()) {
            assert!((l - 0.5 * (v + 0.1 * peak)).abs() < 1e-6);
        }
        assert!(FlimRandomization { lifetimes: [0, 3], ..r }.validate().is_err());
        assert!(FlimRandomization { onset_cycle: [0.5, 0.2], ..r }.validate().is_err());
    }

    #[test]
    fn irf_blur_keeps_the_area_and_widens_the_rise() {
        let g = het();
        let d = decay_bin_averages(g.cycle(), 1e-9, 3e-9);
        let b = IrfKernel::gaussian(g.cycle(), 1e-9).apply(&d);
        let (sd, sb): (f64, f64) = (d.iter().sum(), b.iter().sum());
        assert!((sd - sb).abs() < 1e-9 * sd, "area {sd} -> {sb}");
        // the sharp rise at the onset is spread over several bins: its peak drops
        let (pd, pb) = (d.iter().cloned().fold(0.0, f64::max), b.iter().cloned().fold(0.0, f64::max));
        assert!(pb < 0.9 * pd, "peak {pd} -> {pb}");
    }

    #[test]
    fn a_shifted_onset_is_a_cyclic_time_shift() {
        // the codes loop, so delaying the decay by k bins rolls the cube by k bins
        let g = het();
        let fixed = FlimParams { height: 8, width: 8, ..FlimParams::paper() };
        let (ch, tau) = fixed.channels(5, 1);
        let dt = g.bin_width_s();
        for (irf, k) in [(0.0, 37usize), (0.6e-9, 200)] {
            let base = FlimKnobs { tau, onset_s: 1.3e-9, irf_fwhm_s: irf, background: 0.0, brightness: 1.0 };
            let x0 = render(&ch, &base, &g).x;
            let shifted = render(&ch, &FlimKnobs { onset_s: (base.onset_s + k as f64 * dt) % g.cycle_s(), ..base }, &g).x;
            let t = g.bins();
            let peak = x0.iter().fold(0f32, |m, &v| m.max(v));
            for j in 0..t {
                for (a, b) in shifted.index_axis(ndarray::Axis(0), (j + k) % t).iter().zip(x0.index_axis(ndarray::Axis(0), j).iter()) {
                    assert!((a - b).abs() < 1e-5 * peak, "bin {j}: {a} vs {b}");
                }
            }
        }
    }
}
