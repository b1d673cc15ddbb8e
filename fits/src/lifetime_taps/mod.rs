//! Lifetimes straight from the tap images: a reconvolution fit in the **measurement domain**,
//! as gated FLIm does it (rapid lifetime determination generalised to any codes), with no cube
//! in between.
//!
//! A pixel of subpixel type `n` measures `y_m = Σ_t A[n][m][t]·x(t)`. For a decay of one
//! lifetime on a background, `x = a·(IRF ⊛ D_τ) + b`, its taps divided by their sum are
//!
//! ```text
//! r_m = y_m / Σ_m' y_m' = (1 − β)·g_m(τ) + β·g_m(bg),   g(τ) = A_n (IRF ⊛ D_τ) / Σ,  g(bg) = A_n 1 / Σ,
//! ```
//!
//! with `β ∈ [0, 1]` the background's share of the pixel's charge: the amplitude drops out, and
//! for each candidate `τ` the best `β` is one clamped projection. The cost of `τ` at a pixel is
//! its squared residual times the pixel's charge (shot noise makes the variance of `r` fall as
//! one over the charge), and the lifetime is the minimum of that cost **summed over a small
//! window** of neighbours (all subpixel types of the block take part, each with its own row of
//! `A`): the 4 taps of one pixel hold 3 numbers about its decay, a 3×3 window 27.
//!
//! The onset `t₀` and the IRF width are the instrument's, one per frame: they come from the
//! same cost summed over the frame's brightest pixels, searched over every bin of the cycle
//! (a cyclic shift of the templates) and the candidate widths, then refined to a quarter bin.
//! A delayed scene therefore gives the same lifetimes: the search finds the delayed onset.
//! In a dim frame each pixel's own best lifetime and background share fit its noise, the better
//! at later onsets, and the onset comes late; there the frame's brightest pixels are instead
//! scored under one mixture of (lifetime, background share) components that the frame shares,
//! its weights fitted by EM at the temperature of a tap's noise (from neighbouring pixels), and
//! the IRF held at its narrowest width (docs/lifetimes.md, "The frame's mixture").
//! The lifetimes are searched on a log grid and refined by a parabola through the minimum.

pub mod evidence;
mod instrument;
mod tables;

use instrument::*;
pub use instrument::{instrument_side, MAX_INSTRUMENT_BLOCKS};
use tables::*;

use crate::engine::{argmin, golden, golden_lanes, window_rows, window_total};
use ndarray::{Array2, ArrayView3, Axis};
use rayon::prelude::*;
use tcsense_sensor::waveform::subpixel_flat;
use tcsense_sensor::MeasurementMatrix;

use tcsense_sensor::waveform::{decay_bin_averages, Cycle, IrfKernel};

/// Settings of [`fit_taps`].
#[derive(Debug, Clone, PartialEq)]
pub struct TapFitOptions {
    /// Lifetimes searched, `[lo, hi]` (s).
    pub tau_range_s: [f64; 2],
    /// Points of the log grid of lifetimes.
    pub points: usize,
    /// Side of the square window whose costs are summed (1: every pixel alone).
    pub window: usize,
    /// Pixels whose charge is below this fraction of the brightest pixel's get no lifetime.
    pub min_intensity: f32,
    /// The onset `t₀` (s) when known (a calibration); `None`: fitted to the frame.
    pub onset_s: Option<f64>,
    /// Candidate FWHMs (s) of the fluorescence IRF on top of the sensor's response (in `A`).
    pub irf_fwhm_s: Vec<f64>,
    /// Brightest pixels the onset and IRF are fitted on.
    pub brightest: usize,
    /// Fit a background (`β`) per pixel.
    pub background: bool,
    /// Side of the neighbourhood pooled by likeness (0: the window alone; an odd multiple of
    /// the window's side): the window's cost plus the costs of the neighbouring windows that
    /// tile it, each weighted by how much its posterior overlaps the pixel's window's
    /// ([`crate::evidence::similarity_pool`]).
    pub pool_like: usize,
    /// Side, in blocks of the sensor's subpixel mosaic, of the superpixels the instrument is
    /// fitted on (each subpixel type's taps summed over the superpixel): 1, every pixel alone;
    /// 0, from the frame's photons: every pixel alone where they hold enough photons
    /// ([`instrument_side`] of 1), else the brightest pixels alone under the frame's mixture of
    /// lifetimes and background shares (no superpixels; see the module's notes).
    pub instrument_blocks: usize,
    /// With `instrument_blocks` 0, where the frame's photons ask for superpixels: its
    /// brightest pixels alone under the frame's mixture (true), or superpixels of
    /// [`instrument_side`]'s side (false: as before the mixture).
    pub instrument_mixture: bool,
    /// Where a decoder's mode overrules the fit ([`LifetimeTemplates::refine_modes`]): refine
    /// it in the tap domain wherever it is within one point of the grid of the fit's own
    /// argmin (the window's cost minimised within about a point of the mode), not only where
    /// it is that argmin. False: the fit's refinement only at its own argmin.
    pub refine_near_mode: bool,
}

impl Default for TapFitOptions {
    /// Lifetimes 0.1–25 ns on 96 points, a 3×3 window, pixels above 2 % of the brightest, the
    /// onset fitted, IRF widths 0–2 ns, 256 pixels (or superpixels, as the frame's photons
    /// ask) for the instrument, a background.
    fn default() -> Self {
        TapFitOptions {
            tau_range_s: [0.1e-9, 25e-9],
            points: 96,
            window: 3,
            min_intensity: 0.02,
            onset_s: None,
            irf_fwhm_s: vec![0.0, 0.5e-9, 1e-9, 1.5e-9, 2e-9],
            brightest: 256,
            background: true,
            pool_like: 0,
            instrument_blocks: 0,
            instrument_mixture: true,
            refine_near_mode: false,
        }
    }
}

impl TapFitOptions {
    /// Checks the settings; the error names the field.
    pub fn validate(&self) -> Result<(), String> {
        use crate::range::MAX_WINDOW;
        let [lo, hi] = self.tau_range_s;
        if !(lo > 0.0 && hi > lo && hi.is_finite()) {
            return Err(format!("tau_range_s: [{lo:e}, {hi:e}], expected 0 < lo < hi"));
        }
        if self.points < 3 {
            return Err(format!("points: {}, expected at least 3", self.points));
        }
        if self.window == 0 || self.window.is_multiple_of(2) || self.window > MAX_WINDOW {
            return Err(format!("window: {}, expected an odd size from 1 to {MAX_WINDOW} pixels", self.window));
        }
        if !(0.0..1.0).contains(&self.min_intensity) {
            return Err(format!("min_intensity: {}, expected a fraction in [0, 1)", self.min_intensity));
        }
        if self.irf_fwhm_s.is_empty() || self.irf_fwhm_s.iter().any(|w| !(w.is_finite() && *w >= 0.0)) {
            return Err(format!("irf_fwhm_s: {:?}, expected one or more widths ≥ 0", self.irf_fwhm_s));
        }
        if let Some(t) = self.onset_s.filter(|t| !(t.is_finite() && t.abs() <= tcsense_sensor::params::MAX_RESPONSE_S)) {
            return Err(format!("onset: {:e} s, expected a time within ±1 µs of the cycle's start (taken modulo the code cycle)", t));
        }
        if self.brightest == 0 {
            return Err("brightest: expected at least 1 pixel".into());
        }
        if self.instrument_blocks > MAX_INSTRUMENT_BLOCKS {
            return Err(format!(
                "instrument_blocks: {}, expected 0 (chosen from the frame's photons) or a superpixel side of 1 to {MAX_INSTRUMENT_BLOCKS} blocks",
                self.instrument_blocks
            ));
        }
        if self.pool_like != 0 && !pooled_side(self.pool_like, self.window) {
            return Err(format!(
                "pool_like: {}, expected 0 (the window alone) or an odd multiple of the window's side {} above it, up to {MAX_WINDOW} pixels (e.g. {})",
                self.pool_like,
                self.window,
                3 * self.window
            ));
        }
        Ok(())
    }
}

pub use crate::evidence::pooled_side;

/// What [`fit_taps`] gives for one frame.
#[derive(Debug, Clone)]
pub struct TapFit {
    /// Lifetime `[H, W]` (s); NaN where the pixel holds too little charge or its best lifetime
    /// lies on a bound of the range searched.
    pub lifetime: Array2<f32>,
    /// The taps' sum per pixel `[H, W]` (the measurements' units).
    pub intensity: Array2<f32>,
    /// The background's share `β` of each pixel's charge `[H, W]` (NaN where no lifetime).
    pub background: Array2<f32>,
    /// The frame's onset `t₀` (s, in `[0, P)`).
    pub onset_s: f64,
    /// The fluorescence IRF's FWHM (s).
    pub irf_fwhm_s: f64,
}

/// The instrument of a FLIm frame: its onset and the fluorescence IRF's width. One per
/// recording (the laser's trigger and the optics), so a stream estimates it once.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Instrument {
    /// The onset `t₀` (s, in `[0, P)`).
    pub onset_s: f64,
    /// The fluorescence IRF's FWHM (s) on top of the sensor's response.
    pub irf_fwhm_s: f64,
}

/// A frame's taps normalised by their sum `r` `[H·W][M]`, the sum as weight `[H·W]` (0 below the
/// floor of `min_intensity` of the brightest pixel's, and where no lifetime is fitted) and the
/// sum as the intensity map `[H, W]`.
struct Normalised {
    r: Vec<f32>,
    weight: Vec<f32>,
    intensity: Array2<f32>,
}

fn normalise(y: &ArrayView3<'_, f32>, min_intensity: f32) -> Normalised {
    let (m, h, w) = y.dim();
    let intensity = y.sum_axis(Axis(0));
    let peak = intensity.iter().fold(0f32, |p, &v| p.max(v));
    let floor = min_intensity * peak;
    let mut r = vec![0f32; h * w * m];
    let mut weight = vec![0f32; h * w];
    r.par_chunks_mut(w * m).zip(weight.par_chunks_mut(w)).enumerate().for_each(|(i, (rr, ww))| {
        for j in 0..w {
            let s = intensity[(i, j)];
            if s > 0.0 && s > floor {
                ww[j] = s;
                for k in 0..m {
                    rr[j * m + k] = y[(k, i, j)] / s;
                }
            }
        }
    });
    Normalised { r, weight, intensity }
}

/// The onset and IRF width of one frame (see the module's notes): searched over every bin of
/// the cycle on the frame's brightest pixels, or only the width when `opts.onset_s` is given.
///
/// # Shapes
/// - `y`: `[M, H, W]`, `a`: `A [N, M, T]`
pub fn estimate_instrument(y: &ArrayView3<'_, f32>, a: &MeasurementMatrix, opts: &TapFitOptions) -> Instrument {
    instrument_of(&normalise(y, opts.min_intensity), y.dim(), a, opts)
}

/// How many frames of a recording to sum before its instrument is searched, from the first
/// frame `y`: 1 when its pixels hold enough photons on their own, else `s²` where `s` is the
/// superpixels' side [`instrument_side`] would take (up to 16). The onset and the IRF are the
/// sensor's and the laser's, the same in every frame, so the sum has the photons of a superpixel
/// without mixing neighbouring cells' lifetimes, as superpixels do (a static scene keeps each
/// pixel's lifetime; frames of other scenes mix theirs as a superpixel would).
///
/// # Shapes
/// - `y`: `[M, H, W]`, `a`: `A [N, M, T]`
pub fn instrument_frames(y: &ArrayView3<'_, f32>, a: &MeasurementMatrix, opts: &TapFitOptions) -> usize {
    let (m, h, w) = y.dim();
    let f = normalise(y, opts.min_intensity);
    let side = side_of(&f.r, &f.weight, (m, h, w), a.block(), &brightest_of(&f.weight, opts.brightest));
    side * side
}

/// [`estimate_instrument`] of a normalised frame of `[M, H, W]`: on its pixels, or on
/// superpixels of `opts.instrument_blocks` (or [`instrument_side`]'s) blocks of the mosaic.
fn instrument_of(f: &Normalised, (m, h, w): (usize, usize, usize), a: &MeasurementMatrix, opts: &TapFitOptions) -> Instrument {
    let block = a.block();
    let c = Cycle::new(a.bins(), a.bin_width_s());
    let bright = brightest_of(&f.weight, opts.brightest);
    let gain = (opts.instrument_blocks == 0).then(|| frame_gain(&f.r, &f.weight, (m, h, w), block, &bright)).flatten();
    let side = match opts.instrument_blocks {
        0 => side_for(gain, (h, w), block),
        s => s,
    };
    // a dim frame: its brightest pixels alone under the frame's mixture, at the temperature
    // of a tap's noise (`g/M` in the costs' units: a charge `S`'s normalised taps vary by
    // `g·r̄_k/S`, and the costs are weighted by `S`)
    let temperature = gain.filter(|_| opts.instrument_mixture && side > 1 && opts.onset_s.is_none()).map(|(gain, _)| gain / m as f64);
    // at the narrowest IRF width: in dim light the widths are not told apart, and the onset
    // would drift with the width chosen
    let (onset_s, irf_fwhm_s) = if temperature.is_some() {
        let narrow = TapFitOptions { irf_fwhm_s: vec![opts.irf_fwhm_s.iter().copied().fold(f64::INFINITY, f64::min)], ..opts.clone() };
        instrument(&a.a(), c, &narrow, &f.r, &f.weight, &bright, m, &|p: usize| subpixel_flat(p, w, block), temperature)
    } else if side > 1 {
        let (r, weight) = superpixels(f, (m, h, w), block, side);
        let types = block.0 * block.1;
        instrument(&a.a(), c, opts, &r, &weight, &brightest_of(&weight, opts.brightest), m, &|q: usize| q % types, None)
    } else {
        instrument(&a.a(), c, opts, &f.r, &f.weight, &bright, m, &|p: usize| subpixel_flat(p, w, block), None)
    };
    Instrument { onset_s, irf_fwhm_s }
}

/// Lifetimes of one frame of tap images through the sensor `A`: the instrument estimated from
/// the frame ([`estimate_instrument`]), then every pixel by [`LifetimeTemplates`].
///
/// # Shapes
/// - `y`: `[M, H, W]` (H, W multiples of `A`'s block), `a`: `A [N, M, T]` → maps `[H, W]`
pub fn fit_taps(y: &ArrayView3<'_, f32>, a: &MeasurementMatrix, opts: &TapFitOptions) -> TapFit {
    let f = normalise(y, opts.min_intensity);
    let instrument = instrument_of(&f, y.dim(), a, opts);
    LifetimeTemplates::new(a, instrument, opts).fit_normalised(f, y.dim())
}

/// What the fit's templates are made of: for every lifetime of `opts`' grid, the periodic
/// decay convolved with the instrument's IRF and starting at its onset, averaged over the bins
/// of `a`'s cycle, `[G][T]`. The template of subpixel type `n` at lifetime `i` is
/// `A_n · curve_i` divided by its sum over the taps (what a differentiable copy of the fit,
/// `tcsense_models::lifetime`, projects through learned codes).
pub fn grid_decays(a: &MeasurementMatrix, instrument: Instrument, opts: &TapFitOptions) -> Vec<Vec<f64>> {
    decays(Cycle::new(a.bins(), a.bin_width_s()), &grid(opts, opts.points), instrument.onset_s, instrument.irf_fwhm_s)
}

/// The fit to the taps as dense linear algebra, for one sensor and instrument: the templates
/// of every subpixel type on a log grid of lifetimes (and on the grid of half steps), every
/// pixel's cost on the grid at once (a pixel's 4 taps against the `G` templates of its type,
/// the background share of each in closed form), the costs summed over the window by a box
/// filter, the best lifetime by an argmin, then a parabola through the window's cost at the
/// half steps either side. Built once and applied to every frame of a stream.
///
/// A best lifetime on either end of the grid is not an estimate (the optimum lies on or beyond
/// the bound searched): the pixel gets NaN.
#[derive(Clone)]
pub struct LifetimeTemplates {
    coarse: Vec<TypeTable>,
    fine: Vec<TypeTable>,
    block: (usize, usize),
    taps: usize,
    /// `ln τ` of the grid's first point and its step.
    log_tau: (f64, f64),
    instrument: Instrument,
    window: usize,
    pool_like: usize,
    min_intensity: f32,
    background: bool,
    refine_near_mode: bool,
}

impl LifetimeTemplates {
    /// The templates of sensor `a` at `instrument`, on `opts`' grid.
    pub fn new(a: &MeasurementMatrix, instrument: Instrument, opts: &TapFitOptions) -> LifetimeTemplates {
        let av = a.a();
        let c = Cycle::new(a.bins(), a.bin_width_s());
        let halves = grid(opts, 2 * opts.points - 1);
        let coarse = TypeTable::of(&Templates::new(&av, &grid_decays(a, instrument, opts)));
        let fine = TypeTable::of(&Templates::new(&av, &decays(c, &halves, instrument.onset_s, instrument.irf_fwhm_s)));
        let taus = grid(opts, opts.points);
        let log_tau = (taus[0].ln(), taus[1].ln() - taus[0].ln());
        LifetimeTemplates {
            coarse,
            fine,
            block: a.block(),
            taps: av.dim().1,
            log_tau,
            instrument,
            window: opts.window,
            pool_like: opts.pool_like,
            min_intensity: opts.min_intensity,
            background: opts.background,
            refine_near_mode: opts.refine_near_mode,
        }
    }

    /// Lifetimes of one frame.
    ///
    /// # Shapes
    /// - `y`: `[M, H, W]` → maps `[H, W]`
    pub fn fit(&self, y: &ArrayView3<'_, f32>) -> TapFit {
        self.fit_normalised(normalise(y, self.min_intensity), y.dim())
    }

    /// [`Self::fit`] of a normalised frame of `[M, H, W]`: each pixel's best point of the grid
    /// is the argmin of its window's cost.
    fn fit_normalised(&self, f: Normalised, dims: (usize, usize, usize)) -> TapFit {
        let costs = self.costs_normalised(&f, dims);
        let g = self.points();
        if self.pool_like > self.window {
            return self.fit_pooled(f, dims, &costs);
        }
        self.refine_normalised(f, dims, &costs, |_, total| {
            let best = argmin(total);
            (best > 0 && best + 1 < g).then_some(best)
        })
    }

    /// [`Self::fit_normalised`] pooled by likeness (`opts.pool_like`): each pixel's best point
    /// of the grid is the argmin of its pooled cost ([`crate::evidence::similarity_pool`], in
    /// the frame's nats). Where it is the window's own argmin, the fit's refinement (golden
    /// sections on the window's cost: its precision in bright light, where a parabola through
    /// the pooled costs on the grid is biased by a tenth of a nanosecond at long lifetimes);
    /// elsewhere the parabola through the pooled costs, as the networks on the evidence refine
    /// a mode that overrules the fit ([`Self::refine_modes`]).
    fn fit_pooled(&self, f: Normalised, (m, h, w): (usize, usize, usize), costs: &LifetimeCosts) -> TapFit {
        let g = self.points();
        let (pooled, _) = costs.pooled_by_likeness(&costs.window_sums(), m);
        let (bh, bw) = self.block;
        let (l0, step) = self.log_tau;
        // every lit pixel's pooled best point (none on an end of the grid) with the parabola's
        // lifetime there and the pixel's own background share (NaN without a background)
        let by_pool: Vec<Option<(usize, f32, f32)>> = (0..h * w)
            .into_par_iter()
            .map(|p| {
                let c = &pooled[p * g..(p + 1) * g];
                let b = argmin(c);
                (f.weight[p] > 0.0 && b > 0 && b + 1 < g).then(|| {
                    let u = b as f64 + crate::engine::parabola_min(c[b - 1] as f64, c[b] as f64, c[b + 1] as f64);
                    let beta = if self.background {
                        let n = subpixel_flat(p, w, (bh, bw));
                        self.fine[n].cost_at(2 * b, &f.r[p * m..(p + 1) * m], f.weight[p], true).1
                    } else {
                        f32::NAN
                    };
                    (b, (l0 + u * step).exp() as f32, beta)
                })
            })
            .collect();
        let mut fit = self.refine_normalised(f, (m, h, w), costs, |p, total| by_pool[p].map(|(b, _, _)| b).filter(|&b| b == argmin(total)));
        for ((t, beta), pooled) in fit.lifetime.iter_mut().zip(fit.background.iter_mut()).zip(&by_pool) {
            if let (true, Some((_, tau, share))) = (t.is_nan(), pooled) {
                (*t, *beta) = (*tau, *share);
            }
        }
        fit
    }

    /// Points `G` of the lifetime grid.
    pub fn points(&self) -> usize {
        self.coarse[0].points
    }

    /// The grid: `ln τ` (τ in s) of its first point and its step; point `i` is
    /// `τ_i = exp(ln τ₀ + i·step)`.
    pub fn log_grid(&self) -> (f64, f64) {
        self.log_tau
    }

    /// The instrument the templates are built for.
    pub fn instrument(&self) -> Instrument {
        self.instrument
    }

    /// The fit's evidence for every lifetime of the grid, before any choice is made: each lit
    /// pixel's own cost and the cost summed over the window (what [`Self::fit`] minimises).
    ///
    /// # Shapes
    /// - `y`: `[M, H, W]` → [`LifetimeCosts`] of `[H·W·G]`
    pub fn costs(&self, y: &ArrayView3<'_, f32>) -> LifetimeCosts {
        self.costs_normalised(&normalise(y, self.min_intensity), y.dim())
    }

    /// Lifetimes refined in the tap domain around a point of the grid chosen per pixel by
    /// someone else (a network reading [`Self::costs`]): golden sections on the window's cost
    /// within a step of `best[p]`, as [`Self::fit`] refines its own argmin. `best[p] < 0`, or on
    /// either end of the grid, or an unlit pixel gives NaN.
    ///
    /// # Shapes
    /// - `y`: `[M, H, W]`, `best`: `[H·W]` → maps `[H, W]`
    pub fn refine(&self, y: &ArrayView3<'_, f32>, best: &[i32]) -> TapFit {
        let f = normalise(y, self.min_intensity);
        let costs = self.costs_normalised(&f, y.dim());
        let g = self.points() as i32;
        assert_eq!(best.len(), costs.lit.len(), "refine: one point of the grid per pixel");
        self.refine_normalised(f, y.dim(), &costs, |p, _| (best[p] > 0 && best[p] + 1 < g).then_some(best[p] as usize))
    }

    /// The modes of a posterior over the grid (continuous grid coordinates `u`, NaN: none) as
    /// lifetimes (s): where a mode's nearest point is the fit's own argmin of the window's cost
    /// the fit's refinement in the tap domain (its precision in bright light), elsewhere the
    /// mode itself (the posterior overruled the fit). With
    /// [`TapFitOptions::refine_near_mode`], a mode within one point of the argmin is refined
    /// too, around its own nearest point: the window's cost minimised within about a point of
    /// the mode. NaN where no pixel of the window holds charge: there is no evidence there,
    /// whatever the mode.
    ///
    /// The refinement is taken only where the window's own cost pins its argmin to within
    /// [`REFINE_PRECISION_POINTS`] (its curvature there, in the frame's nats): in dim light the
    /// window's optimum is noise, and a refinement towards it would undo what the posterior
    /// pooled; the mode stands there.
    ///
    /// # Shapes
    /// - `y`: `[M, H, W]`, `costs`: [`Self::costs`] of `y`, `u`: `[H·W]` → `[H, W]`
    pub fn refine_modes(&self, y: &ArrayView3<'_, f32>, costs: &LifetimeCosts, u: &[f32]) -> Array2<f32> {
        let (m, h, w) = y.dim();
        assert!(u.len() == h * w && costs.lit.len() == h * w, "refine_modes: one mode per pixel");
        let g = self.points();
        // the frame's nats per unit of cost (the window's noise level, as the evidence reads it)
        let nats = 1.0 / (2.0 * costs.noise_level_here(m) as f64);
        let f = normalise(y, self.min_intensity);
        let fit = self.refine_normalised(f, y.dim(), costs, |p, total| {
            let best = argmin(total);
            let mode = u[p].round();
            if !(mode.is_finite() && mode >= 0.0) || best == 0 || best + 1 >= g {
                return None;
            }
            let curvature = (total[best - 1] as f64 + total[best + 1] as f64 - 2.0 * total[best] as f64) * nats;
            if !(curvature > 0.0 && curvature.sqrt().recip() < REFINE_PRECISION_POINTS) {
                return None;
            }
            let mode = mode as usize;
            let near = if self.refine_near_mode { mode.abs_diff(best) <= 1 } else { mode == best };
            (near && mode > 0 && mode + 1 < g).then_some(mode)
        });
        let (l0, step) = self.log_tau;
        // no lit pixel in the window: no evidence, no lifetime (whatever the mode says)
        let half = self.window / 2;
        let seen = |i: usize, j: usize| {
            (i.saturating_sub(half)..=(i + half).min(h - 1))
                .any(|a| (j.saturating_sub(half)..=(j + half).min(w - 1)).any(|b| costs.lit[a * w + b]))
        };
        Array2::from_shape_fn((h, w), |(i, j)| {
            let t = fit.lifetime[(i, j)];
            let v = u[i * w + j];
            if t.is_finite() || !v.is_finite() {
                t
            } else if seen(i, j) {
                (l0 + v as f64 * step).exp() as f32
            } else {
                f32::NAN
            }
        })
    }

    /// Every lit pixel's cost on the grid, alone and summed over the window.
    fn costs_normalised(&self, f: &Normalised, (m, h, w): (usize, usize, usize)) -> LifetimeCosts {
        assert_eq!(m, self.taps, "taps of the frame and the templates");
        let (bh, bw) = self.block;
        let g = self.points();
        let Normalised { r, weight, .. } = f;
        let kind = |p: usize| subpixel_flat(p, w, (bh, bw));
        let mut pixel = vec![0f32; h * w * g];
        pixel.par_chunks_mut(w * g).enumerate().for_each(|(i, out)| {
            let mut beta = vec![0f32; g];
            for j in 0..w {
                let p = i * w + j;
                if weight[p] > 0.0 {
                    self.coarse[kind(p)].costs(&r[p * m..(p + 1) * m], weight[p], self.background, &mut beta, &mut out[j * g..(j + 1) * g]);
                }
            }
        });
        let lit: Vec<bool> = weight.iter().map(|&v| v > 0.0).collect();
        let mut rows = Vec::new();
        window_rows(&pixel, &lit, (h, w), g, self.window, &mut rows);
        LifetimeCosts {
            pixel,
            rows,
            lit,
            points: g,
            height: h,
            width: w,
            window: self.window,
            pool_like: self.pool_like,
            noise: std::sync::OnceLock::new(),
        }
    }

    /// The refinement of every pixel around the point of the grid `choose(p, window's cost)`
    /// gives it (`None`: no lifetime).
    fn refine_normalised(
        &self,
        f: Normalised,
        (m, h, w): (usize, usize, usize),
        costs: &LifetimeCosts,
        choose: impl Fn(usize, &[f32]) -> Option<usize> + Sync,
    ) -> TapFit {
        let (bh, bw) = self.block;
        let g = self.points();
        let Normalised { r, weight, intensity } = f;
        let kind = |p: usize| subpixel_flat(p, w, (bh, bw));
        // (the type of a window's slot, beyond the frame too: the same in every lane)
        let kind_at = |i: isize, j: isize| (i.rem_euclid(bh as isize) as usize) * bw + j.rem_euclid(bw as isize) as usize;
        let half = self.window / 2;
        let fits: Vec<(f32, f32)> = (0..h)
            .into_par_iter()
            .flat_map_iter(|i| {
                // the window's pixels (index, type) and the templates between the half steps
                let mut win: Vec<(usize, usize)> = Vec::with_capacity(self.window * self.window);
                let mut between = Between::new(self.fine.len(), m);
                let mut total = vec![0f32; g];
                let (rows, r, weight, choose) = (&costs.rows, &r, &weight, &choose);
                // each pixel's best point on the grid of half steps (None: no lifetime)
                let centres: Vec<Option<usize>> = (0..w)
                    .map(|j| {
                        let p = i * w + j;
                        if weight[p] <= 0.0 {
                            return None;
                        }
                        window_total(rows, (i, j), (h, w), self.window, &mut total);
                        let best = choose(p, &total)?;
                        win.clear();
                        for ii in i.saturating_sub(half)..(i + half + 1).min(h) {
                            for jj in j.saturating_sub(half)..(j + half + 1).min(w) {
                                let q = ii * w + jj;
                                if weight[q] > 0.0 {
                                    win.push((q, kind(q)));
                                }
                            }
                        }
                        // the window's cost at the half steps either side of the best; golden
                        // sections follow within a half step of the best of them, the templates
                        // linear between the half steps (the cost has a kink where the background
                        // share reaches 0, which a parabola would straddle)
                        let at = |f: usize| -> f32 {
                            win.iter().map(|&(q, n)| self.fine[n].cost_at(f, &r[q * m..(q + 1) * m], weight[q], self.background).0).sum()
                        };
                        let c = [total[best - 1], at(2 * best - 1), total[best], at(2 * best + 1), total[best + 1]];
                        let k = 1 + argmin(&c[1..4]);
                        Some(2 * best + k - 2)
                    })
                    .collect();
                // the golden sections of the pixels of one column class (the same subpixel type
                // in every slot of their windows), LANES at a time
                let mut us = vec![f64::NAN; w];
                let side = 2 * half + 1;
                let mut lanes = LaneWindow::new(&self.fine, m, side * side);
                for class in 0..bw.min(w) {
                    let js: Vec<usize> = (class..w).step_by(bw).filter(|&j| centres[j].is_some()).collect();
                    for chunk in js.chunks(LANES) {
                        let mut best = [0usize; LANES];
                        for l in 0..LANES {
                            // (a lane past the chunk's end repeats its last pixel)
                            let j = chunk[l.min(chunk.len() - 1)];
                            best[l] = centres[j].unwrap_or(0);
                            let mut s = 0;
                            for di in 0..side {
                                for dj in 0..side {
                                    let (ii, jj) = ((i + di) as isize - half as isize, (j + dj) as isize - half as isize);
                                    let inside = ii >= 0 && jj >= 0 && (ii as usize) < h && (jj as usize) < w;
                                    let q = if inside { ii as usize * w + jj as usize } else { 0 };
                                    let pixel = (inside && weight[q] > 0.0).then(|| (&r[q * m..(q + 1) * m], weight[q]));
                                    lanes.set_slot(s, l, kind_at(ii, jj), pixel);
                                    s += 1;
                                }
                            }
                        }
                        let found = golden_lanes(&best, 2 * g - 2, REFINE_STEPS, &mut |u, out| lanes.costs(u, self.background, out));
                        for (l, &j) in chunk.iter().enumerate() {
                            us[j] = found[l].0;
                        }
                    }
                }
                (0..w).map(move |j| {
                    let p = i * w + j;
                    if centres[j].is_none() {
                        return (f32::NAN, f32::NAN);
                    }
                    let u = us[j];
                    let tau = (self.log_tau.0 + 0.5 * u * self.log_tau.1).exp();
                    let beta = if self.background {
                        between.set(&self.fine, u);
                        between.cost(kind(p), &r[p * m..(p + 1) * m], weight[p], true).1
                    } else {
                        0.0
                    };
                    (tau as f32, beta)
                })
            })
            .collect();
        let lifetime = Array2::from_shape_fn((h, w), |(i, j)| fits[i * w + j].0);
        let background = Array2::from_shape_fn((h, w), |(i, j)| fits[i * w + j].1);
        TapFit { lifetime, intensity, background, onset_s: self.instrument.onset_s, irf_fwhm_s: self.instrument.irf_fwhm_s }
    }
}

/// The fit's evidence on its lifetime grid for one frame ([`LifetimeTemplates::costs`]).
#[derive(Debug, Clone)]
pub struct LifetimeCosts {
    /// Each pixel's own cost of every lifetime of the grid `[H·W·G]` (pixel-major; 0 where
    /// unlit): its squared residual times its charge.
    pub pixel: Vec<f32>,
    /// The first pass of the window's sum ([`window_rows`]) `[H·W·G]`.
    rows: Vec<f32>,
    /// Whether a pixel holds enough charge to be fitted `[H·W]`.
    pub lit: Vec<bool>,
    /// `G`, `H`, `W` and the window's side.
    pub points: usize,
    pub height: usize,
    pub width: usize,
    pub window: usize,
    /// The side of the neighbourhood the templates pool by likeness (0: none), which
    /// [`evidence::evidence`] pools the window's costs over.
    pub pool_like: usize,
    /// The window's noise level ([`Self::noise_level`]), found once a frame.
    noise: std::sync::OnceLock<f32>,
}

impl LifetimeCosts {
    /// These costs as the fit's [`crate::evidence::CostVolume`], with their window sums
    /// ([`Self::window_sums`]) and the taps per pixel `M`: a window of `n` lit pixels holds
    /// `n·(M − 1)` numbers about its decay (each pixel's amplitude is its own), two of which the
    /// lifetime and the background take.
    pub fn volume<'a>(&'a self, window: &'a [f32], taps: usize) -> crate::evidence::CostVolume<'a> {
        crate::evidence::CostVolume {
            pixel: &self.pixel,
            window,
            lit: &self.lit,
            points: self.points,
            height: self.height,
            width: self.width,
            side: self.window,
            free_per_pixel: taps.saturating_sub(1),
            shared: 2,
        }
    }

    /// The window's costs (`window`, [`Self::window_sums`]) pooled by likeness over the
    /// neighbourhood of [`Self::pool_like`] ([`crate::evidence::similarity_pool`]) in the
    /// window's nats, and that noise level ([`crate::evidence::noise_level`]), for taps per
    /// pixel `M`.
    ///
    /// # Shapes
    /// - `window`: `[H·W·G]` → `([H·W·G], noise)`
    pub fn pooled_by_likeness(&self, window: &[f32], taps: usize) -> (Vec<f32>, f32) {
        let volume = self.volume(window, taps);
        let noise = self.noise_level(window, taps);
        (crate::evidence::similarity_pool(&volume, 1.0 / (2.0 * noise), self.pool_like), noise)
    }

    /// The frame's noise level of the window's costs ([`crate::evidence::noise_level`]: twice
    /// it turns a cost into nats), for their window sums `window` ([`Self::window_sums`]) and
    /// `M` taps a pixel. Found on the first call and kept: the evidence and the refinement of
    /// a network's modes read the same level.
    ///
    /// # Shapes
    /// - `window`: `[H·W·G]`
    pub fn noise_level(&self, window: &[f32], taps: usize) -> f32 {
        *self.noise.get_or_init(|| crate::evidence::noise_level(&self.volume(window, taps)))
    }

    /// [`Self::noise_level`], the window sums computed here when the level is not known yet.
    fn noise_level_here(&self, taps: usize) -> f32 {
        *self.noise.get_or_init(|| crate::evidence::noise_level(&self.volume(&self.window_sums(), taps)))
    }

    /// The cost summed over the window around every pixel, what the fit minimises `[H·W·G]`.
    pub fn window_sums(&self) -> Vec<f32> {
        let (h, w, g) = (self.height, self.width, self.points);
        let mut out = vec![0f32; h * w * g];
        out.par_chunks_mut(w * g).enumerate().for_each(|(i, row)| {
            for (j, total) in row.chunks_mut(g).enumerate() {
                window_total(&self.rows, (i, j), (h, w), self.window, total);
            }
        });
        out
    }
}

/// How precisely (one standard deviation, in points of the grid) a window's own cost must pin
/// its best lifetime for [`LifetimeTemplates::refine_modes`] to refine a posterior's mode in
/// the tap domain: below it the refinement adds what the grid lacks (bright light), above it
/// the window's optimum is noise that the pooled posterior has already weighed (dim light).
/// Measured on `zoo:lifetime-flim-pooled-fast` (docs/lifetimes.md): 0.35, 0.5 and 0.7 give the
/// same errors at 0.02 of the full well, 0.5 the lowest at 0.1.
pub const REFINE_PRECISION_POINTS: f64 = 0.5;

/// Golden-section steps of the refinement within a half step of the best (the bracket of one
/// grid step shrinks to 0.618⁸ of itself: 0.02 steps, 0.001 in `ln τ` on the default grid).
const REFINE_STEPS: usize = 8;

/// The reference fit the fast one is tested against: per pixel, the window's cost on the grid,
/// then golden sections between the grid's points on Catmull-Rom templates.
#[cfg(test)]
fn fit_taps_reference(y: &ArrayView3<'_, f32>, a: &MeasurementMatrix, opts: &TapFitOptions, inst: Instrument) -> Array2<f32> {
    let (m, h, w) = y.dim();
    let (bh, bw) = a.block();
    let c = Cycle::new(a.bins(), a.bin_width_s());
    let Normalised { r, weight, .. } = normalise(y, opts.min_intensity);
    let r: Vec<f64> = r.iter().map(|&v| v as f64).collect();
    let weight: Vec<f64> = weight.iter().map(|&v| v as f64).collect();
    let kind = |p: usize| subpixel_flat(p, w, (bh, bw));
    let taus = grid(opts, opts.points);
    let tpl = Templates::new(&a.a(), &decays(c, &taus, inst.onset_s, inst.irf_fwhm_s));
    let g = taus.len();
    let half = opts.window / 2;
    Array2::from_shape_fn((h, w), |(i, j)| {
        let p = i * w + j;
        if weight[p] <= 0.0 {
            return f32::NAN;
        }
        let window: Vec<usize> = (i.saturating_sub(half)..(i + half + 1).min(h))
            .flat_map(|ii| (j.saturating_sub(half)..(j + half + 1).min(w)).map(move |jj| ii * w + jj))
            .filter(|&q| weight[q] > 0.0)
            .collect();
        let total: Vec<f64> = (0..g)
            .map(|t| window.iter().map(|&q| tpl.cost(t, kind(q), &r[q * m..(q + 1) * m], weight[q], opts.background).0).sum())
            .collect();
        let best = (0..g).min_by(|&x, &y| total[x].total_cmp(&total[y])).unwrap_or(0);
        if best == 0 || best + 1 == g {
            return f32::NAN;
        }
        let mut gq = vec![0.0; m];
        let (u, _) = golden(best, g - 1, 24, &mut |u| {
            window
                .iter()
                .map(|&q| {
                    tpl.at(u, kind(q), &mut gq);
                    tpl.cost_of(&gq, kind(q), &r[q * m..(q + 1) * m], weight[q], opts.background).0
                })
                .sum()
        });
        (taus[0].ln() + u * (taus[1].ln() - taus[0].ln())).exp() as f32
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use tcsense_sensor::generate::prototype_codes;
    use tcsense_sensor::{Irf, Sampling};

    /// The prototype's geometry (4 taps, 2×2, L = 32 at 607 MHz, heterodyne K = 8, physical IRF).
    fn sensor_object() -> tcsense_sensor::Sensor {
        tcsense_sensor::Sensor::ideal(
            prototype_codes(1).unwrap(),
            Sampling::Heterodyne(8),
            Irf::Physical { laser_fwhm_s: 2.55e-9, tap_tau_s: 0.3e-9 },
        )
        .unwrap()
    }

    fn sensor() -> MeasurementMatrix {
        sensor_object().matrix().clone()
    }

    /// Noise-free taps `[M, H, W]` of a scene whose pixel `(i, j)` decays with `tau(i, j)` (by
    /// the datasets crate's generator, an independent implementation), onset `t0`, IRF `fwhm`,
    /// a background share and a brightness that varies over the frame.
    fn taps(
        a: &MeasurementMatrix,
        h: usize,
        w: usize,
        tau: &dyn Fn(usize, usize) -> f64,
        t0: f64,
        fwhm: f64,
        bg: f64,
    ) -> ndarray::Array3<f32> {
        let grid = tcsense_datasets::grid::TimeGrid { length: 32, clock_hz: 607e6, sampling: Sampling::Heterodyne(8) };
        let av = a.a();
        let (bh, bw) = a.block();
        let (_, m, t) = av.dim();
        let mut y = ndarray::Array3::<f32>::zeros((m, h, w));
        for i in 0..h {
            for j in 0..w {
                let d = IrfKernel::gaussian(grid.cycle(), fwhm).apply(&decay_bin_averages(grid.cycle(), tau(i, j), t0));
                let total: f64 = d.iter().sum();
                let bright = 0.3 + 0.7 * ((i * w + j) % 7) as f64 / 6.0;
                let n = tcsense_sensor::waveform::subpixel(i, j, (bh, bw));
                for k in 0..m {
                    y[(k, i, j)] =
                        (bright * (0..t).map(|s| av[(n, k, s)] as f64 * ((1.0 - bg) * d[s] / total + bg / t as f64)).sum::<f64>()) as f32;
                }
            }
        }
        y
    }

    #[test]
    fn recovers_lifetimes_at_any_onset_irf_and_background() {
        let a = sensor();
        // two regions of different lifetimes (left 0.6 ns, right 3.5 ns) so the window sees an edge
        let tau = |_: usize, j: usize| if j < 4 { 0.6e-9 } else { 3.5e-9 };
        for &(t0, fwhm, bg) in &[(2e-9, 0.0, 0.0), (31.7e-9, 1.0e-9, 0.03), (51.9e-9, 2.0e-9, 0.0), (0.1e-9, 0.5e-9, 0.05)] {
            let y = taps(&a, 8, 8, &tau, t0, fwhm, bg);
            // a pixel alone can hold all its charge in one tap (its code has no transition near
            // the decay) and then says nothing about τ: the window brings the other subpixel types
            {
                let window = 3;
                let fit = fit_taps(&y.view(), &a, &TapFitOptions { window, ..Default::default() });
                let dt = (fit.onset_s - t0 + 26.35e-9).rem_euclid(52.7e-9) - 26.35e-9;
                assert!(dt.abs() < 0.005e-9, "onset {:e} vs {t0:e}", fit.onset_s);
                assert!((fit.irf_fwhm_s - fwhm).abs() < 0.1e-9, "IRF {:e} vs {fwhm:e}", fit.irf_fwhm_s);
                for ((i, j), &v) in fit.lifetime.indexed_iter() {
                    // pixels whose window straddles the edge mix both lifetimes
                    if (3..=4).contains(&j) {
                        continue;
                    }
                    let want = tau(i, j);
                    assert!(
                        ((v as f64) - want).abs() < 0.01 * want,
                        "τ at ({i}, {j}) = {v:e}, want {want:e} (onset {t0:e}, IRF {fwhm:e}, background {bg}, window {window})"
                    );
                }
                if bg > 0.0 {
                    // (its median: a pixel whose charge sits in one tap cannot tell background from decay)
                    let mut v: Vec<f32> = fit.background.iter().copied().collect();
                    v.sort_by(f32::total_cmp);
                    let b = v[v.len() / 2];
                    assert!((b - bg as f32).abs() < 0.005, "background share {b} vs {bg}");
                }
            }
        }
    }

    /// The instrument search keeps its coarse tables for the last matrix and options: another
    /// sensor or other widths in between give each its own instrument, and coming back gives
    /// the first answer again, to the bit.
    #[test]
    fn the_instrument_search_keeps_its_tables_per_sensor_and_options() {
        let a = sensor();
        let other = tcsense_sensor::Sensor::ideal(
            prototype_codes(2).unwrap(),
            Sampling::Heterodyne(8),
            Irf::Physical { laser_fwhm_s: 2.55e-9, tap_tau_s: 0.3e-9 },
        )
        .unwrap()
        .matrix()
        .clone();
        let tau = |_: usize, j: usize| if j < 4 { 0.6e-9 } else { 3.5e-9 };
        let y = taps(&a, 8, 8, &tau, 31.7e-9, 1.0e-9, 0.0);
        let y2 = taps(&other, 8, 8, &tau, 12.3e-9, 0.5e-9, 0.0);
        let opts = TapFitOptions::default();
        let narrow = TapFitOptions { irf_fwhm_s: vec![0.0, 0.5e-9], ..Default::default() };
        let first = estimate_instrument(&y.view(), &a, &opts);
        let o = estimate_instrument(&y2.view(), &other, &opts);
        let n = estimate_instrument(&y2.view(), &other, &narrow);
        let again = estimate_instrument(&y.view(), &a, &opts);
        assert_eq!((first.onset_s.to_bits(), first.irf_fwhm_s.to_bits()), (again.onset_s.to_bits(), again.irf_fwhm_s.to_bits()));
        for (i, t0, fwhm) in [(o, 12.3e-9, 0.5e-9), (n, 12.3e-9, 0.5e-9), (first, 31.7e-9, 1.0e-9)] {
            let dt = (i.onset_s - t0 + 26.35e-9).rem_euclid(52.7e-9) - 26.35e-9;
            assert!(dt.abs() < 0.01e-9 && (i.irf_fwhm_s - fwhm).abs() < 0.1e-9, "{i:?} against onset {t0:e}, IRF {fwhm:e}");
        }
    }

    /// Noise on taps: Poisson-like (Gaussian of the charge's variance) at `photons` per pixel.
    fn noisy(y: &ndarray::Array3<f32>, photons: f64, seed: u64) -> ndarray::Array3<f32> {
        crate::testing::noise(y, photons, seed, false)
    }

    /// Shot noise as a sensor has it: Poisson, by the sensor's noise model (no read noise), the
    /// frame's brightest pixel at `photons` and every other in proportion to its charge.
    fn shot_noise(y: &ndarray::Array3<f32>, photons: f64, seed: u64) -> ndarray::Array3<f32> {
        use tcsense_sensor::noise::{add_noise, Exposure};
        let peak = y.sum_axis(ndarray::Axis(0)).iter().fold(0f32, |a, &b| a.max(b));
        let noise = tcsense_sensor::NoiseParams { full_well_e: 1e12, read_noise_e: 0.0, signal_fraction: 1.0, adc_bits: 0 };
        let out = add_noise(&y.view().into_dyn(), &noise, Exposure::ElectronsPerUnit(photons / peak as f64), seed).unwrap();
        out.in_input_units().into_dimensionality().unwrap()
    }

    /// The refinement around points chosen elsewhere is the fit's own where the choice is the
    /// fit's argmin, and stays within a step of a choice one point off; the evidence puts its
    /// maximum at the fit's argmin, in nats that do not change with the frame's scale.
    #[test]
    fn refinement_around_a_chosen_point_and_the_evidence() {
        let a = sensor();
        let tau = |i: usize, j: usize| 0.5e-9 * (1.0 + 0.4 * ((i / 4) * 2 + j / 4) as f64);
        let inst = Instrument { onset_s: 11.0e-9, irf_fwhm_s: 0.5e-9 };
        let y = noisy(&taps(&a, 8, 8, &tau, inst.onset_s, inst.irf_fwhm_s, 0.0), 2000.0, 5);
        let opts = TapFitOptions::default();
        let templates = LifetimeTemplates::new(&a, inst, &opts);
        let own = templates.fit(&y.view());
        let costs = templates.costs(&y.view());
        let g = templates.points();
        let sums = costs.window_sums();
        let best: Vec<i32> = (0..64).map(|p| if costs.lit[p] { argmin(&sums[p * g..(p + 1) * g]) as i32 } else { -1 }).collect();
        let chosen = templates.refine(&y.view(), &best);
        for (x, y) in own.lifetime.iter().zip(chosen.lifetime.iter()) {
            assert!(x.to_bits() == y.to_bits(), "{x:e} against {y:e}");
        }
        let (_, step) = templates.log_grid();
        let off: Vec<i32> = best.iter().map(|&b| b + 1).collect();
        let moved = templates.refine(&y.view(), &off);
        for (x, y) in own.lifetime.iter().zip(moved.lifetime.iter()).filter(|(x, y)| x.is_finite() && y.is_finite()) {
            assert!(((*y as f64).ln() - (*x as f64).ln()).abs() <= 1.5 * step, "{x:e} against {y:e}");
        }
        let no = templates.refine(&y.view(), &vec![-1; 64]);
        assert!(no.lifetime.iter().all(|v| v.is_nan()));
        // modes a point off the argmin: the mode itself, or refined near it
        // (refine_near_mode): within a point of it, and the fit's lifetime where the fit's own
        // optimum lies within that reach
        let u: Vec<f32> = off.iter().map(|&b| b as f32).collect();
        let plain = templates.refine_modes(&y.view(), &costs, &u);
        let near =
            LifetimeTemplates::new(&a, inst, &TapFitOptions { refine_near_mode: true, ..opts.clone() }).refine_modes(&y.view(), &costs, &u);
        let (l0, _) = templates.log_grid();
        // refined only where the window's cost pins its argmin within REFINE_PRECISION_POINTS
        let nats = 1.0 / (2.0 * crate::evidence::noise_level(&costs.volume(&sums, 4)) as f64);
        let sharp = |p: usize| {
            let (b, t) = (best[p] as usize, &sums[p * g..(p + 1) * g]);
            let k = (t[b - 1] as f64 + t[b + 1] as f64 - 2.0 * t[b] as f64) * nats;
            k > 0.0 && 1.0 / k.sqrt() < REFINE_PRECISION_POINTS
        };
        let (mut n, mut pinned, mut refined, mut at_fit) = (0, 0, 0, 0);
        for p in (0..64).filter(|&p| costs.lit[p] && best[p] > 0 && (best[p] as usize) + 2 < g) {
            let (t0, t1, fit) = (plain[(p / 8, p % 8)] as f64, near[(p / 8, p % 8)] as f64, own.lifetime[(p / 8, p % 8)] as f64);
            assert!((t0.ln() - (l0 + u[p] as f64 * step)).abs() < 1e-5, "the mode itself without refine_near_mode: {t0:e}");
            n += 1;
            assert!((t1.ln() - t0.ln()).abs() <= 1.01 * step, "refined within a point of the mode: {t1:e} against {t0:e}");
            assert_eq!(t1 != t0, sharp(p), "pixel {p}: refined ({t1:e} against the mode {t0:e}) where the window pins it");
            pinned += usize::from(sharp(p));
            refined += usize::from(t1 != t0);
            at_fit += usize::from((t1.ln() - fit.ln()).abs() < 1e-3);
        }
        assert!(
            n >= 50 && pinned >= n - 8 && at_fit >= 20,
            "refined near the mode: {refined} of {n} pixels ({pinned} pinned), {at_fit} at the fit's own lifetime"
        );
        // modes beside the windows' argmins in dim light: the windows pin almost nothing, the
        // modes stand; in bright light every mode is refined
        let near_opts = TapFitOptions { refine_near_mode: true, ..opts.clone() };
        for (photons, least, most) in [(20.0, 0, 8), (1e6, 60, 64)] {
            let frame = noisy(&taps(&a, 8, 8, &tau, inst.onset_s, inst.irf_fwhm_s, 0.0), photons, 5);
            let t = LifetimeTemplates::new(&a, inst, &near_opts);
            let c = t.costs(&frame.view());
            let s = c.window_sums();
            let modes: Vec<f32> = (0..64).map(|p| if c.lit[p] { argmin(&s[p * g..(p + 1) * g]) as f32 + 0.3 } else { f32::NAN }).collect();
            let out = t.refine_modes(&frame.view(), &c, &modes);
            let moved = (0..64)
                .filter(|&p| modes[p].is_finite() && ((out[(p / 8, p % 8)] as f64).ln() - (l0 + modes[p] as f64 * step)).abs() > 1e-5)
                .count();
            assert!((least..=most).contains(&moved), "{photons} photons: {moved} of 64 modes refined, expected {least}–{most}");
        }
        // a dark corner (no charge in rows and columns 0–4): no lifetime where the window holds
        // no lit pixel (rows and columns 0–3), whatever the mode; the mode beside it
        let mut dark = y.clone();
        dark.slice_mut(ndarray::s![.., ..5, ..5]).fill(0.0);
        let dark_costs = templates.costs(&dark.view());
        let modes = templates.refine_modes(&dark.view(), &dark_costs, &u);
        for i in 0..8 {
            for j in 0..8 {
                let t = modes[(i, j)];
                assert_eq!(t.is_nan(), i < 4 && j < 4, "pixel ({i}, {j}): {t:e}");
            }
        }
        // the evidence: 0 nats at the argmin of the window's cost, negative elsewhere; the same
        // for the frame times 7 (the noise level takes the scale)
        let e = evidence::evidence(&costs, &y.sum_axis(Axis(0)), 4, 2);
        assert_eq!(e.features.dim(), (8, 8, evidence::feature_channels(g, 2)));
        for p in (0..64).filter(|&p| costs.lit[p]) {
            let col: Vec<f32> = (0..g).map(|k| e.skip[(p / 8, p % 8, k)]).collect();
            assert_eq!(col[best[p] as usize], 0.0);
            assert!(col.iter().all(|&v| v <= 0.0));
            let posterior: f32 = (0..g / 2).map(|k| e.features[(p / 8, p % 8, k)]).sum();
            assert!((posterior - (g / 2) as f32).abs() < 1e-2, "pooled posterior sums to {posterior}");
        }
        let y7 = y.mapv(|v| 7.0 * v);
        let e7 = evidence::evidence(&templates.costs(&y7.view()), &y7.sum_axis(Axis(0)), 4, 2);
        assert!((e7.noise / e.noise - 7.0).abs() < 1e-3, "noise level {} against {}", e7.noise, e.noise);
        for (a, b) in e.skip.iter().zip(e7.skip.iter()) {
            assert!((a - b).abs() <= 1e-3 * a.abs().max(1.0), "{a} against {b}");
        }
    }

    /// Pooling by likeness: in dim light the pooled fit is below the 3×3 fit's error within a
    /// region of one lifetime (it pools the region), in bright light it keeps the 3×3 fit's
    /// precision over the whole frame, the edge between two lifetimes included (where a
    /// wider window fails); and it validates its side.
    /// Cells of four lifetimes (1–4 ns) in blocks of 8×8 pixels.
    fn cells(i: usize, j: usize) -> f64 {
        [1.0e-9, 2.2e-9, 3.1e-9, 4.0e-9][(i / 8 + 2 * (j / 8)) % 4]
    }

    /// The superpixels' side comes from the photons, whatever the frame's units: bright, every
    /// pixel; in dim light, sides whose superpixels hold about 250 photons, up to 4 blocks (a
    /// frame of 32×32 pixels holds 8 blocks: 4 is the cap); a frame of 8×8 pixels holds 2 blocks
    /// at most.
    #[test]
    fn the_instrument_side_reads_the_photons_whatever_the_units() {
        let a = sensor();
        let side = |y: &ndarray::Array3<f32>| {
            let f = normalise(&y.view(), 0.02);
            instrument_side(&f.r, &f.weight, y.dim(), a.block(), 256)
        };
        let y = taps(&a, 32, 32, &cells, 2e-9, 0.5e-9, 0.0);
        for (photons, want) in [(1e6, 1), (2e4, 1), (60.0, 2), (20.0, 4), (5.0, 4)] {
            let noisy = shot_noise(&y, photons, 3);
            assert_eq!(side(&noisy), want, "{photons} photons");
            assert_eq!(side(&noisy.mapv(|v| v * 1234.5)), want, "{photons} photons in other units");
        }
        let small = shot_noise(&taps(&a, 8, 8, &cells, 2e-9, 0.5e-9, 0.0), 20.0, 3);
        assert_eq!(side(&small), 2);
        assert!(TapFitOptions { instrument_blocks: MAX_INSTRUMENT_BLOCKS + 1, ..Default::default() }.validate().is_err());
    }

    /// A superpixel holds each subpixel type's taps summed over its blocks, normalised; the last
    /// row and column hold what is left of the frame.
    #[test]
    fn superpixels_sum_each_subpixel_types_taps() {
        let a = sensor();
        let y = shot_noise(&taps(&a, 10, 12, &cells, 2e-9, 0.5e-9, 0.02), 300.0, 5);
        let f = normalise(&y.view(), 0.0);
        let (r, weight) = superpixels(&f, y.dim(), (2, 2), 2);
        // 3 × 3 superpixels of 4 types, the last row 2 pixels high
        assert_eq!(weight.len(), 36);
        let total: f64 = weight.iter().map(|&v| v as f64).sum();
        assert!((total - y.iter().map(|&v| v as f64).sum::<f64>()).abs() < 1e-3 * total);
        // superpixel (2, 1) of type 3 (odd row, odd column): pixels (9, 5) and (9, 7)
        let q = (2 * 3 + 1) * 4 + 3;
        let want: Vec<f64> = (0..4).map(|k| (y[(k, 9, 5)] + y[(k, 9, 7)]) as f64).collect();
        let sum: f64 = want.iter().sum();
        assert!((weight[q] as f64 - sum).abs() < 1e-4 * sum, "{} vs {sum}", weight[q]);
        for k in 0..4 {
            assert!((r[q * 4 + k] as f64 - want[k] / sum).abs() < 1e-5, "tap {k}");
        }
    }

    /// In dim light the onset fitted on every pixel alone comes late (each pixel's own lifetime
    /// fits its noise); on superpixels of 4 blocks (across the cells' edges) it comes within a
    /// third of that error, and in bright light the chosen side is every pixel: the same
    /// instrument to the bit.
    #[test]
    fn superpixels_keep_the_onset_in_dim_light() {
        let a = sensor();
        let t0 = 2e-9;
        let y = taps(&a, 32, 32, &|i, j| cells(i + 3, j + 5), t0, 1.5e-9, 0.0);
        let instrument = |y: &ndarray::Array3<f32>, blocks: usize| {
            estimate_instrument(&y.view(), &a, &TapFitOptions { instrument_blocks: blocks, ..Default::default() })
        };
        let error = |i: Instrument| ((i.onset_s - t0 + 26.35e-9).rem_euclid(52.7e-9) - 26.35e-9).abs();
        let (mut alone, mut pooled) = (0.0, 0.0);
        for seed in 0..3 {
            let dim = shot_noise(&y, 100.0, seed);
            alone += error(instrument(&dim, 1)) / 3.0;
            pooled += error(instrument(&dim, 4)) / 3.0;
        }
        assert!(alone > 0.4e-9 && pooled < alone / 3.0, "onset off by {alone:e} s alone, {pooled:e} s on superpixels");
        let bright = shot_noise(&y, 1e5, 7);
        assert_eq!(instrument(&bright, 0), instrument(&bright, 1));
        assert!(error(instrument(&bright, 0)) < 0.1e-9);
    }

    /// In dim light the frame's mixture (the default where the photons ask for superpixels)
    /// keeps the onset on every pixel alone, where their least costs put it late: over three
    /// seeds of a frame of four lifetimes (shot noise, 100 photons in the brightest pixel), each
    /// within 0.25 ns, where the pixels alone read it 0.8 ns late or more. The mixture's
    /// temperature counts: at a tenth of it the onset comes late again.
    #[test]
    fn the_frames_mixture_keeps_the_onset_in_dim_light() {
        let a = sensor();
        let t0 = 2e-9;
        let y = taps(&a, 32, 32, &|i, j| cells(i + 3, j + 5), t0, 0.0, 0.0);
        let instrument = |y: &ndarray::Array3<f32>, blocks: usize| {
            estimate_instrument(&y.view(), &a, &TapFitOptions { instrument_blocks: blocks, ..Default::default() })
        };
        let late = |i: Instrument| (i.onset_s - t0 + 26.35e-9).rem_euclid(52.7e-9) - 26.35e-9;
        for seed in 0..3 {
            let dim = shot_noise(&y, 100.0, seed);
            let (alone, mixture) = (late(instrument(&dim, 1)), late(instrument(&dim, 0)));
            assert!(
                alone > 0.75e-9 && mixture.abs() < 0.25e-9,
                "seed {seed}: onset {mixture:e} s late under the mixture, {alone:e} s alone"
            );
        }
        // the same search at a tenth of the temperature
        let dim = shot_noise(&y, 100.0, 0);
        let f = normalise(&dim.view(), 0.0);
        let bright = brightest_of(&f.weight, 256);
        let (gain, _) = frame_gain(&f.r, &f.weight, dim.dim(), a.block(), &bright).unwrap();
        let c = Cycle::new(a.bins(), a.bin_width_s());
        let opts = TapFitOptions { irf_fwhm_s: vec![0.0], ..Default::default() };
        let subpixel = |p: usize| subpixel_flat(p, 32, a.block());
        let cold = instrument::instrument(&a.a(), c, &opts, &f.r, &f.weight, &bright, 4, &subpixel, Some(0.1 * gain / 4.0));
        assert!(late(Instrument { onset_s: cold.0, irf_fwhm_s: cold.1 }) > 0.35e-9, "onset {:e} at a tenth of the temperature", cold.0);
    }

    #[test]
    fn pooling_by_likeness_pools_dim_regions_and_keeps_bright_edges() {
        let a = sensor();
        let (h, w) = (24, 36);
        let tau = |_: usize, j: usize| if j < 18 { 1.0e-9 } else { 3.0e-9 };
        let inst = Instrument { onset_s: 7.0e-9, irf_fwhm_s: 0.0 };
        let clean = taps(&a, h, w, &tau, inst.onset_s, inst.irf_fwhm_s, 0.0);
        // the MAE over columns `cols`
        let mae = |fit: &TapFit, cols: std::ops::Range<usize>| {
            let (mut sum, mut n) = (0.0, 0usize);
            for ((i, j), &v) in fit.lifetime.indexed_iter() {
                if v.is_finite() && cols.contains(&j) {
                    sum += (v as f64 - tau(i, j)).abs();
                    n += 1;
                }
            }
            assert!(n >= h * cols.len() * 9 / 10, "{n} of {} pixels with a lifetime", h * cols.len());
            sum / n as f64
        };
        let fit = |side: usize, pool_like: usize, y: &ndarray::Array3<f32>| {
            LifetimeTemplates::new(&a, inst, &TapFitOptions { window: side, pool_like, ..Default::default() }).fit(&y.view())
        };
        for (photons, seed) in [(20.0, 3), (60.0, 4)] {
            let dim = noisy(&clean, photons, seed);
            let (p, q) = (mae(&fit(3, 0, &dim), 0..10), mae(&fit(3, 15, &dim), 0..10));
            assert!(q < 0.9 * p, "{photons} photons: pooled {q:e} against the 3×3 fit's {p:e}");
        }
        let bright = noisy(&clean, 1e4, 5);
        let (p, q, wide) = (mae(&fit(3, 0, &bright), 0..w), mae(&fit(3, 15, &bright), 0..w), mae(&fit(9, 0, &bright), 0..w));
        assert!(q < 1.1 * p + 0.005e-9, "bright: pooled {q:e} against the 3×3 fit's {p:e}");
        assert!(wide > 1.5 * p, "bright: the 9×9 window {wide:e} against the 3×3 fit's {p:e}");
        for bad in [3, 4, 11, 18, 1001] {
            assert!(TapFitOptions { pool_like: bad, ..Default::default() }.validate().is_err(), "{bad}");
        }
    }

    /// The dense fit (grid, box filter, argmin, parabola at half steps) gives the reference's
    /// continuous minimum (golden sections on interpolated templates) to 0.01 ns, on noisy taps
    /// where the two converge.
    #[test]
    fn the_dense_fit_equals_the_golden_section_fit() {
        let a = sensor();
        let tau = |i: usize, j: usize| 0.4e-9 * (1.0 + 0.35 * (i * 16 + j) as f64 / 16.0);
        let inst = Instrument { onset_s: 7.3e-9, irf_fwhm_s: 0.5e-9 };
        let clean = taps(&a, 16, 16, &tau, inst.onset_s, inst.irf_fwhm_s, 0.02);
        let y = noisy(&clean, 3000.0, 3);
        for background in [true, false] {
            let opts = TapFitOptions { background, ..Default::default() };
            let fast = LifetimeTemplates::new(&a, inst, &opts).fit(&y.view());
            let slow = fit_taps_reference(&y.view(), &a, &opts, inst);
            let mut worst = 0f64;
            let mut both = 0;
            for (f, s) in fast.lifetime.iter().zip(slow.iter()) {
                assert_eq!(f.is_finite(), s.is_finite(), "one fit on a bound, not the other: {f:e} {s:e}");
                if f.is_finite() {
                    worst = worst.max((*f as f64 - *s as f64).abs());
                    both += 1;
                }
            }
            assert!(both > 200, "{both} pixels fitted");
            assert!(worst < 0.01e-9, "the dense fit differs from the reference by {worst:e} s (background {background})");
            // and they are estimates: within 20 % of the truth on average (0.4–2.4 ns through a
            // 2.55 ns laser pulse, 3 000 photons a pixel)
            let mae: f64 = fast.lifetime.indexed_iter().map(|((i, j), &v)| (v as f64 - tau(i, j)).abs() / tau(i, j)).sum::<f64>() / 256.0;
            assert!(mae < 0.2, "relative error {mae}");
        }
    }

    /// A lifetime beyond the range searched is not placed on the bound: the pixel gets NaN
    /// (and the decoder a confidence of 0), while the pixels inside the range keep theirs.
    #[test]
    fn a_lifetime_beyond_the_range_searched_is_nan() {
        let a = sensor();
        // (a decay far longer than the cycle is nearly flat: with a background fitted it would
        // be a background, so none here)
        let tau = |_: usize, j: usize| match j {
            0..4 => 2e-9,
            4..6 => 0.1e-9,
            _ => 40e-9,
        };
        let inst = Instrument { onset_s: 3e-9, irf_fwhm_s: 0.0 };
        let y = taps(&a, 8, 8, &tau, inst.onset_s, inst.irf_fwhm_s, 0.0);
        let opts = TapFitOptions { window: 1, tau_range_s: [0.5e-9, 10e-9], background: false, ..Default::default() };
        let fit = LifetimeTemplates::new(&a, inst, &opts).fit(&y.view());
        for ((i, j), &v) in fit.lifetime.indexed_iter() {
            if j < 4 {
                assert!((v as f64 - 2e-9).abs() < 0.02e-9, "({i}, {j}): {v:e}");
            } else {
                assert!(v.is_nan(), "({i}, {j}): {v:e} for a decay of {:e} s searched over 0.5–10 ns", tau(i, j));
            }
        }
    }
}
