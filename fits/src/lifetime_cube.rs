//! Lifetimes from a transient cube, as lifetime software does them (FLIMfit, SPCImage,
//! phasorpy): a least-squares **reconvolution** fit of one or two exponentials with the
//! instrument response, cyclic, with a background, and the **phasor referenced to the IRF**.
//!
//! The model of a pixel's bins (the cube covers one code cycle `P = T·Δt`, and the excitation
//! repeats every cycle, so every decay is the periodic steady state):
//!
//! ```text
//! x̂(t_j) = Σ_i a_i · (IRF ⊛ D_τi)(t_j) + b,   D_τ(t) = Σ_k e^{−(t − t₀ + kP)/τ}·[t ≥ t₀ − kP],
//! ```
//!
//! each bin the exact average of the continuous model over it, the IRF a Gaussian of FWHM `w`
//! (bin-integrated) or a measured response. The onset `t₀` and the IRF are the instrument's,
//! the same for every pixel: they come from a fit of the frame's summed decay (a bi-exponential
//! over a grid of `t₀` and `w`, then refined), as a global IRF-shift fit does. Per pixel, the
//! amplitudes and the background are linear and are solved exactly for each candidate lifetime
//! (variable projection); the lifetimes are searched on a fine log grid of precomputed,
//! IRF-convolved decays (1.7 % apart, then refined continuously on curves interpolated between them), whose Gram matrix is computed
//! once per frame, so a pixel costs one product with the grid plus O(1) per candidate pair.
//! Two components are kept where they lower the Akaike criterion by more than
//! [`FitOptions::two_component_aic`]; the map shows the amplitude-weighted mean
//! `τ_m = Σ a_iτ_i / Σ a_i`.
//!
//! The phasor at the cycle's first harmonic `ω = 2π/P` of the background-free decay, divided by
//! that of the instrument response: single exponentials fall on the universal semicircle
//! `g = 1/(1+ω²τ²)`, `s = ωτ/(1+ω²τ²)` whatever the onset and IRF, and `τ_φ = s/(ωg)`.

use ndarray::{Array2, Array3, ArrayView3, Axis};
use rayon::prelude::*;
use tcsense_sensor::waveform::{decay_bin_averages, Cycle, IrfKernel};

/// The instrument response the fit convolves with.
#[derive(Debug, Clone, PartialEq)]
pub enum IrfModel {
    /// A Gaussian of this FWHM (s), or of a FWHM fitted to the frame (`None`).
    Gaussian(Option<f64>),
    /// A measured response, one value per bin of the cycle (any scale; its position is free:
    /// the fit shifts it).
    Measured(Vec<f64>),
}

/// How many exponentials a pixel gets.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Components {
    One,
    Two,
    /// Two where they lower the Akaike criterion by [`FitOptions::two_component_aic`].
    Auto,
}

/// Settings of [`fit_cube`].
#[derive(Debug, Clone, PartialEq)]
pub struct FitOptions {
    pub irf: IrfModel,
    pub components: Components,
    /// Pixels whose total is below this fraction of the brightest pixel's get no lifetime.
    pub min_intensity: f32,
    /// Lifetimes searched, `[lo, hi]` (s).
    pub tau_range_s: [f64; 2],
    /// Decrease of the Akaike criterion a second component must bring.
    pub two_component_aic: f64,
}

impl Default for FitOptions {
    /// Fitted Gaussian IRF, one or two components by AIC (10), pixels above 2 % of the brightest,
    /// lifetimes 0.1–60 ns (shorter components trade off against the IRF width at 206 ps bins).
    fn default() -> Self {
        FitOptions {
            irf: IrfModel::Gaussian(None),
            components: Components::Auto,
            min_intensity: 0.02,
            tau_range_s: [0.1e-9, 60e-9],
            two_component_aic: 10.0,
        }
    }
}

/// What [`fit_cube`] gives.
#[derive(Debug, Clone)]
pub struct LifetimeFit {
    /// `τ_m`, `τ₁ ≤ τ₂` (s) and the amplitude fraction `α₁` of `τ₁`, `[4, H, W]`; NaN where no
    /// fit (one component: `τ₁ = τ₂ = τ_m`, `α₁ = 1`).
    pub lifetimes: Array3<f32>,
    /// Background per bin, `[H, W]` (the cube's units; NaN where no fit).
    pub background: Array2<f32>,
    /// IRF-referenced phasor `(g, s)`, `[2, H, W]` (NaN where no fit).
    pub phasor: Array3<f32>,
    /// The frame's onset `t₀` (s, in `[0, P)`).
    pub onset_s: f64,
    /// FWHM of the Gaussian IRF (s; 0 for a measured IRF).
    pub irf_fwhm_s: f64,
}

/// The kernel of `irf` (a Gaussian of `fwhm` unless measured).
fn kernel_of(c: Cycle, irf: &IrfModel, fwhm: f64) -> IrfKernel {
    match irf {
        IrfModel::Measured(m) => IrfKernel::measured(m),
        IrfModel::Gaussian(_) => IrfKernel::gaussian(c, fwhm),
    }
}

/// IRF-convolved decays on a log grid of lifetimes with their Gram matrix.
struct Basis {
    log_tau: Vec<f64>,
    curves: Vec<Vec<f64>>,
    /// `⟨D_i, D_j⟩`, `[G, G]`.
    gram: Vec<f64>,
    /// `⟨D_i, 1⟩`.
    sums: Vec<f64>,
}

impl Basis {
    fn new(c: Cycle, kernel: &IrfKernel, t0: f64, range: [f64; 2], points: usize) -> Basis {
        let (lo, hi) = (range[0].ln(), range[1].ln());
        let log_tau: Vec<f64> = (0..points).map(|i| lo + (hi - lo) * i as f64 / (points - 1) as f64).collect();
        let curves: Vec<Vec<f64>> = log_tau.par_iter().map(|&l| kernel.apply(&decay_bin_averages(c, l.exp(), t0))).collect();
        let g = points;
        let rows: Vec<Vec<f64>> =
            (0..g).into_par_iter().map(|i| (0..g).map(|j| if j < i { 0.0 } else { dot(&curves[i], &curves[j]) }).collect()).collect();
        let mut gram = vec![0.0; g * g];
        for i in 0..g {
            for j in i..g {
                gram[i * g + j] = rows[i][j];
                gram[j * g + i] = rows[i][j];
            }
        }
        let sums = curves.iter().map(|c| c.iter().sum()).collect();
        Basis { log_tau, curves, gram, sums }
    }
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

/// The best one- and two-exponential fits of one waveform on a basis.
#[derive(Debug, Clone, Copy)]
struct PixelFit {
    /// `(τ, a)` of each component (a second with `a = 0` when one).
    comps: [(f64, f64); 2],
    background: f64,
    sse: f64,
}

/// Solve `A z = r` for a small symmetric system by Gaussian elimination (`None` if singular).
fn solve<const N: usize>(mut a: [[f64; N]; N], mut r: [f64; N]) -> Option<[f64; N]> {
    for col in 0..N {
        let piv = (col..N).max_by(|&i, &j| a[i][col].abs().total_cmp(&a[j][col].abs()))?;
        if a[piv][col].abs() < 1e-300 {
            return None;
        }
        a.swap(col, piv);
        r.swap(col, piv);
        for row in col + 1..N {
            let f = a[row][col] / a[col][col];
            for k in col..N {
                a[row][k] -= f * a[col][k];
            }
            r[row] -= f * r[col];
        }
    }
    let mut z = [0.0; N];
    for i in (0..N).rev() {
        z[i] = (r[i] - (i + 1..N).map(|k| a[i][k] * z[k]).sum::<f64>()) / a[i][i];
    }
    Some(z)
}

/// Per-waveform statistics against a basis: `p_i = ⟨D_i, x⟩`, `q = Σx`, `r = ⟨x, x⟩`.
struct Stats {
    p: Vec<f64>,
    q: f64,
    r: f64,
    n: f64,
}

impl Stats {
    fn new(b: &Basis, x: &[f64]) -> Stats {
        Stats { p: b.curves.iter().map(|c| dot(c, x)).collect(), q: x.iter().sum(), r: dot(x, x), n: x.len() as f64 }
    }

    /// One exponential on grid point `i`: `(a, b, sse)`.
    fn one(&self, b: &Basis, i: usize) -> Option<(f64, f64, f64)> {
        let g = b.log_tau.len();
        let [a, bg] = solve([[b.gram[i * g + i], b.sums[i]], [b.sums[i], self.n]], [self.p[i], self.q])?;
        Some((a, bg, self.r - a * self.p[i] - bg * self.q))
    }

    /// Two exponentials on grid points `i < j`: `(a_i, a_j, b, sse)`.
    fn two(&self, b: &Basis, i: usize, j: usize) -> Option<(f64, f64, f64, f64)> {
        let g = b.log_tau.len();
        let m = [
            [b.gram[i * g + i], b.gram[i * g + j], b.sums[i]],
            [b.gram[i * g + j], b.gram[j * g + j], b.sums[j]],
            [b.sums[i], b.sums[j], self.n],
        ];
        let [ai, aj, bg] = solve(m, [self.p[i], self.p[j], self.q])?;
        Some((ai, aj, bg, self.r - ai * self.p[i] - aj * self.p[j] - bg * self.q))
    }
}

/// The decay at fractional grid position `u` (Catmull–Rom through the four nearest curves;
/// exact at the grid points) and its products with the basis' inputs.
fn curve_at(b: &Basis, u: f64) -> Vec<f64> {
    let g = b.log_tau.len();
    let u = u.clamp(0.0, (g - 1) as f64);
    let i = (u.floor() as usize).min(g - 2);
    let f = u - i as f64;
    let c = |k: isize| &b.curves[(i as isize + k).clamp(0, g as isize - 1) as usize];
    let (p0, p1, p2, p3) = (c(-1), c(0), c(1), c(2));
    let (f2, f3) = (f * f, f * f * f);
    let w = [-0.5 * f3 + f2 - 0.5 * f, 1.5 * f3 - 2.5 * f2 + 1.0, -1.5 * f3 + 2.0 * f2 + 0.5 * f, 0.5 * f3 - 0.5 * f2];
    (0..p0.len()).map(|j| w[0] * p0[j] + w[1] * p1[j] + w[2] * p2[j] + w[3] * p3[j]).collect()
}

/// Least squares of `x` on two curves and a constant: `(a₁, a₂, b, sse)`.
fn two_on(x: &[f64], s: &Stats, d1: &[f64], d2: &[f64]) -> Option<(f64, f64, f64, f64)> {
    let (s1, s2) = (d1.iter().sum::<f64>(), d2.iter().sum::<f64>());
    let (p1, p2) = (dot(d1, x), dot(d2, x));
    let m = [[dot(d1, d1), dot(d1, d2), s1], [dot(d1, d2), dot(d2, d2), s2], [s1, s2, s.n]];
    let [a1, a2, bg] = solve(m, [p1, p2, s.q])?;
    Some((a1, a2, bg, s.r - a1 * p1 - a2 * p2 - bg * s.q))
}

/// Refine a two-component grid fit continuously in `(log τ₁, log τ₂)`: coordinate steps on the
/// interpolated curves, halved when no step helps, down to a hundredth of the grid spacing.
fn refine_two(b: &Basis, x: &[f64], s: &Stats, start: (f64, f64), fit: PixelFit) -> PixelFit {
    let step_ln = b.log_tau[1] - b.log_tau[0];
    let (mut u, mut best) = ([start.0, start.1], fit);
    let (mut d1, mut d2) = (curve_at(b, u[0]), curve_at(b, u[1]));
    let mut h = 0.5;
    while h > 0.01 {
        let mut moved = false;
        for k in 0..2 {
            for sign in [-1.0, 1.0] {
                let mut v = u;
                v[k] += sign * h;
                let dv = curve_at(b, v[k]);
                let r = if k == 0 { two_on(x, s, &dv, &d2) } else { two_on(x, s, &d1, &dv) };
                if let Some((a1, a2, bg, sse)) = r {
                    if a1 >= 0.0 && a2 >= 0.0 && sse < best.sse {
                        u = v;
                        if k == 0 {
                            d1 = dv;
                        } else {
                            d2 = dv;
                        }
                        let tau = |w: f64| (b.log_tau[0] + w * step_ln).exp();
                        best = PixelFit { comps: [(tau(u[0]), a1), (tau(u[1]), a2)], background: bg, sse };
                        moved = true;
                    }
                }
            }
        }
        if !moved {
            h *= 0.5;
        }
    }
    best
}

/// Fit one waveform: the best single exponential (parabola-refined on the grid) and, if asked,
/// the best pair (coarse pairs, then the fine neighbourhood).
/// Whether every component of `f` lies strictly inside the lifetimes searched (an optimum on
/// the grid's first or last point is on the bound, or beyond it).
fn inside(b: &Basis, f: &PixelFit) -> bool {
    let (lo, hi) = (b.log_tau[0], b.log_tau[b.log_tau.len() - 1]);
    let step = b.log_tau[1] - b.log_tau[0];
    f.comps.iter().filter(|c| c.1 > 0.0).all(|c| {
        let l = c.0.ln();
        l > lo + 0.01 * step && l < hi - 0.01 * step
    })
}

fn fit_pixel(b: &Basis, x: &[f64], comps: Components, aic: f64) -> Option<PixelFit> {
    let g = b.log_tau.len();
    let s = Stats::new(b, x);
    // one component
    let ones: Vec<Option<(f64, f64, f64)>> = (0..g).map(|i| s.one(b, i).filter(|o| o.0 > 0.0)).collect();
    let best1 = (0..g)
        .filter(|&i| ones[i].is_some())
        .min_by(|&i, &j| ones[i].map(|o| o.2).unwrap_or(f64::MAX).total_cmp(&ones[j].map(|o| o.2).unwrap_or(f64::MAX)));
    let one = best1.and_then(|i| {
        let (a, bg, sse) = ones[i]?;
        let step = b.log_tau[1] - b.log_tau[0];
        // continuous refinement on the interpolated curves, steps halved to 1/100 of the grid
        let (mut u, mut best) = (i as f64, PixelFit { comps: [(b.log_tau[i].exp(), a), (0.0, 0.0)], background: bg, sse });
        let mut h = 0.5;
        while h > 0.01 {
            let mut moved = false;
            for sign in [-1.0, 1.0] {
                let v = u + sign * h;
                let d = curve_at(b, v);
                let sd = d.iter().sum::<f64>();
                let p = dot(&d, x);
                if let Some([a, bg]) = solve([[dot(&d, &d), sd], [sd, s.n]], [p, s.q]) {
                    let sse = s.r - a * p - bg * s.q;
                    if a > 0.0 && sse < best.sse {
                        (u, best, moved) =
                            (v, PixelFit { comps: [((b.log_tau[0] + v * step).exp(), a), (0.0, 0.0)], background: bg, sse }, true);
                    }
                }
            }
            if !moved {
                h *= 0.5;
            }
        }
        Some(best)
    });
    // an optimum on a bound of the lifetimes searched is not an estimate
    let one = one.filter(|f| inside(b, f));
    if comps == Components::One {
        return one;
    }
    // two components: every pair on a coarse grid, then the fine neighbourhood of the best
    let stride = 5;
    let mut best: Option<(usize, usize, (f64, f64, f64, f64))> = None;
    let consider = |i: usize, j: usize, best: &mut Option<(usize, usize, (f64, f64, f64, f64))>| {
        if i >= j || j >= g {
            return;
        }
        if let Some(t) = s.two(b, i, j) {
            if t.0 >= 0.0 && t.1 >= 0.0 && best.as_ref().is_none_or(|(_, _, bt)| t.3 < bt.3) {
                *best = Some((i, j, t));
            }
        }
    };
    for i in (0..g).step_by(stride) {
        for j in (i + stride..g).step_by(stride) {
            consider(i, j, &mut best);
        }
    }
    for _ in 0..2 {
        if let Some((bi, bj, _)) = best {
            for i in bi.saturating_sub(stride)..=(bi + stride).min(g - 1) {
                for j in bj.saturating_sub(stride)..=(bj + stride).min(g - 1) {
                    consider(i, j, &mut best);
                }
            }
        }
    }
    let two = best.map(|(i, j, (ai, aj, bg, sse))| {
        refine_two(
            b,
            x,
            &s,
            (i as f64, j as f64),
            PixelFit { comps: [(b.log_tau[i].exp(), ai), (b.log_tau[j].exp(), aj)], background: bg, sse },
        )
    });
    let two = two.filter(|f| inside(b, f));
    match (one, two, comps) {
        (o, Some(t), Components::Two) => Some(t).or(o),
        (Some(o), Some(t), _) => {
            let n = x.len() as f64;
            let crit = |sse: f64, k: f64| n * (sse.max(1e-300) / n).ln() + 2.0 * k;
            Some(if crit(t.sse, 5.0) + aic < crit(o.sse, 3.0) { t } else { o })
        }
        (o, t, _) => o.or(t),
    }
}

/// The frame's onset and IRF: a bi-exponential fit of the summed decay over a grid of onsets
/// (quarter bins about the steepest rise) and IRF widths (if not given), then refined on
/// `pixels` (a sample of the brightest waveforms).
fn instrument(c: Cycle, total: &[f64], pixels: &[Vec<f64>], irf: &IrfModel, range: [f64; 2]) -> (f64, f64) {
    let n = c.bins;
    // steepest cyclic rise of the summed decay
    let rise = (0..n).max_by(|&i, &j| (total[(i + 1) % n] - total[i]).total_cmp(&(total[(j + 1) % n] - total[j]))).unwrap_or(0);
    let sse = |t0: f64, fwhm: f64| -> f64 {
        let k = kernel_of(c, irf, fwhm);
        let b = Basis::new(c, &k, t0, range, 48);
        fit_pixel(&b, total, Components::Two, 0.0).map_or(f64::MAX, |f| f.sse)
    };
    let widths: Vec<f64> = match irf {
        IrfModel::Gaussian(None) => (0..=12).map(|i| i as f64 * 0.25e-9).collect(),
        IrfModel::Gaussian(Some(w)) => vec![*w],
        IrfModel::Measured(_) => vec![0.0],
    };
    let reach = 12.0; // bins before the steepest rise where the onset may be (a wide IRF)
    let starts: Vec<f64> = (0..((reach + 4.0) * 4.0) as usize).map(|q| (rise as f64 + 1.0 + 4.0 - q as f64 * 0.25) * c.dt_s).collect();
    let grid: Vec<(f64, f64, f64)> =
        starts.par_iter().flat_map_iter(|&t0| widths.iter().map(move |&w| (t0, w))).map(|(t0, w)| (t0, w, sse(t0, w))).collect();
    let (mut t0, mut w, _) = grid.iter().copied().min_by(|a, b| a.2.total_cmp(&b.2)).unwrap_or((rise as f64 * c.dt_s, 0.0, f64::MAX));
    // refine on the pixels themselves (a global analysis: the onset and IRF shared, one or two
    // lifetimes per pixel), the summed decay being a mixture of more lifetimes than two
    let step = (pixels.len() / 64).max(1);
    let sample: Vec<&Vec<f64>> = pixels.iter().step_by(step).take(64).collect();
    let global = |t0: f64, fwhm: f64| -> f64 {
        let k = kernel_of(c, irf, fwhm);
        let b = Basis::new(c, &k, t0, range, 120);
        sample.par_iter().map(|v| fit_pixel(&b, v, Components::Two, 0.0).map_or(f64::MAX, |f| f.sse)).sum()
    };
    let mut best = global(t0, w);
    let mut dt0 = 0.25 * c.dt_s;
    let mut dw = if widths.len() > 1 { 0.125e-9 } else { 0.0 };
    for _ in 0..48 {
        if dt0 < 0.0005 * c.dt_s && (dw == 0.0 || dw < 0.002e-9) {
            break;
        }
        let cands: Vec<(f64, f64)> = [(-1.0, 0.0), (1.0, 0.0), (0.0, -1.0), (0.0, 1.0)]
            .iter()
            .filter(|(_, b)| *b == 0.0 || dw > 0.0)
            .map(|(a, b)| (t0 + a * dt0, (w + b * dw).max(0.0)))
            .collect();
        let vals: Vec<(f64, f64, f64)> = cands.iter().map(|&(a, b)| (a, b, global(a, b))).collect();
        match vals.iter().min_by(|x, y| x.2.total_cmp(&y.2)) {
            Some(&(a, b, v)) if v < best => (t0, w, best) = (a, b, v),
            _ => {
                dt0 *= 0.5;
                dw *= 0.5;
            }
        }
    }
    (t0.rem_euclid(c.period_s), w)
}

/// Fit every pixel of `x` `[T, H, W]` (one code cycle of bins `bin_width_s`).
///
/// # Shapes
/// - `x`: `[T, H, W]` → lifetimes `[4, H, W]`, background `[H, W]`, phasor `[2, H, W]`
pub fn fit_cube(x: &ArrayView3<'_, f32>, bin_width_s: f64, opts: &FitOptions) -> LifetimeFit {
    let (t, h, w) = x.dim();
    let c = Cycle::new(t, bin_width_s);
    let totals = x.sum_axis(Axis(0)); // [H, W]
    let max = totals.iter().fold(0f32, |m, &v| m.max(v));
    let bright = |r: usize, col: usize| totals[(r, col)] > opts.min_intensity * max && totals[(r, col)] > 0.0;
    let summed: Vec<f64> = (0..t)
        .map(|j| {
            (0..h)
                .flat_map(|r| (0..w).map(move |col| (r, col)))
                .filter(|&(r, col)| bright(r, col))
                .map(|(r, col)| x[(j, r, col)] as f64)
                .sum()
        })
        .collect();
    let mut lifetimes = Array3::<f32>::from_elem((4, h, w), f32::NAN);
    let mut background = Array2::<f32>::from_elem((h, w), f32::NAN);
    let mut phasor = Array3::<f32>::from_elem((2, h, w), f32::NAN);
    if max <= 0.0 || t < 4 {
        return LifetimeFit { lifetimes, background, phasor, onset_s: f64::NAN, irf_fwhm_s: f64::NAN };
    }
    // the brightest pixels' waveforms, for the global refinement
    let mut order: Vec<(usize, usize)> = (0..h).flat_map(|r| (0..w).map(move |col| (r, col))).filter(|&(r, col)| bright(r, col)).collect();
    order.sort_by(|a, b| totals[*b].total_cmp(&totals[*a]));
    let waves: Vec<Vec<f64>> = order.iter().take(256).map(|&(r, col)| (0..t).map(|j| x[(j, r, col)] as f64).collect()).collect();
    let (onset_s, fwhm) = instrument(c, &summed, &waves, &opts.irf, opts.tau_range_s);
    let kernel = kernel_of(c, &opts.irf, fwhm);
    let basis = Basis::new(c, &kernel, onset_s, opts.tau_range_s, 400);
    // the IRF's own phasor at the first harmonic: the delay e^{iωt₀} times the kernel's
    // transform (the bins' own box filter is common to both and within 3·10⁻⁵ of 1 here)
    let omega = 2.0 * std::f64::consts::PI / t as f64; // per bin
    let harmonic = |v: &[f64]| -> (f64, f64, f64) {
        let (mut s0, mut re, mut im) = (0.0, 0.0, 0.0);
        for (j, &u) in v.iter().enumerate() {
            let ph = omega * (j as f64 + 0.5);
            s0 += u;
            re += u * ph.cos();
            im += u * ph.sin();
        }
        (s0, re, im)
    };
    let (kre, kim) = kernel.weights().fold((0.0, 0.0), |(a, b), (d, k)| {
        let ph = omega * d as f64;
        (a + k * ph.cos(), b + k * ph.sin())
    });
    let d = omega * onset_s / bin_width_s;
    let (rre, rim) = (kre * d.cos() - kim * d.sin(), kre * d.sin() + kim * d.cos());
    let rmag = rre * rre + rim * rim;
    let fits: Vec<Option<(PixelFit, (f64, f64))>> = (0..h * w)
        .into_par_iter()
        .map(|p| {
            let (r, col) = (p / w, p % w);
            if !bright(r, col) {
                return None;
            }
            let v: Vec<f64> = (0..t).map(|j| x[(j, r, col)] as f64).collect();
            let f = fit_pixel(&basis, &v, opts.components, opts.two_component_aic)?;
            let clean: Vec<f64> = v.iter().map(|u| u - f.background).collect();
            let (s0, re, im) = harmonic(&clean);
            // (re + i·im)/s0 divided by the reference's (rre + i·rim)
            let (pr, pi) = (re / s0, im / s0);
            let g = (pr * rre + pi * rim) / rmag;
            let s = (pi * rre - pr * rim) / rmag;
            Some((f, (g, s)))
        })
        .collect();
    for (p, fit) in fits.into_iter().enumerate() {
        let Some((f, (g, s))) = fit else { continue };
        let (r, col) = (p / w, p % w);
        let [(t1, a1), (t2, a2)] = f.comps;
        let (mean, lo, hi, frac) = if a2 > 0.0 && a1 + a2 > 0.0 {
            let m = (a1 * t1 + a2 * t2) / (a1 + a2);
            if t1 <= t2 {
                (m, t1, t2, a1 / (a1 + a2))
            } else {
                (m, t2, t1, a2 / (a1 + a2))
            }
        } else {
            (t1, t1, t1, 1.0)
        };
        for (k, v) in [mean, lo, hi, frac].into_iter().enumerate() {
            lifetimes[(k, r, col)] = v as f32;
        }
        background[(r, col)] = f.background as f32;
        phasor[(0, r, col)] = g as f32;
        phasor[(1, r, col)] = s as f32;
    }
    LifetimeFit { lifetimes, background, phasor, onset_s, irf_fwhm_s: if matches!(opts.irf, IrfModel::Measured(_)) { 0.0 } else { fwhm } }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array3;

    const DT: f64 = 32.0 / 607e6 / 256.0; // heterodyne K = 8 bins, 205.9 ps

    /// A cube of `[T, 2, 2]` pixels with the given decays, onset, Gaussian IRF and background,
    /// built as the datasets crate's generator builds them.
    fn cube(pixels: &[&[(f64, f64)]], t0: f64, fwhm: f64, bg: f64) -> Array3<f32> {
        let grid = tcsense_datasets::grid::TimeGrid { length: 32, clock_hz: 607e6, sampling: tcsense_sensor::Sampling::Heterodyne(8) };
        let mut x = Array3::<f32>::zeros((256, 1, pixels.len()));
        for (p, comps) in pixels.iter().enumerate() {
            for &(tau, a) in comps.iter() {
                let d = IrfKernel::gaussian(grid.cycle(), fwhm).apply(&decay_bin_averages(grid.cycle(), tau, t0));
                for j in 0..256 {
                    x[(j, 0, p)] += (a * d[j]) as f32;
                }
            }
            for j in 0..256 {
                x[(j, 0, p)] += bg as f32;
            }
        }
        x
    }

    #[test]
    fn recovers_single_and_double_exponentials_at_any_onset_and_irf() {
        for &(t0, fwhm, bg) in &[(2e-9, 0.0, 0.0), (31.7e-9, 0.6e-9, 0.02), (51.9e-9, 1.4e-9, 0.05), (0.1e-9, 0.9e-9, 0.0)] {
            let pixels: [&[(f64, f64)]; 4] =
                [&[(0.4e-9, 1.0)], &[(3.1e-9, 0.7)], &[(1.0e-9, 0.6), (4.0e-9, 0.4)], &[(0.8e-9, 0.3), (2.5e-9, 0.5)]];
            let x = cube(&pixels, t0, fwhm, bg);
            // the IRF unknown: its width is fitted with the onset
            let free = fit_cube(&x.view(), DT, &FitOptions::default());
            assert!((free.irf_fwhm_s - fwhm).abs() < 0.15e-9, "IRF {} vs {fwhm}", free.irf_fwhm_s); // below a bin (206 ps) a width is hardly seen
            let again = fit_cube(&x.view(), DT, &FitOptions::default());
            assert_eq!(free.lifetimes, again.lifetimes, "deterministic");
            // the IRF known, as reconvolution software takes it: every lifetime within 2 %
            let fit = fit_cube(&x.view(), DT, &FitOptions { irf: IrfModel::Gaussian(Some(fwhm)), ..Default::default() });
            let want_t0 = t0;
            assert!(
                ((fit.onset_s - want_t0 + 26.35e-9).rem_euclid(52.7e-9) - 26.35e-9).abs() < 0.05 * DT + 0.02e-9,
                "onset {} vs {want_t0}",
                fit.onset_s
            );
            for (p, comps) in pixels.iter().enumerate() {
                let total: f64 = comps.iter().map(|c| c.1).sum();
                let mean = comps.iter().map(|c| c.0 * c.1).sum::<f64>() / total;
                let got = fit.lifetimes[(0, 0, p)] as f64;
                assert!((got / mean - 1.0).abs() < 0.02, "t0 {t0:e}, IRF {fwhm:e}: pixel {p} τ_m {got:e} vs {mean:e}");
                let free_m = free.lifetimes[(0, 0, p)] as f64;
                assert!((free_m / mean - 1.0).abs() < 0.05, "fitted IRF: pixel {p} τ_m {free_m:e} vs {mean:e}");
                if comps.len() == 2 {
                    for (k, c) in comps.iter().enumerate() {
                        let got = fit.lifetimes[(1 + k, 0, p)] as f64;
                        assert!((got / c.0 - 1.0).abs() < 0.02, "pixel {p} τ{} {got:e} vs {:e}", k + 1, c.0);
                    }
                    assert!((fit.lifetimes[(3, 0, p)] as f64 - comps[0].1 / total).abs() < 0.02);
                }
                assert!((fit.background[(0, p)] as f64 - bg).abs() < 1e-3 * (1.0 + bg));
            }
            // single exponentials on the semicircle at their lifetime
            let omega = 2.0 * std::f64::consts::PI / (256.0 * DT);
            for (p, tau) in [(0usize, 0.4e-9f64), (1, 3.1e-9)] {
                let (g, s) = (fit.phasor[(0, 0, p)] as f64, fit.phasor[(1, 0, p)] as f64);
                let wt = omega * tau;
                assert!(
                    (g - 1.0 / (1.0 + wt * wt)).abs() < 2e-3 && (s - wt / (1.0 + wt * wt)).abs() < 2e-3,
                    "pixel {p}: ({g}, {s}) for τ {tau:e}"
                );
            }
        }
    }

    /// A decay outside the lifetimes searched is not placed on the bound: NaN, while a pixel
    /// inside keeps its lifetime (a poor cube gave most pixels the 60 ns bound).
    #[test]
    fn an_optimum_on_a_bound_is_no_lifetime() {
        // (most of the frame's light in 2 ns decays: the onset is fitted on the frame's sum)
        let pixels: [&[(f64, f64)]; 4] = [&[(2e-9, 1.0)], &[(30e-9, 0.2)], &[(0.05e-9, 0.2)], &[(2e-9, 1.0)]];
        let x = cube(&pixels, 5e-9, 0.5e-9, 0.0);
        let fit = fit_cube(
            &x.view(),
            DT,
            &FitOptions {
                irf: IrfModel::Gaussian(Some(0.5e-9)),
                components: Components::One,
                tau_range_s: [0.5e-9, 10e-9],
                ..Default::default()
            },
        );
        assert!((fit.lifetimes[(0, 0, 0)] as f64 / 2e-9 - 1.0).abs() < 0.01, "{}", fit.lifetimes[(0, 0, 0)]);
        assert!(fit.lifetimes[(0, 0, 1)].is_nan(), "30 ns searched up to 10 ns: {}", fit.lifetimes[(0, 0, 1)]);
        assert!(fit.lifetimes[(0, 0, 2)].is_nan(), "0.05 ns searched from 0.5 ns: {}", fit.lifetimes[(0, 0, 2)]);
    }

    #[test]
    fn dark_pixels_get_no_lifetime_and_a_known_irf_is_kept() {
        let pixels: [&[(f64, f64)]; 2] = [&[(2e-9, 1.0)], &[(2e-9, 0.001)]];
        let x = cube(&pixels, 5e-9, 0.5e-9, 0.0);
        let fit = fit_cube(
            &x.view(),
            DT,
            &FitOptions { irf: IrfModel::Gaussian(Some(0.5e-9)), components: Components::One, ..Default::default() },
        );
        assert!((fit.lifetimes[(0, 0, 0)] as f64 / 2e-9 - 1.0).abs() < 0.01);
        assert!(fit.lifetimes[(0, 0, 1)].is_nan() && fit.phasor[(0, 0, 1)].is_nan());
        assert_eq!(fit.irf_fwhm_s, 0.5e-9);
        // a measured IRF: the bin-integrated Gaussian itself, anywhere in the cycle
        let k = IrfKernel::gaussian(Cycle::new(256, DT), 0.5e-9);
        let mut irf = vec![0.0; 256];
        for (d, v) in k.weights() {
            irf[(d + 100 + 256) as usize % 256] = v;
        }
        let fit = fit_cube(&x.view(), DT, &FitOptions { irf: IrfModel::Measured(irf), components: Components::One, ..Default::default() });
        assert!((fit.lifetimes[(0, 0, 0)] as f64 / 2e-9 - 1.0).abs() < 0.01, "{}", fit.lifetimes[(0, 0, 0)]);
    }
}
