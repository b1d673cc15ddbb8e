//! Ranges straight from the tap images with no decoder before them: the range fit's templates
//! ([`crate::range`]) as dense linear algebra, the way compressive single-photon LiDAR
//! decodes coded histograms against a table of templates.
//!
//! 1. **Every candidate at once.** A pixel of subpixel type `n` and taps `y` costs, at each of
//!    the `C = T·os` candidate ranges of the cycle, `‖y − a·g_n(c) − b·s_n‖²` minimised over an
//!    amplitude and an ambient level `a, b ≥ 0` in closed form: the products `g_n(c)·y` of all
//!    candidates are one `[M] × [M, C]` product, and the rest is element-wise over `c` (f32,
//!    vectorised).
//! 2. **A first estimate per pixel.** The costs summed over the `window × window` neighbourhood
//!    (a box filter over the cost volume), the argmin over the **whole cycle**. This needs codes
//!    that do not alias: `tcsense codes analyze` must give an alias distance ≥ 0.5 (the designed
//!    codes: 0.77; the prototype's 0.01, which a global search confuses).
//! 3. **Edges kept.** The window is then restricted to the neighbours on the same surface (their
//!    first estimate within [`RangeFitOptions::edge_bins`] of the pixel's), its summed cost
//!    searched within [`RangeFitOptions::search_bins`] of the first estimate, and the best
//!    candidate refined with no new cost inside a segment between the bins' centres (a
//!    parabola) and two on a centre, where the templates have a kink and a parabola through
//!    it would be biased (each side's parabola through the kink and half a candidate off).
//!    Every `os`-th candidate sits on a bin's centre for this.
//! 4. **A second return.** Each pixel's residual after its single return is matched against
//!    every candidate (its product with each template, and the part of each template outside
//!    the first's and the ambient's span: one more `[M] × [M, C]` product and a table). Summed
//!    over the window with **one amplitude** for the second return — a sheet's amplitude varies
//!    slowly, so the products add coherently and the noise does not — it says how much of the
//!    window's residual a second return could remove: where less than
//!    40 % ([`PRESCREEN`]), there is none (on the standard set this keeps 99 % of the pixels that
//!    have two returns and 20 % of those with one). Elsewhere its highest local maxima at least
//!    two bins from the first seed the joint fit, each screened by one joint evaluation with the
//!    first held where it is; where the best halves the residual, the joint fit of two returns
//!    (the range fit's coordinate descent, within a bin) runs, and is kept where it leaves at
//!    most [`DepthFitOptions::second_residual`] of the single return's residual and the weaker
//!    return holds [`DepthFitOptions::second_amplitude`] of the stronger's amplitude. With no
//!    decoder to propose a second return, the rule is stricter than the range fit's: a free
//!    second return also fits the noise and what the template lacks (measured on the standard
//!    set: a joint fit leaves a median 5 % of the single residual where there are two returns,
//!    48 % where there is one).
//!    Seeded by a network's modes, the second return is searched on the window its first was
//!    refined on, grown in dim light (step 3), and there each rule also passes where the second
//!    return is significant: [`SECOND_EVIDENCE_NATS`] of the frame's nats or more.
//!
//! Time at 188×212 on 2 cores (designed codes, T = 32, 4 candidates per bin): one return 25 ms
//! per frame, two about 115 ms (the joint fits of two returns: `WindowFit::joint` alone 38 %).
//!
//! Pixels whose charge is below [`DepthFitOptions::min_intensity`] of the frame's brightest get
//! no return, and a best candidate on the bound of the restricted search is no estimate (NaN).

use ndarray::{Array2, Array3, ArrayView3};
use rayon::prelude::*;
use tcsense_sensor::waveform::subpixel_flat;
use tcsense_sensor::{MeasurementMatrix, C};

use crate::engine::{argmin, parabola_min, window_sums};
use crate::evidence::{CostVolume, Evidence};
use crate::range::{cyclic_gap, wrap, wrap_index, RangeFitOptions, Templates, WindowFit, EXPLAINED, MIN_GAP};

/// The pre-screen of a second return: one return of one amplitude over the window must remove at
/// least this share of the window's single-return residual.
pub const PRESCREEN: f64 = 0.4;

/// Local maxima of the matched residual tried as the second return's seed.
const SEEDS: usize = 4;

/// The screen of a second return: the joint cost with the first held where the single fit put
/// it and the second at a seed must be at most this share of the single return's before the
/// joint fit is run.
const SCREEN: f64 = 0.5;

/// How well a posterior mode's window must place its best candidate before it stops growing
/// (bins: one standard deviation, from the summed cost's curvature at that candidate in the
/// frame's nats). Seeded by a mode ([`Seeds::Modes`]), the window on the pixel's surface that
/// refines it starts at the fit's side and grows by a pixel a side, up to
/// [`DepthFitOptions::mode_window`], while it is less precise than this: in bright light the
/// fit's 3×3 window is sharp and stays, in dim light the window of like-range neighbours widens.
/// Measured on `zoo:unet-lidar-evidence-8k` over `scripts/lidar_ladder.sh`'s sets
/// (docs/results.md): a 7×7 window for every pixel takes the motorcycle's median error at 0.02
/// of the full well from 0.275 to 0.208 bins but at 0.8 from 0.029 to 0.070; grown to 0.12 bins,
/// the error at 0.02 falls on every set (the motorcycle 0.61–0.67× → 0.51–0.58× the fit's, the
/// dense sheets 0.89–0.95× → 0.62–0.76×) and at 0.8 stays within 1.03× the fit's (0.10: 1.05×).
pub const MODE_PRECISION_BINS: f64 = 0.12;

/// A second return on a window that grew (a network's mode in dim light) is also kept where it
/// lowers the window's cost by at least this many of the frame's nats (each rule of a second
/// return, the pre-screen, the screen and the joint fit, then passes on its share of the residual
/// or on this gain). In dim light the residual is mostly noise, so a true second return removes
/// too small a share of it for the share rules, while over the grown window its gain in nats
/// adds up; the share rules still decide in bright light, where the window stays 3×3. Measured on
/// `zoo:unet-lidar-evidence-8k` over `scripts/lidar_ladder.sh`'s sets (docs/results.md, "Second
/// returns on the grown window"): at 0.02 of the full well the standard set's second returns are
/// found on 50 % of the pixels that have one (the fit: 29 %) with false ones on 19 % of those
/// that have none (the fit: 28 %); 7 nats: 30 % and 8 %; share rules alone: 3 % and 2 %.
pub const SECOND_EVIDENCE_NATS: f64 = 5.0;

/// The largest half-side of the window that refines a posterior's mode (3: 7×7 pixels;
/// [`DepthFitOptions::mode_window`] of [`DepthFitOptions::for_evidence`] and of
/// [`DepthFitOptions::pooled`]; the plain fit keeps its window, 3×3).
pub const MODE_MAX_HALF: usize = 3;

/// The best candidate `c` of a cyclic cost, refined between its neighbours (in candidates, within
/// ±½): the templates are linear between the bins' centres (every `os`-th candidate), so the
/// cost is smooth between them and has kinks on them. Inside a segment, the parabola through
/// the best and its two neighbours (no cost evaluated again); on a kink, the parabola of each
/// side through the kink, the cost `at` half a candidate away on that side and the neighbour,
/// whose vertex lies on that side and below the kink, else the kink itself.
fn refine(cost: &[f32], c: usize, os: usize, at: &mut dyn FnMut(f64) -> f64) -> f64 {
    let n = cost.len();
    let v = |k: isize| cost[(c as isize + k).rem_euclid(n as isize) as usize] as f64;
    if !c.is_multiple_of(os) || os < 2 {
        return parabola_min(v(-1), v(0), v(1));
    }
    // on a kink: each side's parabola through the kink, half a candidate and one candidate away
    let (l, centre, r) = (at(-0.5), v(0), at(0.5));
    let side = |x: [f64; 3], y: [f64; 3]| -> Option<(f64, f64)> {
        let d01 = (y[1] - y[0]) / (x[1] - x[0]);
        let d12 = (y[2] - y[1]) / (x[2] - x[1]);
        let a = (d12 - d01) / (x[2] - x[0]);
        if a <= 0.0 {
            return None;
        }
        let b = d01 - a * (x[0] + x[1]);
        let xv = -b / (2.0 * a);
        Some((xv, y[0] + (xv - x[0]) * (d01 + a * (xv - x[1]))))
    };
    let left = side([-1.0, -0.5, 0.0], [v(-1), l, centre]).filter(|&(x, _)| (-1.0..0.0).contains(&x));
    let right = side([0.0, 0.5, 1.0], [centre, r, v(1)]).filter(|&(x, _)| x > 0.0 && x <= 1.0);
    let best = match (left, right) {
        (Some(a), Some(b)) => {
            if a.1 <= b.1 {
                a
            } else {
                b
            }
        }
        (Some(a), None) | (None, Some(a)) => a,
        (None, None) => (0.0, centre),
    };
    if best.1 < centre {
        best.0.clamp(-0.5, 0.5)
    } else {
        0.0
    }
}

/// Settings of [`fit_ranges`].
#[derive(Debug, Clone, PartialEq)]
pub struct DepthFitOptions {
    /// The window, search, candidates per bin, edge rule and second-return rule.
    pub fit: RangeFitOptions,
    /// Pixels whose taps sum to less than this fraction of the brightest pixel's get no return.
    pub min_intensity: f32,
    /// Returns per pixel: 1, or 2 (a second where the taps call for it).
    pub returns: usize,
    /// A second return is kept where the joint fit leaves at most this share of the single
    /// return's residual (with no decoder to propose it, a stricter rule than the range fit's
    /// [`RangeFitOptions::second_return_residual`]: a free second return also fits the noise
    /// and whatever the pulse template lacks).
    pub second_residual: f64,
    /// … and where the weaker of the two holds at least this share of the stronger's amplitude
    /// (summed over the window).
    pub second_amplitude: f64,
    /// Pool each window with the neighbouring windows of like ranges that tile this side (an
    /// odd multiple of the window's; 0: the window alone): the first return is the pooled
    /// cost's best candidate, refined in the tap domain where it is the window's own
    /// ([`RangeTemplates::pooled_modes`]).
    pub pool_like: usize,
    /// The largest side of the window that refines a posterior's mode ([`Seeds::Modes`]): it
    /// grows from the fit's window while less precise than [`MODE_PRECISION_BINS`] (odd, up to
    /// [`crate::range::MAX_WINDOW`]; 7 for a network's evidence; at most the fit's window, as
    /// the fits' default 3, keeps that window fixed, whatever side it is given).
    pub mode_window: usize,
}

impl Default for DepthFitOptions {
    fn default() -> Self {
        DepthFitOptions {
            fit: RangeFitOptions::default(),
            min_intensity: 0.02,
            returns: 2,
            second_residual: 0.3,
            second_amplitude: 0.1,
            pool_like: 0,
            mode_window: 3,
        }
    }
}

impl DepthFitOptions {
    /// The settings of the fit whose evidence a network reads ([`RangeTemplates::evidence`]):
    /// `oversample` candidates per bin, every lit pixel (no intensity floor: the network's
    /// confidence decides), `returns` (1 or 2).
    pub fn for_evidence(oversample: usize, returns: usize) -> DepthFitOptions {
        DepthFitOptions {
            fit: RangeFitOptions { oversample, ..Default::default() },
            min_intensity: 0.0,
            returns: returns.clamp(1, 2),
            mode_window: 2 * MODE_MAX_HALF + 1,
            ..Default::default()
        }
    }

    /// These settings pooled by likeness over `side` (0: the window alone,
    /// [`Self::pool_like`]): each pixel's first return is the pooled cost's best candidate,
    /// refined on a window of like-range neighbours that grows in dim light as a network's
    /// mode's does (up to [`MODE_MAX_HALF`]), and stays the fit's window in bright light.
    ///
    /// The growth is what pooling needs in dim light: where a 3×3 window cannot place its
    /// best candidate to [`MODE_PRECISION_BINS`], refining the pooled mode on it pulls the mode
    /// back to that window's noise. On the six LiDAR sets of `scripts/lidar_ladder.sh`
    /// (docs/results.md) it takes `depth-fit-pooled` from 0.67× to 0.36× the 3×3 fit's median
    /// first-return error at 0.02 of the full well (SBR 1: 0.63× → 0.31×), from 0.94× to 0.75×
    /// at 0.1 and from 0.98× to 0.97× at 0.8.
    pub fn pooled(self, side: usize) -> DepthFitOptions {
        let mode_window = if side > 0 { self.mode_window.max(2 * MODE_MAX_HALF + 1) } else { self.mode_window };
        DepthFitOptions { pool_like: side, mode_window, ..self }
    }

    /// `Err(what was expected)` for settings the fit cannot use.
    pub fn validate(&self) -> Result<(), String> {
        self.fit.validate()?;
        if !(0.0..1.0).contains(&self.min_intensity) {
            return Err(format!("min_intensity {}: expected a fraction in [0, 1)", self.min_intensity));
        }
        if !(self.second_residual > 0.0 && self.second_residual <= 1.0) {
            return Err(format!("second_residual {}: expected a share in (0, 1]", self.second_residual));
        }
        if !(0.0..=1.0).contains(&self.second_amplitude) {
            return Err(format!("second_amplitude {}: expected a share in [0, 1]", self.second_amplitude));
        }
        if self.pool_like != 0 && !crate::evidence::pooled_side(self.pool_like, self.fit.window) {
            return Err(format!(
                "pool_like {}: expected 0 (no pooling) or an odd multiple of the window's side {} above it, up to {} pixels (e.g. 9, 15, 21)",
                self.pool_like,
                self.fit.window,
                crate::range::MAX_WINDOW
            ));
        }
        if !(1..=2).contains(&self.returns) {
            return Err(format!("returns {}: expected 1 or 2", self.returns));
        }
        if self.mode_window.is_multiple_of(2) || self.mode_window > crate::range::MAX_WINDOW {
            return Err(format!(
                "mode_window {}: expected an odd side up to {} pixels (e.g. 7; at most the window's, {}: never grown)",
                self.mode_window,
                crate::range::MAX_WINDOW,
                self.fit.window
            ));
        }
        Ok(())
    }
}

/// The power of two that brings `top` (a frame's largest magnitude) into [1, 2); 1 where it is
/// 0 or not finite.
fn unit_scale(top: f32) -> f32 {
    if top > 0.0 && top.is_finite() {
        // (within f32's normal exponents: a subnormal frame is scaled as far as they go)
        (2f64).powi((-(top.log2().floor() as i32)).clamp(-126, 127)) as f32
    } else {
        1.0
    }
}

/// The candidates' templates of one subpixel type, struct of arrays in f32 for the dense pass:
/// `g[k·C + c]`, the Gram entries `g·g`, `g·s` and `1/det` per candidate, `s` and `s·s`.
struct Dense {
    g: Vec<f32>,
    gg: Vec<f32>,
    gs: Vec<f32>,
    inv_det: Vec<f32>,
    inv_gg: Vec<f32>,
    s: Vec<f32>,
    ss: f32,
}

impl Dense {
    fn of(tpl: &Templates) -> Vec<Dense> {
        let (m, cands) = (tpl.m, tpl.candidates());
        (0..tpl.n)
            .map(|n| {
                let mut g = vec![0f32; m * cands];
                let (mut gg, mut gs, mut inv_det, mut inv_gg) =
                    (vec![0f32; cands], vec![0f32; cands], vec![0f32; cands], vec![0f32; cands]);
                let ss = tpl.gram[n * cands][2];
                for c in 0..cands {
                    for (k, &v) in tpl.g(n, c).iter().enumerate() {
                        g[k * cands + c] = v as f32;
                    }
                    let [a, b, _] = tpl.gram[n * cands + c];
                    let det = a * ss - b * b;
                    gg[c] = a as f32;
                    gs[c] = b as f32;
                    // an ill-posed solve takes the boundary (one column alone)
                    inv_det[c] = if det > 1e-12 * a * ss { (1.0 / det) as f32 } else { 0.0 };
                    inv_gg[c] = if a > 0.0 { (1.0 / a) as f32 } else { 0.0 };
                }
                Dense { g, gg, gs, inv_det, inv_gg, s: tpl.s(n).iter().map(|&v| v as f32).collect(), ss: ss as f32 }
            })
            .collect()
    }

    /// The products `g(c)·v` of `v` `[M]` with every candidate's template, into `out` `[C]`:
    /// one `[M] × [M, C]` product, the loop over the candidates innermost (vectorised).
    fn products(&self, v: &[f32], out: &mut [f32]) {
        let cands = out.len();
        out.fill(0.0);
        for (k, &vk) in v.iter().enumerate() {
            for (o, &g) in out.iter_mut().zip(&self.g[k * cands..(k + 1) * cands]) {
                *o += g * vk;
            }
        }
    }

    /// The single-return cost of taps `y` `[M]` at every candidate into `out` `[C]` (`gy` `[C]`
    /// scratch): `yy − max fit` over `a, b ≥ 0`, as `range_fit::nnls2`.
    fn costs(&self, y: &[f32], gy: &mut [f32], out: &mut [f32]) {
        let cands = out.len();
        self.products(y, gy);
        let yy: f32 = y.iter().map(|v| v * v).sum();
        let sy: f32 = y.iter().zip(&self.s).map(|(a, b)| a * b).sum();
        let (ss, inv_ss) = (self.ss, if self.ss > 0.0 { 1.0 / self.ss } else { 0.0 });
        let only_s = sy.max(0.0) * sy.max(0.0) * inv_ss;
        for c in 0..cands {
            let g = gy[c];
            let a = (ss * g - self.gs[c] * sy) * self.inv_det[c];
            let b = (self.gg[c] * sy - self.gs[c] * g) * self.inv_det[c];
            let inside = yy - a * g - b * sy;
            let only_g = g.max(0.0) * g.max(0.0) * self.inv_gg[c];
            let boundary = yy - only_g.max(only_s);
            let v = if a >= 0.0 && b >= 0.0 && self.inv_det[c] > 0.0 { inside } else { boundary };
            out[c] = v.max(0.0);
        }
    }
}

/// `‖P⊥g_n(c)‖²` for every type, first candidate `c₁` and candidate `c` (see
/// [`RangeTemplates`]): `‖g‖² − [g·g₁, g·s] G⁻¹ [g·g₁, g·s]ᵀ` with `G` the Gram matrix of `g₁`
/// and `s`; infinite where nothing is left.
fn perpendicular(tpl: &Templates) -> Vec<f32> {
    let cands = tpl.candidates();
    let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f64>();
    let mut out = vec![f32::INFINITY; tpl.n * cands * cands];
    for n in 0..tpl.n {
        let s = tpl.s(n);
        let ss = dot(s, s);
        for c1 in 0..cands {
            let g1 = tpl.g(n, c1);
            let (p, q) = (dot(g1, g1), dot(g1, s));
            let det = p * ss - q * q;
            if det <= 1e-12 * p * ss {
                continue;
            }
            for c in 0..cands {
                let g = tpl.g(n, c);
                let (a, b) = (dot(g, g1), dot(g, s));
                let perp = dot(g, g) - (a * a * ss - 2.0 * a * b * q + b * b * p) / det;
                if perp > 1e-6 * dot(g, g) {
                    out[(n * cands + c1) * cands + c] = perp as f32;
                }
            }
        }
    }
    out
}

/// The residual of taps `y` after the best `a·g + b·s`, `a, b ≥ 0`.
fn residual(y: &[f64], g: &[f64], s: &[f64]) -> Vec<f64> {
    let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f64>();
    let (gg, gs, ss, gy, sy) = (dot(g, g), dot(g, s), dot(s, s), dot(g, y), dot(s, y));
    let det = gg * ss - gs * gs;
    let (mut a, mut b) = if det > 1e-12 * gg * ss { ((ss * gy - gs * sy) / det, (gg * sy - gs * gy) / det) } else { (-1.0, -1.0) };
    if a < 0.0 || b < 0.0 {
        // one column alone, the better of the two
        let (ag, bs) = (if gg > 0.0 { (gy / gg).max(0.0) } else { 0.0 }, if ss > 0.0 { (sy / ss).max(0.0) } else { 0.0 });
        (a, b) = if ag * gy >= bs * sy { (ag, 0.0) } else { (0.0, bs) };
    }
    y.iter().zip(g).zip(s).map(|((y, g), s)| y - a * g - b * s).collect()
}

/// Ranges (m) of up to two returns per pixel from one frame of taps, with no estimate to start
/// from (see the module's notes): [`RangeTemplates`] built for this one frame.
///
/// # Shapes
/// - `y`: `[M, H, W]` tap images (H, W multiples of the sensor's block), `sensor`: `A [N, M, T]`
///   → `[returns, H, W]` (m from the start of the code cycle, arrival order, NaN where none)
pub fn fit_ranges(y: &ArrayView3<'_, f32>, sensor: &MeasurementMatrix, opts: &DepthFitOptions) -> Array3<f32> {
    RangeTemplates::new(sensor, opts).fit(y)
}

/// The sides of the wider windows whose log-likelihoods the range fit's evidence gives after
/// the fit's window's, and whose posteriors after the pixel's ([`RangeTemplates::evidence`]).
/// Measured with the fit itself on the Middlebury motorcycle (designed codes, physical IRF,
/// `eval --light`): a 9×9 window instead of 3×3 takes the median first-return error from 4.37
/// to 0.93 bins at 0.005 of the full well and from 0.41 to 0.20 at 0.02, and loses precision
/// at 0.1 and above (0.09 to 0.11 bins): the window should follow the light and the surface.
pub const CONTEXT_WINDOWS: [usize; 3] = [5, 9, 15];

/// Log-likelihood volumes of the range fit's evidence: the fit's window and the
/// [`CONTEXT_WINDOWS`].
pub const SCALES: usize = 1 + CONTEXT_WINDOWS.len();

/// Channels of the range fit's evidence's features for `candidates` pooled by `pool`.
pub fn range_feature_channels(candidates: usize, pool: usize) -> usize {
    crate::evidence::feature_channels_with(candidates, pool, CONTEXT_WINDOWS.len())
}

/// The candidate ranges of the dense pass: `C = T·oversample` round a code cycle of `range_m`,
/// candidate `u` (continuous, cyclic) at `(u + oversample/2)·range_m/C`, so every
/// `oversample`-th sits on a bin's centre.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CandidateGrid {
    pub candidates: usize,
    pub oversample: usize,
    pub range_m: f64,
}

impl CandidateGrid {
    /// The range (m) of candidate coordinate `u`, within the cycle.
    pub fn range(&self, u: f64) -> f64 {
        ((u + 0.5 * self.oversample as f64) / self.candidates as f64 * self.range_m).rem_euclid(self.range_m)
    }

    /// The candidate coordinate of range `r` (m), in `[0, C)`.
    pub fn candidate(&self, r: f64) -> f64 {
        (r * self.candidates as f64 / self.range_m - 0.5 * self.oversample as f64).rem_euclid(self.candidates as f64)
    }
}

/// The dense pass's templates as a linear map of `A`'s columns, for a differentiable copy of
/// the costs (`tcsense_models::range_evidence`): candidate `c` of `bins·oversample` (at
/// `c/oversample + ½` bins) has the template `(1 − f)·A[:, t0] + f·A[:, t1]`, given as
/// `(t0, t1, f)`.
pub fn candidate_columns(bins: usize, oversample: usize) -> Vec<(usize, usize, f64)> {
    (0..bins * oversample).map(|c| crate::range::columns(bins, c as f64 / oversample as f64 + 0.5)).collect()
}

/// One frame's costs at every candidate of the cycle ([`RangeTemplates::costs`]): what the
/// fit and a network on its evidence start from.
#[derive(Debug, Clone, Default)]
pub struct RangeCosts {
    /// The taps `[H·W·M]`, pixel-major.
    taps: Vec<f64>,
    /// Whether a pixel holds enough charge to be fitted `[H·W]`.
    pub lit: Vec<bool>,
    /// Each pixel's single-return cost at every candidate `[H·W·C]` (0 where unlit).
    pub pixel: Vec<f32>,
    /// The costs summed over the window's lit pixels `[H·W·C]`.
    pub window: Vec<f32>,
    /// The box filter's row sums (scratch).
    rows: Vec<f32>,
    /// `H`, `W`, `M`.
    pub height: usize,
    pub width: usize,
    pub m: usize,
    /// The power of two the frame's taps were multiplied by before the costs
    /// ([`RangeTemplates::costs`]: its largest magnitude brought into [1, 2)), so that its
    /// squares neither overflow nor underflow f32 at any scale; the costs are in its square.
    pub scale: f32,
}

/// Where [`RangeTemplates::ranges`] starts each pixel.
#[derive(Debug, Clone, Copy)]
pub enum Seeds<'a> {
    /// The window's best candidate over the whole cycle (the fit).
    Argmin,
    /// A continuous candidate coordinate per pixel `[H·W]` (a posterior's mode; NaN: no
    /// return), `u` at [`CandidateGrid::range`]`(u)`.
    Modes(&'a [f32]),
}

/// The template fit of ranges for one sensor, built once and applied to every frame of a
/// stream (its cost volume reused from frame to frame).
pub struct RangeTemplates {
    /// Candidates with every `os`-th on a bin's centre (the templates' kinks), for the dense pass.
    tpl: Templates,
    /// The range fit's own grid (candidates between the kinks) for the joint fit of two returns,
    /// whose searches end in a parabola.
    jtpl: Templates,
    dense: Vec<Dense>,
    block: (usize, usize),
    /// Metres per bin.
    delta: f64,
    opts: DepthFitOptions,
    /// `‖P⊥g_n(c)‖²`, `[N][C₁][C]`: a second return at `c` beside a first at `c₁`, the part of
    /// its template outside the first's and the ambient's columns (infinite where nothing is
    /// left).
    perp: Vec<f32>,
    /// Every pixel's residual's product with every candidate's template, `[H·W][C]` (scratch,
    /// reused from frame to frame).
    scratch: Vec<f32>,
    /// The last frame's costs (buffers reused by [`Self::fit`]).
    frame: Option<RangeCosts>,
    /// Every pixel's residual after its single return, `[H·W]` (scratch).
    rr: Vec<f32>,
}

impl RangeTemplates {
    /// The templates of `sensor` with `opts` (checked by the caller: [`DepthFitOptions::validate`]).
    pub fn new(sensor: &MeasurementMatrix, opts: &DepthFitOptions) -> RangeTemplates {
        let os = opts.fit.oversample;
        let tpl = Templates::with_offset(sensor, os, 0.5 * os as f64);
        let dense = Dense::of(&tpl);
        let perp = perpendicular(&tpl);
        RangeTemplates {
            jtpl: Templates::new(sensor, os),
            dense,
            tpl,
            perp,
            block: sensor.block(),
            delta: C * sensor.bin_width_s() / 2.0,
            opts: opts.clone(),
            scratch: Vec::new(),
            frame: None,
            rr: Vec::new(),
        }
    }

    /// The ranges of one frame.
    ///
    /// # Shapes
    /// - `y`: `[M, H, W]` → `[returns, H, W]` (m, arrival order, NaN where none)
    pub fn fit(&mut self, y: &ArrayView3<'_, f32>) -> Array3<f32> {
        let (_, h, w) = y.dim();
        // (the cost volume's buffers kept from frame to frame)
        let mut costs = self.frame.take().unwrap_or_default();
        let out = if self.costs_into(y, &mut costs) {
            if self.opts.pool_like > self.opts.fit.window {
                let u = self.pooled_modes(&costs, self.opts.pool_like);
                self.ranges(&costs, Seeds::Modes(&u))
            } else {
                self.ranges(&costs, Seeds::Argmin)
            }
        } else {
            Array3::from_elem((self.opts.returns, h, w), f32::NAN)
        };
        self.frame = Some(costs);
        out
    }

    /// Every lit pixel's first return from its window's costs pooled by likeness over a
    /// neighbourhood of `side` ([`crate::evidence::similarity_pool`], in the frame's nats): the
    /// pooled cost's best candidate, refined by a parabola through its neighbours (cyclic), as
    /// the continuous candidate coordinate [`Seeds::Modes`] takes (NaN where unlit). In bright
    /// light a window's posterior is sharp, no neighbour of another range weighs in, and the
    /// best candidate is the window's own (which [`Self::ranges`] refines in the tap domain);
    /// in dim light the windows of one surface pool as one wider window.
    ///
    /// # Shapes
    /// - `costs`: of `[H·W·C]` → `[H·W]`
    pub fn pooled_modes(&self, costs: &RangeCosts, side: usize) -> Vec<f32> {
        let c = self.tpl.candidates();
        let (pooled, _) = self.pooled_costs(costs, side);
        pooled
            .par_chunks(c)
            .zip(costs.lit.par_iter())
            .map(|(v, &lit)| {
                if !lit {
                    return f32::NAN;
                }
                let b = argmin(v);
                let at = |k: usize| v[k % c] as f64;
                (b as f64 + crate::engine::parabola_min(at(b + c - 1), at(b), at(b + 1))) as f32
            })
            .collect()
    }

    /// Every pixel's window cost pooled by likeness with the neighbouring windows that tile
    /// `side` ([`crate::evidence::similarity_pool`], in the frame's nats), and the frame's noise
    /// level (its window's, [`crate::evidence::noise_level`]).
    ///
    /// # Shapes
    /// - `costs`: of `[H·W·C]` → `[H·W·C]`
    fn pooled_costs(&self, costs: &RangeCosts, side: usize) -> (Vec<f32>, f32) {
        let volume = self.volume(costs);
        let noise = crate::evidence::noise_level(&volume);
        (crate::evidence::similarity_pool(&volume, 1.0 / (2.0 * noise), side), noise)
    }

    /// A frame's costs as the fit's [`CostVolume`]: each pixel's amplitude and ambient are its
    /// own (`M − 2` numbers a pixel about the range), the window shares the range.
    fn volume<'a>(&self, costs: &'a RangeCosts) -> CostVolume<'a> {
        CostVolume {
            pixel: &costs.pixel,
            window: &costs.window,
            lit: &costs.lit,
            points: self.tpl.candidates(),
            height: costs.height,
            width: costs.width,
            side: self.opts.fit.window,
            free_per_pixel: costs.m.saturating_sub(2),
            shared: 1,
        }
    }

    /// Candidates `C` around the cycle (`T` bins × the candidates per bin).
    pub fn candidates(&self) -> usize {
        self.tpl.candidates()
    }

    /// Step 1 of the fit for one frame: every lit pixel's cost at every candidate and its sum
    /// over the window; `None` where `y` has another number of taps than the sensor or no
    /// pixel.
    ///
    /// # Shapes
    /// - `y`: `[M, H, W]` → [`RangeCosts`] of `[H·W·C]`
    pub fn costs(&self, y: &ArrayView3<'_, f32>) -> Option<RangeCosts> {
        let mut costs = RangeCosts::default();
        self.costs_into(y, &mut costs).then_some(costs)
    }

    /// [`Self::costs`] into the buffers of `costs` (a stream's, reused); `false` where there is
    /// nothing to fit.
    pub fn costs_into(&self, y: &ArrayView3<'_, f32>, costs: &mut RangeCosts) -> bool {
        let (m, h, w) = y.dim();
        let (tpl, dense) = (&self.tpl, &self.dense);
        let cands = tpl.candidates();
        let (bh, bw) = self.block;
        let kind = |p: usize| subpixel_flat(p, w, (bh, bw));
        if m != tpl.m || h == 0 || w == 0 {
            return false;
        }
        // taps [H·W][M] (f32 for the dense pass, f64 for the window fits) and who has light,
        // times a power of two (exact: the ranges are the frame's as given, at any scale)
        let scale = unit_scale(y.iter().fold(0f32, |a, &v| a.max(v.abs())));
        let mut y32 = vec![0f32; h * w * m];
        for ((k, i, j), &v) in y.indexed_iter() {
            y32[(i * w + j) * m + k] = v * scale;
        }
        let charge: Vec<f32> = (0..h * w).map(|p| y32[p * m..(p + 1) * m].iter().sum()).collect();
        let floor = self.opts.min_intensity * charge.iter().fold(0f32, |a, &b| a.max(b));
        let lit: Vec<bool> = charge.iter().map(|&c| c > 0.0 && c > floor).collect();
        // every lit pixel's cost at every candidate, [H·W][C] (the others are never read)
        let RangeCosts { taps, lit: lit_out, pixel, window, rows, .. } = costs;
        pixel.clear();
        pixel.resize(h * w * cands, 0.0);
        pixel.par_chunks_mut(w * cands).enumerate().for_each(|(i, row)| {
            let mut gy = vec![0f32; cands];
            for j in 0..w {
                let p = i * w + j;
                if lit[p] {
                    dense[kind(p)].costs(&y32[p * m..(p + 1) * m], &mut gy, &mut row[j * cands..(j + 1) * cands]);
                }
            }
        });
        // summed over the window's lit pixels
        let side = self.opts.fit.window;
        window_sums(pixel, &lit, (h, w), cands, side, rows, window);
        taps.clear();
        taps.extend(y32.iter().map(|&v| v as f64));
        *lit_out = lit;
        (costs.height, costs.width, costs.m, costs.scale) = (h, w, m, scale);
        true
    }

    /// The fit's evidence of one frame ([`crate::evidence`]): each pixel's amplitude and
    /// ambient are its own, the window shares the range. After the fit's window's
    /// log-likelihood and each pixel's posterior over the candidates, those of its
    /// [`CONTEXT_WINDOWS`] (the costs summed over wider windows). Pooled by likeness
    /// ([`DepthFitOptions::pool_like`]), the window's log-likelihood is its cost pooled with
    /// its neighbours' ([`RangeTemplates::pooled_modes`]'), in the window's nats.
    ///
    /// # Shapes
    /// - `costs`: of `[H·W·C]`, `intensity`: `[H, W]` → [`Evidence`] of skip `[H, W, SCALES·C]`,
    ///   [`range_feature_channels`] features
    pub fn evidence(&self, costs: &RangeCosts, intensity: &Array2<f32>, pool: usize) -> Evidence {
        self.evidence_into(costs, intensity, pool, crate::evidence::EvidenceBuffers::default())
    }

    /// [`Self::evidence`] written into an earlier frame's `buffers` (a stream's): the same
    /// numbers.
    pub fn evidence_into(
        &self,
        costs: &RangeCosts,
        intensity: &Array2<f32>,
        pool: usize,
        buffers: crate::evidence::EvidenceBuffers,
    ) -> Evidence {
        let (h, w, cands) = (costs.height, costs.width, self.tpl.candidates());
        let mut rows = Vec::new();
        let wider: Vec<Vec<f32>> = CONTEXT_WINDOWS
            .iter()
            .map(|&side| {
                let mut sums = Vec::new();
                window_sums(&costs.pixel, &costs.lit, (h, w), cands, side, &mut rows, &mut sums);
                sums
            })
            .collect();
        let wider: Vec<&[f32]> = wider.iter().map(|v| v.as_slice()).collect();
        let mut evidence = if self.opts.pool_like > self.opts.fit.window {
            // the window's log-likelihood pooled by likeness, in the window's nats
            let (pooled, noise) = self.pooled_costs(costs, self.opts.pool_like);
            let volume = CostVolume { window: &pooled, ..self.volume(costs) };
            crate::evidence::evidence_at_noise(&volume, noise, intensity, pool, &wider, buffers)
        } else {
            crate::evidence::evidence_into(&self.volume(costs), intensity, pool, &wider, buffers)
        };
        // the noise level in the units of the taps as given (the costs are in the scale's square)
        evidence.noise = evidence.noise / costs.scale / costs.scale;
        evidence
    }

    /// Steps 2 to 4 of the fit from a frame's costs: the first estimate of every pixel (the
    /// window's argmin over the cycle, or `seeds`' modes), the window on its surface searched
    /// near it and refined, a second return.
    ///
    /// With [`Seeds::Modes`] a pixel's range is its mode refined in the tap domain where the
    /// window's best candidate within the search is the mode's own or its neighbour (as the fit
    /// refines its argmin); elsewhere the mode itself. A pixel without a mode has no return.
    ///
    /// # Shapes
    /// - `costs`: of `[H·W·C]` → `[returns, H, W]` (m, arrival order, NaN where none)
    pub fn ranges(&mut self, costs: &RangeCosts, seeds: Seeds<'_>) -> Array3<f32> {
        let (m, h, w) = (costs.m, costs.height, costs.width);
        let opts = &self.opts;
        let fit = &opts.fit;
        let (tpl, jtpl, dense) = (&self.tpl, &self.jtpl, &self.dense);
        let cands = tpl.candidates();
        let (bh, bw) = self.block;
        let kind = |p: usize| subpixel_flat(p, w, (bh, bw));
        let delta = self.delta;
        let os = fit.oversample as f64;
        let half = fit.window / 2;
        let mut out = Array3::from_elem((opts.returns, h, w), f32::NAN);
        let (taps, lit, cost) = (&costs.taps, &costs.lit, &costs.pixel);
        // 2. the first estimate: the window's argmin over the cycle, or the seeds' modes
        let first: Vec<f64> = match seeds {
            Seeds::Argmin => (0..h * w)
                .into_par_iter()
                .map(|p| if lit[p] { tpl.tau(argmin(&costs.window[p * cands..(p + 1) * cands])) } else { f64::NAN })
                .collect(),
            Seeds::Modes(u) => {
                assert_eq!(u.len(), h * w, "RangeTemplates::ranges: a mode per pixel");
                u.iter()
                    .zip(lit.iter())
                    .map(|(&u, &l)| if l && u.is_finite() { (tpl.tau(0) + u as f64 / os).rem_euclid(tpl.t as f64) } else { f64::NAN })
                    .collect()
            }
        };
        let moded = matches!(seeds, Seeds::Modes(_));
        // a mode's window may grow: the frame's nats per unit of cost (the noise level of the
        // window's evidence, as the evidence reads it)
        let grows = moded && opts.mode_window > fit.window;
        let nats = if grows { 1.0 / (2.0 * crate::evidence::noise_level(&self.volume(costs)) as f64) } else { 0.0 };

        // 3. the window on the pixel's surface: search near the first estimate, refine
        let t = tpl.t;
        // a neighbour `q` on the surface of a pixel at range `own` (lit, within edge_bins)
        let on_surface = |q: usize, own: f64, first: &[f64]| lit[q] && cyclic_gap(first[q], own, t) <= fit.edge_bins;
        let hood_of = |i: usize, j: usize, side: usize, first: &[f64], hood: &mut Vec<usize>| {
            let (p, own) = (i * w + j, first[i * w + j]);
            hood.clear();
            for ii in i.saturating_sub(side)..(i + side + 1).min(h) {
                for jj in j.saturating_sub(side)..(j + side + 1).min(w) {
                    let q = ii * w + jj;
                    if q == p || on_surface(q, own, first) {
                        hood.push(q);
                    }
                }
            }
        };
        let (tau1, sides): (Vec<f64>, Vec<usize>) = (0..h)
            .into_par_iter()
            .flat_map_iter(|i| {
                let mut win = WindowFit::new(jtpl, taps, fit.window);
                let mut total = vec![0f32; cands];
                let mut g = vec![0.0f64; m];
                let mut hood: Vec<usize> = Vec::with_capacity(fit.window * fit.window);
                let first = &first;
                (0..w)
                    .map(move |j| {
                        let p = i * w + j;
                        let own = first[p];
                        if !lit[p] || !own.is_finite() {
                            return (f64::NAN, half);
                        }
                        // the best candidate within ±search_bins of the first estimate (cyclic)
                        let centre = tpl.nearest(own) as i64;
                        let reach = (fit.search_bins * os).floor() as i64;
                        let at = |d: i64| wrap_index(centre + d, cands as i64);
                        // a mode's window grows on its surface until its best candidate is the
                        // mode's own (or its neighbour) and known to MODE_PRECISION_BINS (dim
                        // light), up to mode_window
                        let mut grown = half;
                        // only the candidates the search and its refinement read: ±(reach + 1)
                        // around the centre, as at most two runs of the cyclic axis
                        let span = (2 * reach as usize + 3).min(cands);
                        let start = wrap_index(centre - reach - 1, cands as i64);
                        let runs = [(start, (start + span).min(cands)), (0, (start + span).saturating_sub(cands))];
                        hood_of(i, j, half, first, &mut hood);
                        total.fill(0.0);
                        let add = |total: &mut [f32], q: usize| {
                            for &(a, b) in &runs {
                                total[a..b].iter_mut().zip(&cost[q * cands + a..q * cands + b]).for_each(|(s, c)| *s += c);
                            }
                        };
                        for &q in &hood {
                            add(&mut total, q);
                        }
                        let d = loop {
                            let d = (-reach..=reach)
                                .min_by(|&a, &b| total[at(a)].total_cmp(&total[at(b)]).then(a.abs().cmp(&b.abs())))
                                .unwrap_or(0);
                            if !grows || grown >= opts.mode_window / 2 {
                                break d;
                            }
                            // the cost's curvature at the best candidate, in nats per bin²
                            let c = |k: i64| total[at(d + k)] as f64;
                            let curvature = (c(-1) - 2.0 * c(0) + c(1)) * os * os * nats;
                            if d.abs() <= 1 && curvature > 0.0 && curvature.sqrt().recip() <= MODE_PRECISION_BINS {
                                break d;
                            }
                            // the ring the window gains, on the pixel's surface
                            grown += 1;
                            for ii in i.saturating_sub(grown)..(i + grown + 1).min(h) {
                                for jj in j.saturating_sub(grown)..(j + grown + 1).min(w) {
                                    let q = ii * w + jj;
                                    if ii.abs_diff(i).max(jj.abs_diff(j)) == grown && on_surface(q, own, first) {
                                        hood.push(q);
                                        add(&mut total, q);
                                    }
                                }
                            }
                        };
                        if moded && d.abs() > 1 {
                            return (own, grown); // the mode is not the window's best: the prior's choice stands
                        }
                        if d.abs() == reach && reach > 0 {
                            return (f64::NAN, grown); // on the bound of the search
                        }
                        let best = at(d);
                        win.set_window(hood.iter().map(|&q| (kind(q), q * m)));
                        let offset = refine(&total, best, fit.oversample, &mut |x| win.single_at(tpl.tau(best) + x / os, &mut g));
                        (wrap(tpl.tau(best) + offset / os, t as f64), grown)
                    })
                    .collect::<Vec<_>>()
            })
            .unzip();
        let mut cells: Vec<(f64, f64)> = tau1.iter().map(|&t| (t, f64::NAN)).collect();
        if opts.returns > 1 {
            // 4. a second return. Each pixel's residual `r` after its single return (amplitude
            // and ambient refitted), matched against every candidate: `r·g(c)`, and `‖P⊥g(c)‖²`
            // with `P⊥` the projection out of the first return's and the ambient's columns (the
            // table `perp`); with one amplitude over the window, a second return at `c` removes
            // `(Σ r·g(c))² / Σ ‖P⊥g(c)‖²` of the residual. Its highest local maxima two bins or
            // more from the first are the seeds of the joint fit.
            self.rr.resize(h * w, 0.0);
            self.scratch.resize(h * w * cands, 0.0);
            self.scratch.par_chunks_mut(w * cands).zip(self.rr.par_chunks_mut(w)).enumerate().for_each(|(i, (row, rrow))| {
                let mut g1 = vec![0.0f64; m];
                for j in 0..w {
                    let p = i * w + j;
                    if !tau1[p].is_finite() {
                        continue;
                    }
                    let n = kind(p);
                    jtpl.at(n, tau1[p], &mut g1);
                    let r = residual(&taps[p * m..(p + 1) * m], &g1, jtpl.s(n));
                    let r32: Vec<f32> = r.iter().map(|&v| v as f32).collect();
                    dense[n].products(&r32, &mut row[j * cands..(j + 1) * cands]);
                    rrow[j] = r.iter().map(|v| v * v).sum::<f64>() as f32;
                }
            });
            let (zvol, perp, rr) = (&self.scratch, &self.perp, &self.rr);
            let seconds: Vec<Option<(usize, f64, f64)>> = (0..h)
                .into_par_iter()
                .flat_map_iter(|i| {
                    let mut win = WindowFit::new(jtpl, taps, fit.window);
                    let mut total = vec![0f32; cands];
                    let mut zsum = vec![0f32; cands];
                    let mut psum = vec![0f32; cands];
                    let mut g = vec![0.0f64; m];
                    // (the window a first return was refined on: up to mode_window a side)
                    let side = fit.window.max(opts.mode_window);
                    let mut hood: Vec<usize> = Vec::with_capacity(side * side);
                    let (first, tau1, sides) = (&first, &tau1, &sides);
                    (0..w)
                        .map(move |j| {
                            let p = i * w + j;
                            let tau = tau1[p];
                            if !tau.is_finite() {
                                return None;
                            }
                            // the window the first return was refined on (grown in dim light, on the
                            // pixel's surface); where it grew, a second return is also kept where it
                            // is significant in the frame's nats, not only where it removes a share
                            let side = sides[p];
                            let grew = side > half;
                            hood_of(i, j, side, first, &mut hood);
                            hood.retain(|&q| tau1[q].is_finite());
                            // one amplitude of the second return over the window: the matched
                            // products add coherently, the noise does not
                            zsum.fill(0.0);
                            psum.fill(0.0);
                            let mut left = 0.0f64;
                            for &q in &hood {
                                let row = (kind(q) * cands + tpl.nearest(tau1[q])) * cands;
                                zsum.iter_mut().zip(&zvol[q * cands..(q + 1) * cands]).for_each(|(a, b)| *a += b);
                                psum.iter_mut().zip(&perp[row..row + cands]).for_each(|(a, b)| *a += b);
                                left += rr[q] as f64;
                            }
                            for c in 0..cands {
                                total[c] = zsum[c] * zsum[c] / psum[c];
                            }
                            let best =
                                (0..cands).filter(|&c| cyclic_gap(tpl.tau(c), tau, t) >= MIN_GAP).map(|c| total[c]).fold(0f32, f32::max);
                            let significant = |gain: f64| grew && gain * nats >= SECOND_EVIDENCE_NATS;
                            if (best as f64) < PRESCREEN * left && !significant(best as f64) {
                                return None;
                            }
                            win.set_window(hood.iter().map(|&q| (kind(q), q * m)));
                            let single = win.single_at(tau, &mut g);
                            if single <= EXPLAINED * win.energy() {
                                return None;
                            }
                            // seeds: the matched residual's highest local maxima, screened by one
                            // joint evaluation each with the first held where it is
                            let mut seeds = [(f32::NEG_INFINITY, 0usize); SEEDS];
                            for c in 0..cands {
                                let v = total[c];
                                // (the cyclic neighbours, without a division per candidate)
                                let (before, after) = (if c == 0 { cands - 1 } else { c - 1 }, if c + 1 == cands { 0 } else { c + 1 });
                                if v >= total[before]
                                    && v >= total[after]
                                    && v > seeds[SEEDS - 1].0
                                    && cyclic_gap(tpl.tau(c), tau, t) >= MIN_GAP
                                {
                                    seeds[SEEDS - 1] = (v, c);
                                    seeds.sort_by(|a, b| b.0.total_cmp(&a.0));
                                }
                            }
                            win.fix_other(tau);
                            // (each seed at its candidate on the joint fit's grid)
                            let (screened, c2) = seeds
                                .iter()
                                .filter(|s| s.0.is_finite())
                                .map(|s| (win.joint(jtpl.nearest(tpl.tau(s.1))), s.1))
                                .min_by(|a, b| a.0.total_cmp(&b.0))?;
                            if screened > SCREEN * single && !significant(single - screened) {
                                return None;
                            }
                            // (a round that leaves twice the residual kept is given up; on a grown
                            // window, one that leaves the single return's)
                            let give_up = if grew { single } else { 2.0 * opts.second_residual * single };
                            let ((t1, t2), joint) = win.two_returns_until((tau, tpl.tau(c2)), 1.0, give_up);
                            let (a1, a2) = win.amplitudes(t1, t2);
                            let keep = cyclic_gap(t1, t2, t) >= MIN_GAP
                                && (joint <= opts.second_residual * single || significant(single - joint))
                                && a1.min(a2) >= opts.second_amplitude * a1.max(a2);
                            keep.then_some((p, t1.min(t2), t1.max(t2))) // arrival order
                        })
                        .collect::<Vec<_>>()
                })
                .collect();
            for (p, t1, t2) in seconds.into_iter().flatten() {
                cells[p] = (t1, t2);
            }
        }
        let k = out.dim().0;
        for (p, c) in cells.iter().enumerate() {
            out[(0, p / w, p % w)] = (c.0 * delta) as f32;
            if k > 1 {
                out[(1, p / w, p % w)] = (c.1 * delta) as f32;
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::range::refine_ranges;
    use ndarray::{Array3, Array4, Axis};
    use tcsense_sensor::params::{DEFAULT_LASER_FWHM_S, DEFAULT_TAP_TAU_S};
    use tcsense_sensor::{Codes, Irf, SensorParams};

    /// The zoo's codes designed for range on the prototype's shape (4 taps, 2×2, L = 32, alias
    /// 0.77), physical IRF: a sensor whose codes do not alias.
    fn sensor() -> MeasurementMatrix {
        let codes = Codes::from_json(include_str!("../../zoo/unet-lidar-designed/codes.json")).unwrap();
        let params = SensorParams {
            irf: Irf::Physical { laser_fwhm_s: DEFAULT_LASER_FWHM_S, tap_tau_s: DEFAULT_TAP_TAU_S },
            ..SensorParams::from_codes(&codes)
        };
        MeasurementMatrix::synthesize(&codes, &params.validate().unwrap()).unwrap()
    }

    /// Taps `[M, H, W]` of returns `(τ bins, amplitude)` per pixel on an ambient level `b`.
    fn taps(a: &MeasurementMatrix, h: usize, w: usize, returns: &dyn Fn(usize, usize) -> Vec<(f64, f64)>, b: f64) -> ndarray::Array3<f32> {
        let (av, (bh, bw)) = (a.a(), a.block());
        let (_, m, t) = av.dim();
        let mut y = ndarray::Array3::zeros((m, h, w));
        for i in 0..h {
            for j in 0..w {
                let mut x = vec![b; t];
                for (tau, amp) in returns(i, j) {
                    let p = tau - 0.5;
                    let t0 = p.floor() as usize;
                    x[t0 % t] += amp * (1.0 - (p - p.floor()));
                    x[(t0 + 1) % t] += amp * (p - p.floor());
                }
                let n = tcsense_sensor::waveform::subpixel(i, j, (bh, bw));
                for mm in 0..m {
                    y[(mm, i, j)] = (0..t).map(|k| av[(n, mm, k)] as f64 * x[k]).sum::<f64>() as f32;
                }
            }
        }
        y
    }

    /// The taps at any scale give the same ranges, to the bit where the scale is a power of two
    /// (the costs are computed on the frame brought into [1, 2)), and the same evidence, whose
    /// noise level is in the units of the taps as given: without the scaling, taps of 2^70
    /// overflow f32 in their squares and taps of 2^-75 underflow.
    #[test]
    fn the_taps_at_any_scale_give_the_same_ranges_and_evidence() {
        let a = sensor();
        let clean = taps(&a, 12, 12, &|i, j| vec![(4.0 + 0.7 * j as f64, 0.8), (20.0 + 0.3 * i as f64, 0.3)], 0.01);
        let y = crate::testing::noise(&clean, 300.0, 3, false);
        let opts = DepthFitOptions::default().pooled(9);
        let mut templates = RangeTemplates::new(&a, &opts);
        let want = templates.fit(&y.view());
        assert!(want.iter().filter(|v| v.is_finite()).count() > 144, "returns found");
        let costs = templates.costs(&y.view()).unwrap();
        let base = templates.evidence(&costs, &y.sum_axis(Axis(0)), 4);
        for k in [70, 30, -30, -75] {
            let s = 2f32.powi(k);
            let ys = y.mapv(|v| v * s);
            let got = templates.fit(&ys.view());
            assert!(got.iter().zip(want.iter()).all(|(p, q)| p.to_bits() == q.to_bits()), "ranges of the taps times 2^{k}");
            let costs = templates.costs(&ys.view()).unwrap();
            let ev = templates.evidence(&costs, &ys.sum_axis(Axis(0)), 4);
            assert_eq!(ev.skip, base.skip, "log-likelihoods of the taps times 2^{k}");
            assert_eq!(ev.features, base.features, "posteriors of the taps times 2^{k}");
            let noise = base.noise as f64 * (s as f64).powi(2);
            if noise < f32::MAX as f64 && noise > f32::MIN_POSITIVE as f64 {
                assert_eq!(ev.noise as f64, noise, "the noise level times 2^{}", 2 * k);
            }
        }
    }

    /// With no estimate to start from, every return of the cycle is found (a global search) and
    /// placed where the range fit started a bin away places it: within 0.02 bins of each other.
    #[test]
    fn every_range_of_the_cycle_is_found_and_equals_the_range_fit() {
        let a = sensor();
        let dz = C * a.bin_width_s() / 2.0;
        for tau in [1.3, 7.62, 15.03, 22.5, 30.9] {
            let y = taps(&a, 8, 8, &|_, _| vec![(tau, 0.8)], 0.01);
            let got = fit_ranges(&y.view(), &a, &DepthFitOptions { returns: 1, ..Default::default() });
            let mut depth = Array4::from_elem((1, 2, 8, 8), f32::NAN);
            depth.index_axis_mut(Axis(1), 0).fill(((tau + 0.9) * dz) as f32);
            refine_ranges(y.view().insert_axis(Axis(0)), &a, &mut depth, &RangeFitOptions::default());
            for ((i, j), &v) in got.index_axis(Axis(0), 0).indexed_iter() {
                let (v, r) = (v as f64 / dz, depth[(0, 0, i, j)] as f64 / dz);
                assert!((v - tau).abs() < 0.05, "τ = {tau}: {v} at ({i}, {j})");
                assert!((v - r).abs() < 0.02, "τ = {tau}: the dense fit {v}, the range fit {r}");
            }
        }
    }

    /// Two surfaces, each half the frame: in dim light the windows pooled by likeness place
    /// the first return better than the 3×3 fit, and better refined on a window grown on the
    /// surface than on the 3×3 window alone; in bright light they are the fit, and the edge
    /// between the surfaces stays sharp.
    #[test]
    fn pooling_by_likeness_pools_dim_surfaces_and_keeps_bright_edges() {
        let a = sensor();
        let dz = C * a.bin_width_s() / 2.0;
        let (h, w) = (24, 36);
        let tau = |_: usize, j: usize| if j < w / 2 { 9.3 } else { 21.7 };
        let clean = taps(&a, h, w, &|i, j| vec![(tau(i, j), 1.0)], 0.02);
        // (mode_window 3: the pooled mode refined on the fit's 3×3 window alone, as before the
        // window grew)
        let errors_in = |pool_like: usize, mode_window: usize, y: &ndarray::Array3<f32>, cols: &dyn Fn(usize) -> bool| {
            let opts = DepthFitOptions { returns: 1, ..Default::default() }.pooled(pool_like);
            let opts = DepthFitOptions { mode_window: mode_window.min(opts.mode_window), ..opts };
            assert!(opts.validate().is_ok());
            let got = fit_ranges(&y.view(), &a, &opts);
            let mut e: Vec<f64> = got
                .index_axis(Axis(0), 0)
                .indexed_iter()
                .filter(|((_, j), _)| cols(*j))
                .map(|((i, j), &v)| if v.is_finite() { (v as f64 / dz - tau(i, j)).abs() } else { f64::INFINITY })
                .collect();
            e.sort_by(f64::total_cmp);
            e
        };
        let errors = |pool_like: usize, y: &ndarray::Array3<f32>, cols: &dyn Fn(usize) -> bool| errors_in(pool_like, usize::MAX, y, cols);
        let away = |j: usize| j.abs_diff(w / 2) > 3 && j.abs_diff(w / 2 - 1) > 3;
        // (three noise draws a level: the medians of 1 800 pixels)
        let median = |mut e: Vec<f64>| {
            e.sort_by(f64::total_cmp);
            e[e.len() / 2]
        };
        for photons in [1.0, 2.0] {
            let (mut fit, mut pooled, mut fixed) = (Vec::new(), Vec::new(), Vec::new());
            for seed in 3..6 {
                let dim = crate::testing::noise(&clean, photons, seed, false);
                fit.extend(errors(0, &dim, &away));
                pooled.extend(errors(15, &dim, &away));
                fixed.extend(errors_in(15, 3, &dim, &away));
            }
            let (p, q, r) = (median(fit), median(pooled), median(fixed));
            assert!(q < 0.8 * p, "{photons} photons a pixel: the pooled median error {q} bins against the 3×3 fit's {p}");
            // the mode refined on a window grown on its surface, not pulled back to the 3×3
            // window's noise
            assert!(q < 0.9 * r, "{photons} photons a pixel: the pooled median error {q} bins, refined on the 3×3 window alone {r}");
        }
        let bright = crate::testing::noise(&clean, 1e5, 5, false);
        let (fit, pooled) = (errors(0, &bright, &|_| true), errors(15, &bright, &|_| true));
        let (p, q) = (fit[fit.len() / 2], pooled[pooled.len() / 2]);
        assert!(q <= 1.1 * p + 0.005, "bright: the pooled median error {q} bins against the 3×3 fit's {p}");
        let edge = errors(15, &bright, &|j| !away(j));
        assert!(edge.last().is_some_and(|&e| e < 0.25), "bright: the columns beside the edge {edge:?}");
        for bad in [3, 4, 11, 18, 1001] {
            assert!(DepthFitOptions { pool_like: bad, ..Default::default() }.validate().is_err(), "{bad}");
        }
    }

    /// Seeded by a posterior's modes (here 0.3 bins off the true range), the window that refines
    /// them grows in dim light, so a plane's median error falls well below the 3×3 window's
    /// (measured 0.40–0.74× at 10 and 20 photons a pixel), and stays the fit's window in bright
    /// light: the same ranges as the 3×3 window, to the bit.
    #[test]
    fn a_modes_window_grows_in_dim_light_and_stays_in_bright_light() {
        let a = sensor();
        let dz = C * a.bin_width_s() / 2.0;
        let (h, w, tau) = (24, 24, 12.05);
        let clean = taps(&a, h, w, &|_, _| vec![(tau, 1.0)], 0.02);
        let ranges = |y: &ndarray::Array3<f32>, mode_window: usize| {
            let opts = DepthFitOptions { mode_window, ..DepthFitOptions::for_evidence(4, 1) };
            assert!(opts.validate().is_ok());
            let mut templates = RangeTemplates::new(&a, &opts);
            let costs = templates.costs(&y.view()).expect("a frame");
            // a mode 0.3 bins off, between the templates' kinks (on a bin's centre a range snaps
            // to the kink), as a network's mode may be
            let u = vec![((tau + 0.3 - 0.5) * 4.0) as f32; h * w];
            templates.ranges(&costs, Seeds::Modes(&u))
        };
        let median = |r: &Array3<f32>| {
            let mut e: Vec<f64> =
                r.index_axis(Axis(0), 0).iter().map(|&v| if v.is_finite() { (v as f64 / dz - tau).abs() } else { f64::INFINITY }).collect();
            e.sort_by(f64::total_cmp);
            e[e.len() / 2]
        };
        for (photons, seed) in [(10.0, 3), (10.0, 4), (10.0, 5), (20.0, 3), (20.0, 4), (20.0, 5)] {
            let dim = crate::testing::noise(&clean, photons, seed, false);
            let (fixed, grown) = (median(&ranges(&dim, 3)), median(&ranges(&dim, 7)));
            assert!(
                grown < 0.8 * fixed,
                "{photons} photons, seed {seed}: the grown window's median error {grown} bins against the 3×3 window's {fixed}"
            );
        }
        let bright = crate::testing::noise(&clean, 1e5, 5, false);
        let (fixed, grown) = (ranges(&bright, 3), ranges(&bright, 7));
        assert!(fixed.iter().zip(grown.iter()).all(|(a, b)| a.to_bits() == b.to_bits()), "bright: the window stays the fit's");
        assert!(median(&fixed) < 0.05, "bright: {}", median(&fixed));
        for bad in [0, 2, 4, 65] {
            assert!(DepthFitOptions { mode_window: bad, ..Default::default() }.validate().is_err(), "{bad}");
        }
        // a fit given a wider window keeps the default mode window (never grown), as `--window 5`
        for window in [1, 5, 9] {
            let opts = DepthFitOptions { fit: RangeFitOptions { window, ..Default::default() }, ..Default::default() };
            assert!(opts.validate().is_ok(), "window {window}");
        }
    }

    /// In dim light a sheet's second return is found on the grown window, where the share rules of
    /// the 3×3 window miss it, and the grown window adds few second returns where there is none.
    #[test]
    fn a_dim_sheets_second_return_is_found_on_the_grown_window() {
        let a = sensor();
        let dz = C * a.bin_width_s() / 2.0;
        let (h, w, sheet, wall) = (24, 24, 6.3, 19.6);
        let clean = taps(&a, h, w, &|_, j| if j < w / 2 { vec![(sheet, 0.5), (wall, 1.0)] } else { vec![(wall, 1.0)] }, 0.02);
        // (found, false): the share of the left half's pixels whose second return is the sheet's
        // or the wall's within a bin, and of the right half's with a second return at all
        let shares = |y: &ndarray::Array3<f32>, mode_window: usize| {
            let opts = DepthFitOptions { mode_window, ..DepthFitOptions::for_evidence(4, 2) };
            let mut templates = RangeTemplates::new(&a, &opts);
            let costs = templates.costs(&y.view()).expect("a frame");
            // the network's mode on the wall, the stronger return, between the kinks
            let u = vec![((wall + 0.1 - 0.5) * 4.0) as f32; h * w];
            let r = templates.ranges(&costs, Seeds::Modes(&u));
            let (mut found, mut false_) = (0usize, 0usize);
            for i in 0..h {
                for j in 0..w {
                    let (r0, r1) = (r[(0, i, j)] as f64 / dz, r[(1, i, j)] as f64 / dz);
                    if j < w / 2 {
                        found += usize::from(r1.is_finite() && (r0 - sheet).abs() < 1.0 && (r1 - wall).abs() < 1.0);
                    } else {
                        false_ += usize::from(r1.is_finite());
                    }
                }
            }
            let half = (h * w / 2) as f64;
            (found as f64 / half, false_ as f64 / half)
        };
        // measured: found 0.23–0.50 on the 3×3 window, 0.80–0.97 grown; false 0.05–0.10, 0.03–0.08
        for photons in [4.0, 8.0] {
            for seed in 3..6 {
                let y = crate::testing::noise(&clean, photons, seed, false);
                let ((found3, false3), (found7, false7)) = (shares(&y, 3), shares(&y, 7));
                assert!(
                    found7 >= 0.75 && found7 >= found3 + 0.3,
                    "{photons} photons, seed {seed}: the sheet found on {found7} grown, {found3} on 3×3"
                );
                assert!(false7 <= 0.1 && false7 <= false3 + 0.02, "{photons} photons, seed {seed}: false {false7} grown, {false3} on 3×3");
            }
        }
    }

    /// Pooled by likeness, the evidence's window log-likelihood is the pooled cost's (0 at its
    /// best candidate, which is `pooled_modes`' seed, in the window's nats); the pixel's
    /// posteriors, the wider windows and the noise level are the window's own evidence's.
    #[test]
    fn pooled_evidence_is_the_pooled_cost_in_the_window_nats() {
        let a = sensor();
        let (h, w) = (16, 20);
        let clean = taps(&a, h, w, &|_, j| vec![(if j < 10 { 7.2 } else { 18.6 }, 1.0)], 0.02);
        let y = crate::testing::noise(&clean, 3.0, 7, false);
        let intensity = y.sum_axis(Axis(0));
        let opts = |pool_like| DepthFitOptions { returns: 1, pool_like, ..DepthFitOptions::for_evidence(4, 1) };
        let (plain, pooled) = (RangeTemplates::new(&a, &opts(0)), RangeTemplates::new(&a, &opts(15)));
        let costs = plain.costs(&y.view()).expect("a frame");
        let (e0, e1) = (plain.evidence(&costs, &intensity, 4), pooled.evidence(&costs, &intensity, 4));
        let c = plain.candidates();
        assert_eq!(e0.noise, e1.noise);
        assert_eq!(e0.features, e1.features, "the posteriors are the pixel's and the wider windows'");
        assert_eq!(e0.skip.slice(ndarray::s![.., .., c..]), e1.skip.slice(ndarray::s![.., .., c..]));
        let (cost, _) = pooled.pooled_costs(&costs, 15);
        let seeds = pooled.pooled_modes(&costs, 15);
        // (the costs are in the square of the scale the taps were brought to, the noise level in the taps' units)
        let nats = 1.0 / (2.0 * e1.noise * costs.scale * costs.scale);
        let mut differ = 0;
        for p in 0..h * w {
            let own = &cost[p * c..(p + 1) * c];
            let least = own.iter().fold(f32::INFINITY, |a, &b| a.min(b));
            for k in 0..c {
                let want = -(own[k] - least) * nats;
                assert!((e1.skip[(p / w, p % w, k)] - want).abs() <= 1e-4 * want.abs().max(1.0), "pixel {p}, candidate {k}");
            }
            let best = (0..c).max_by(|&i, &j| e1.skip[(p / w, p % w, i)].total_cmp(&e1.skip[(p / w, p % w, j)])).unwrap();
            assert!((seeds[p] - best as f32).abs() <= 0.5, "pixel {p}: seed {} against {best}", seeds[p]);
            differ += (0..c).any(|k| e1.skip[(p / w, p % w, k)] != e0.skip[(p / w, p % w, k)]) as usize;
        }
        assert!(differ > h * w / 2, "in dim light pooling changes most windows ({differ})");
    }

    /// A sheet in front of a wall in half the frame: two returns there (both placed), one on
    /// the wall alone, and a dark pixel gets none.
    #[test]
    fn a_sheet_in_front_gets_a_second_return_only_where_it_is() {
        let a = sensor();
        let dz = C * a.bin_width_s() / 2.0;
        let (sheet, wall) = (6.4, 19.7);
        let y = taps(
            &a,
            16,
            16,
            &|i, j| {
                if (i, j) == (15, 15) {
                    vec![]
                } else if j < 8 {
                    vec![(sheet, 0.4), (wall, 1.0)]
                } else {
                    vec![(wall, 1.0)]
                }
            },
            0.0,
        );
        let got = fit_ranges(&y.view(), &a, &DepthFitOptions::default());
        let bins = |k: usize, i: usize, j: usize| got[(k, i, j)] as f64 / dz;
        assert!(got[(0, 15, 15)].is_nan() && got[(1, 15, 15)].is_nan(), "a dark pixel has no return");
        for i in 0..16 {
            for j in 0..16 {
                if (6..=9).contains(&j) || (i, j) == (15, 15) {
                    continue; // windows across the sheet's edge
                }
                if j < 8 {
                    // (the joint fit within a quarter bin, as the range fit's)
                    assert!(
                        (bins(0, i, j) - sheet).abs() < 0.25 && (bins(1, i, j) - wall).abs() < 0.25,
                        "({i}, {j}): {} {}",
                        bins(0, i, j),
                        bins(1, i, j)
                    );
                } else {
                    assert!(
                        (bins(0, i, j) - wall).abs() < 0.05 && got[(1, i, j)].is_nan(),
                        "({i}, {j}): {} {}",
                        bins(0, i, j),
                        bins(1, i, j)
                    );
                }
            }
        }
    }
}
