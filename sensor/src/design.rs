//! Code design by identifiability ([`crate::identify`]): score code sets by what the taps can
//! tell apart, pick the best of many random candidates, and improve it by a local search whose
//! every move keeps the hardware constraints exact.
//!
//! - [`Criterion::Range`] (LiDAR): the range alias must reach the threshold (default 0.5);
//!   above it, the smaller the worst single-return range bound over the cycle, the better.
//! - [`Criterion::Lifetime`] (FLIm): the lifetime alias (two decays whose onsets are two masks
//!   or more apart) and the range alias must reach the threshold; above it, the smaller the
//!   worst relative lifetime bound `σ(τ_f)/τ_f` over 0.2–8 ns and the onsets of the cycle, the
//!   better.
//!
//! Both are closed-form: a candidate's `A` comes from its bits through the sensor's code basis
//! (`A[n][m] = Σ_l g[n][m][l]·G[l]`, [`MeasurementMatrix::code_basis`]), so thousands of
//! candidates score in seconds.
//!
//! The local search starts from the best candidate. A move sets one subpixel's tap (or the
//! drain) over a few consecutive masks — with the tap constraint — or one channel's bits over a
//! few masks without it; a move that breaks any declared constraint is refused (the checker of
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

use crate::codes::Codes;
use crate::identify::{self, Columns, Light};
use crate::matrix::MeasurementMatrix;
use crate::params::SensorSpec;
use rand::rngs::StdRng;
use rand::{RngExt, SeedableRng};
use serde::Serialize;

/// Delays per bin of the range bound during design.
const RANGE_PER_BIN: usize = 2;
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
    /// The alias the threshold applies to (the smaller of range and lifetime alias for
    /// [`Criterion::Lifetime`]).
    pub alias: f64,
    /// The worst bound over the cycle: bins (range) or `σ(τ_f)/τ_f` (lifetime).
    pub worst: f64,
    /// The mean of the same bound.
    pub mean: f64,
    /// Higher is better: `−worst` at or above the alias threshold, `alias − 1000` below.
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
        let (alias, worst, mean) = match self.criterion {
            Criterion::Range => {
                let r = identify::range_bound_weighted(&cols, &self.light, RANGE_PER_BIN, &weights);
                (range_alias, r.worst_bins, r.mean_bins)
            }
            Criterion::Lifetime => {
                let la = identify::lifetime_alias(&cols, &self.taus, DESIGN_ONSETS).distance;
                let pts = identify::lifetime_bound(&cols, &self.light, &self.taus, DESIGN_ONSETS, &weights);
                let worst = pts.iter().map(|p| p.known_worst_s / p.tau_s).fold(0.0, f64::max);
                let mean = pts.iter().map(|p| p.known_mean_s / p.tau_s).sum::<f64>() / pts.len() as f64;
                (range_alias.min(la), worst, mean)
            }
        };
        let value = if alias >= self.threshold && worst.is_finite() { -worst } else { alias - INFEASIBLE };
        Score { alias, worst, mean, value }
    }
}

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
/// moves with the best so far; `cancel` stops it early (the best so far is returned).
pub fn search(obj: &Objective, start: Codes, opts: &SearchOptions, on_step: &mut dyn FnMut(&Score), cancel: &dyn Fn() -> bool) -> SearchResult {
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
        tried += 1;
        let mut cand = best.clone();
        let l0 = rng.random_range(0..len);
        let w = rng.random_range(1..=MAX_MOVE_MASKS.min(len));
        if tap {
            // one subpixel's tap (M: the drain) over masks l0..l0+w
            let n = rng.random_range(0..n_sub);
            let choices = taps + usize::from(best.drain());
            let q = rng.random_range(0..choices);
            for d in 0..w {
                let l = (l0 + d) % len;
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
        if it % 100 == 99 {
            on_step(&score);
        }
    }
    SearchResult { codes: best, score, tried, infeasible, kept }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{generate, Irf, Sampling, SensorParams};

    fn spec(sampling: Sampling) -> SensorSpec {
        let codes = generate::prototype_codes(1).unwrap();
        SensorParams { irf: Irf::Physical { laser_fwhm_s: 2.55e-9, tap_tau_s: 0.3e-9 }, sampling, ..SensorParams::from_codes(&codes) }.validate().unwrap()
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
