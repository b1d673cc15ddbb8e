//! Code design by identifiability ([`crate::identify`]): score code sets by what the taps can
//! tell apart, pick the best of many random candidates, and improve it by a local search whose
//! every move keeps the hardware constraints exact.
//!
//! - [`Criterion::Range`] (LiDAR): the range alias must reach the threshold (default 0.5);
//!   above it, the smaller the worst single-return range bound over the cycle, the better.
//! - [`Criterion::Lifetime`] (FLIm): the range alias (returns two masks or more apart: what
//!   places the frame's onset) must reach the threshold; above it, the smaller the worst
//!   relative lifetime bound `σ(τ_f)/τ_f` (onset known: the onset is the instrument's, one per
//!   frame) over 0.2–8 ns and the onsets of the cycle, the better. The lifetime alias (two
//!   decays whose onsets are two masks or more apart) is reported, not required: it is the
//!   ambiguity of a pixel that fits its own onset, and with the IRF's 2.55 ns pulse it stays
//!   near 0.3 under the prototype's constraints (the best of 4 000 candidates and 40 000 moves
//!   reached 0.33).
//!
//! Both are closed-form: a candidate's `A` comes from its bits through the sensor's code basis
//! (`A[n][m] = Σ_l g[n][m][l]·G[l]`, [`MeasurementMatrix::code_basis`]), so thousands of
//! candidates score in seconds.
//!
//! The local search starts from the best candidates. With the tap constraint a move changes one
//! subpixel: its tap (or the drain) over a few consecutive masks, or its whole sequence shifted
//! by a mask (exchanging two taps' roles would be pointless: every measure is invariant to it); without it, a move sets one channel's bits over a few masks; a move that breaks any declared constraint is refused (the checker of
//! [`Codes::violations`] decides), so every visited set is feasible. A move is kept when the
//! score does not fall (sideways moves let the search cross plateaus of the worst case).
//!
//! ```
//! use tcsense_sensor::design::{Criterion, Objective, search, SearchOptions};
//! use tcsense_sensor::{generate, identify::Light, SensorParams, Irf};
//! let codes = generate::prototype_codes(1).unwrap();
//! let spec = SensorParams { irf: Irf::Ideal, ..SensorParams::from_codes(&codes) }.validate().unwrap();
//! let obj = Objective::new(Criterion::Range, &spec, Light::default(), 0.5);
//! let before = obj.score(&codes);
//! let out = search(&obj, codes, &SearchOptions { iterations: 200, seed: 3 }, &mut |_| {}, &|| false);
//! assert!(out.codes.violations().is_empty());
//! assert!(out.score.value >= before.value);
//! ```

use crate::codes::{CodeShape, Codes, Constraints};
use crate::error::{Result, SensorError};
use crate::generate::random_codes;
use crate::identify::{self, Columns, Light};
use crate::matrix::MeasurementMatrix;
use crate::params::SensorSpec;
use rand::rngs::StdRng;
use rand::{RngExt, SeedableRng};
use rayon::prelude::*;
use serde::Serialize;
use std::sync::atomic::{AtomicBool, Ordering};

/// Delays per bin of the range bound during design (as `codes analyze` reports it).
const RANGE_PER_BIN: usize = 4;
/// Lifetimes (0.2–8 ns) and onsets over the cycle the lifetime criterion evaluates.
const DESIGN_LIFETIMES: usize = 6;
const DESIGN_ONSETS: usize = 16;
/// Scores below the alias threshold sit this far below every score above it.
const INFEASIBLE: f64 = 1e3;
/// Longest run of masks one move sets.
const MAX_MOVE_MASKS: usize = 4;

/// What a code set is designed for.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Criterion {
    /// Single returns: no alias, the smallest worst-case range bound.
    Range,
    /// Fluorescence decays: no alias (range nor lifetime), the smallest worst-case relative
    /// lifetime bound.
    Lifetime,
}

impl Criterion {
    /// The name on the command line.
    pub fn name(self) -> &'static str {
        match self {
            Criterion::Range => "range",
            Criterion::Lifetime => "lifetime",
        }
    }
}

/// A code set's score under a criterion.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Score {
    /// The range alias, which the threshold applies to.
    pub alias: f64,
    /// The lifetime alias ([`Criterion::Lifetime`] only; NaN otherwise).
    pub lifetime_alias: f64,
    /// The worst bound over the cycle: bins (range) or `σ(τ_f)/τ_f` (lifetime).
    pub worst: f64,
    /// The mean of the same bound.
    pub mean: f64,
    /// Higher is better: `−‖bound‖₈` (a soft worst case, [`soft_max`]) at or above the alias
    /// threshold, `alias − 1000` below.
    pub value: f64,
}

/// A criterion with everything it needs precomputed for one sensor.
#[derive(Debug, Clone)]
pub struct Objective {
    criterion: Criterion,
    light: Light,
    threshold: f64,
    /// Code basis `G [L, T]`, row-major.
    basis: Vec<f64>,
    len: usize,
    t: usize,
    k: usize,
    bin_width_s: f64,
    taus: Vec<f64>,
}

impl Objective {
    /// The objective of `criterion` on the sensor `spec` (IRF and sampling), at `light`, with
    /// aliases below `threshold` ranked below every set above it.
    pub fn new(criterion: Criterion, spec: &SensorSpec, light: Light, threshold: f64) -> Objective {
        let g = MeasurementMatrix::code_basis(spec);
        let (len, t) = g.dim();
        Objective {
            criterion,
            light,
            threshold,
            basis: g.iter().map(|&v| v as f64).collect(),
            len,
            t,
            k: spec.sampling().k(),
            bin_width_s: spec.bin_width_s(),
            taus: identify::lifetime_grid(DESIGN_LIFETIMES),
        }
    }

    /// The criterion.
    pub fn criterion(&self) -> Criterion {
        self.criterion
    }

    /// `A` of `codes` through the code basis.
    pub fn columns(&self, codes: &Codes) -> Columns {
        let (n, m, t) = (codes.subpixels(), codes.taps(), self.t);
        let mut a = vec![0.0; n * m * t];
        for c in 0..n * m {
            let row = &mut a[c * t..(c + 1) * t];
            for (l, &bit) in codes.channel(c).iter().enumerate().take(self.len) {
                if bit != 0 {
                    for (r, g) in row.iter_mut().zip(&self.basis[l * t..(l + 1) * t]) {
                        *r += g;
                    }
                }
            }
        }
        Columns::from_values(a, n, m, t, self.k, self.bin_width_s)
    }

    /// Score a code set (its shape must match the sensor's).
    pub fn score(&self, codes: &Codes) -> Score {
        let cols = self.columns(codes);
        let weights = vec![1.0; codes.subpixels()];
        let range_alias = identify::range_alias(&cols).distance;
        let alias = range_alias;
        let (lifetime_alias, worst, mean, soft) = match self.criterion {
            Criterion::Range => {
                let r = identify::range_bound_weighted(&cols, &self.light, RANGE_PER_BIN, &weights);
                (f64::NAN, r.worst_bins, r.mean_bins, soft_max(&r.sigma_bins))
            }
            Criterion::Lifetime => {
                if alias < self.threshold {
                    // below the threshold only the alias ranks: skip the pairwise lifetime alias
                    (f64::NAN, f64::INFINITY, f64::INFINITY, f64::INFINITY)
                } else {
                    let pts = identify::lifetime_bound(&cols, &self.light, &self.taus, DESIGN_ONSETS, &weights);
                    let la = identify::lifetime_alias(&cols, &self.taus, DESIGN_ONSETS).distance;
                    let worst = pts.iter().map(|p| p.known_worst_s / p.tau_s).fold(0.0, f64::max);
                    let mean = pts.iter().map(|p| p.known_mean_s / p.tau_s).sum::<f64>() / pts.len() as f64;
                    let rel: Vec<f64> = pts.iter().map(|p| p.known_worst_s / p.tau_s).collect();
                    (la, worst, mean, soft_max(&rel))
                }
            }
        };
        let value = if alias >= self.threshold && soft.is_finite() { -soft } else { alias - INFEASIBLE };
        Score { alias, lifetime_alias, worst, mean, value }
    }
}

/// The power mean of order [`SOFT_MAX_ORDER`]: within `n^(1/8)` (1.8 for 128 delays) of the
/// maximum, but every value counts, so a local move that lowers the bound where it is not yet
/// the worst is seen (the plain maximum leaves the search on plateaus).
pub fn soft_max(v: &[f64]) -> f64 {
    let top = v.iter().copied().fold(0.0f64, f64::max);
    if !(top.is_finite() && top > 0.0) {
        return top;
    }
    let mean = v.iter().map(|x| (x / top).powi(SOFT_MAX_ORDER)).sum::<f64>() / v.len() as f64;
    top * mean.powf(1.0 / SOFT_MAX_ORDER as f64)
}

/// Order of [`soft_max`].
const SOFT_MAX_ORDER: i32 = 8;

/// Settings of [`search`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SearchOptions {
    /// Moves tried.
    pub iterations: usize,
    /// Seed of the moves.
    pub seed: u64,
}

/// What [`search`] found.
#[derive(Debug, Clone)]
pub struct SearchResult {
    pub codes: Codes,
    pub score: Score,
    /// Moves tried, moves refused by the constraints, moves kept.
    pub tried: usize,
    pub infeasible: usize,
    pub kept: usize,
}

/// Local search from `start` (feasible) for the highest score; `on_step` is called every 100
/// moves tried with the best so far; `cancel` stops it early (the best so far is returned).
pub fn search(
    obj: &Objective,
    start: Codes,
    opts: &SearchOptions,
    on_step: &mut dyn FnMut(&Score),
    cancel: &dyn Fn() -> bool,
) -> SearchResult {
    let mut rng = StdRng::seed_from_u64(opts.seed);
    let mut best = start;
    let mut score = obj.score(&best);
    let (mut infeasible, mut kept, mut tried) = (0, 0, 0);
    let (n_sub, taps, len) = (best.subpixels(), best.taps(), best.length());
    let tap = best.constraints.tap;
    for it in 0..opts.iterations {
        if cancel() {
            break;
        }
        if it % 100 == 99 {
            on_step(&score);
        }
        tried += 1;
        let mut cand = best.clone();
        let l0 = rng.random_range(0..len);
        let w = rng.random_range(1..=MAX_MOVE_MASKS.min(len));
        if tap {
            let n = rng.random_range(0..n_sub);
            let choices = taps + usize::from(best.drain());
            // the subpixel's state (tap, or `taps` for the drain) at every mask
            let state: Vec<usize> = (0..len).map(|l| (0..taps).find(|&m| best.get(n, m, l)).unwrap_or(taps)).collect();
            let mut next = state.clone();
            if rng.random_bool(0.75) {
                // one tap (or the drain) over masks l0..l0+w
                let q = rng.random_range(0..choices);
                for d in 0..w {
                    next[(l0 + d) % len] = q;
                }
            } else {
                // the whole sequence one mask earlier or later (moves its switches)
                let k = if rng.random_bool(0.5) { 1 } else { len - 1 };
                for (l, v) in next.iter_mut().enumerate() {
                    *v = state[(l + k) % len];
                }
            }
            for (l, &q) in next.iter().enumerate() {
                for m in 0..taps {
                    cand.set(n, m, l, m == q);
                }
            }
        } else {
            let c = rng.random_range(0..n_sub * taps);
            let on = rng.random_bool(0.5);
            for d in 0..w {
                cand.set(c / taps, c % taps, (l0 + d) % len, on);
            }
        }
        if cand == best {
            continue;
        }
        if !cand.violations().is_empty() {
            infeasible += 1;
            continue;
        }
        let s = obj.score(&cand);
        if s.value >= score.value {
            best = cand;
            score = s;
            kept += 1;
        }
    }
    SearchResult { codes: best, score, tried, infeasible, kept }
}

/// Settings of [`design`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DesignOptions {
    /// Random candidates scored (seeds `seed, seed + 1, …`).
    pub candidates: usize,
    /// Local searches, from the best candidates, and moves of each.
    pub starts: usize,
    pub moves: usize,
    /// First candidate seed; the searches' moves are seeded from it too.
    pub seed: u64,
}

impl Default for DesignOptions {
    /// 20 000 candidates, 8 searches of 50 000 moves: about 6 s for the prototype's LiDAR codes
    /// and 40 s for its FLIm codes (`Criterion::Lifetime`, heterodyne K = 8) on two cores.
    fn default() -> Self {
        DesignOptions { candidates: 20_000, starts: 8, moves: 50_000, seed: 0 }
    }
}

/// What [`design`] did: the codes, and the steps that led to them.
#[derive(Debug, Clone)]
pub struct Designed {
    pub codes: Codes,
    pub score: Score,
    /// The best random candidate: its seed and score; the median alias of all candidates.
    pub best_candidate: (u64, Score),
    pub median_alias: f64,
    /// Every local search: the seed of the candidate it started from, and what it found.
    pub searches: Vec<(u64, SearchResult)>,
    /// The seed of the candidate whose search won.
    pub start_seed: u64,
}

/// Where [`design`] reports its progress (candidates scored, moves tried).
pub trait DesignProgress: Sync {
    fn candidates(&self, _done: usize, _of: usize) {}
    fn moves(&self, _done: usize, _score: &Score) {}
}

/// The most random candidates a design scores (each is held with its score until ranked).
pub const MAX_CANDIDATES: usize = 1_000_000;
/// The most moves of one local search.
pub const MAX_MOVES: usize = 100_000_000;

/// No progress reports.
pub struct Quiet;
impl DesignProgress for Quiet {}

/// Code design by `obj`: the best of `opts.candidates` random code sets of `shape` under
/// `constraints` (each a pure function of its seed, scored in parallel), then a local search
/// from each of the `opts.starts` best, in parallel; the best end wins (ties: the earlier
/// candidate). Same options, same codes, whatever the thread count. `cancel` is polled between
/// chunks of candidates and moves; a cancelled design returns [`SensorError::Cancelled`].
pub fn design(
    obj: &Objective,
    shape: CodeShape,
    clock_hz: f64,
    constraints: Constraints,
    opts: &DesignOptions,
    progress: &dyn DesignProgress,
    cancel: &AtomicBool,
) -> Result<Designed> {
    if opts.candidates == 0 || opts.starts == 0 {
        return Err(crate::error::invalid("candidates", opts.candidates.min(opts.starts), "at least one candidate and one search"));
    }
    if opts.candidates > MAX_CANDIDATES || opts.starts > MAX_CANDIDATES || opts.moves > MAX_MOVES {
        return Err(crate::error::invalid(
            "candidates",
            format!("{} candidates, {} searches of {} moves", opts.candidates, opts.starts, opts.moves),
            format!("at most {MAX_CANDIDATES} candidates and searches, at most {MAX_MOVES} moves each"),
        ));
    }
    let seeds: Vec<u64> = (0..opts.candidates as u64).map(|i| opts.seed.wrapping_add(i)).collect();
    let mut scored: Vec<(u64, Score)> = Vec::with_capacity(seeds.len());
    for chunk in seeds.chunks(CHUNK) {
        if cancel.load(Ordering::SeqCst) {
            return Err(SensorError::Cancelled);
        }
        let part: Vec<Result<(u64, Score)>> =
            chunk.par_iter().map(|&s| Ok((s, obj.score(&random_codes(shape, clock_hz, constraints, s)?)))).collect();
        for r in part {
            scored.push(r?);
        }
        progress.candidates(scored.len(), seeds.len());
    }
    let mut aliases: Vec<f64> = scored.iter().map(|x| x.1.alias).collect();
    aliases.sort_by(f64::total_cmp);
    let median_alias = aliases[aliases.len() / 2];
    scored.sort_by(|x, y| y.1.value.total_cmp(&x.1.value).then(x.0.cmp(&y.0)));
    let best_candidate = scored[0];
    let starts: Vec<u64> = scored.iter().take(opts.starts).map(|x| x.0).collect();
    let ends: Vec<Result<(u64, SearchResult)>> = starts
        .par_iter()
        .enumerate()
        .map(|(i, &s)| {
            let start = random_codes(shape, clock_hz, constraints, s)?;
            let out = search(
                obj,
                start,
                &SearchOptions { iterations: opts.moves, seed: opts.seed.wrapping_add(i as u64) },
                &mut |sc| progress.moves(100, sc),
                &|| cancel.load(Ordering::SeqCst),
            );
            Ok((s, out))
        })
        .collect();
    if cancel.load(Ordering::SeqCst) {
        return Err(SensorError::Cancelled);
    }
    let searches = ends.into_iter().collect::<Result<Vec<_>>>()?;
    let mut win = 0;
    for (i, (_, out)) in searches.iter().enumerate() {
        if out.score.value > searches[win].1.score.value {
            win = i;
        }
    }
    let (start_seed, best) = (searches[win].0, searches[win].1.clone());
    let mut codes = best.codes;
    codes.ensure_feasible()?;
    codes.provenance = serde_json::json!({
        "method": "design",
        "criterion": obj.criterion().name(),
        "candidates": opts.candidates,
        "first_seed": opts.seed,
        "best_candidate_seed": best_candidate.0,
        "search_starts": starts.len(),
        "search_moves": opts.moves,
        "search_start_seed": start_seed,
        "light": obj.light,
        "alias_threshold": obj.threshold,
        "score": best.score,
    });
    Ok(Designed { codes, score: best.score, best_candidate, median_alias, searches, start_seed })
}

/// Candidates scored between two looks at the cancel flag.
const CHUNK: usize = 256;

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{generate, Irf, Sampling, SensorParams};

    fn spec(sampling: Sampling) -> SensorSpec {
        let codes = generate::prototype_codes(1).unwrap();
        SensorParams { irf: Irf::Physical { laser_fwhm_s: 2.55e-9, tap_tau_s: 0.3e-9 }, sampling, ..SensorParams::from_codes(&codes) }
            .validate()
            .unwrap()
    }

    /// The code basis gives the synthesised matrix, so the design scores what `analyze` reports.
    #[test]
    fn basis_columns_match_the_synthesised_matrix() {
        for sampling in [Sampling::Oversample(1), Sampling::Heterodyne(4)] {
            let sp = spec(sampling);
            let codes = generate::prototype_codes(5).unwrap();
            let obj = Objective::new(Criterion::Range, &sp, Light::default(), 0.5);
            let a = MeasurementMatrix::synthesize(&codes, &sp).unwrap();
            let direct = identify::range_alias(&Columns::new(&a, sampling.k()));
            let through = identify::range_alias(&obj.columns(&codes));
            assert!((direct.distance - through.distance).abs() < 1e-5, "{direct:?} {through:?}");
        }
    }

    #[test]
    fn search_keeps_constraints_and_lifts_the_seed_one_alias() {
        let sp = spec(Sampling::Oversample(1));
        let start = generate::prototype_codes(1).unwrap();
        let obj = Objective::new(Criterion::Range, &sp, Light::default(), 0.5);
        let before = obj.score(&start);
        assert!(before.alias < 0.05, "the zoo's prototype codes alias: {before:?}");
        let out = search(&obj, start, &SearchOptions { iterations: 3000, seed: 1 }, &mut |_| {}, &|| false);
        assert!(out.codes.violations().is_empty());
        assert!(out.score.alias >= 0.5, "{:?}", out.score);
        assert!(out.infeasible > 0 && out.kept > 0);
    }
}
