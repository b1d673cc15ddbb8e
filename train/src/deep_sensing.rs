//! Deep sensing: exposure codes learned jointly with the decoder (the paper's §III-B-2,
//! DESIGN §6), then projected exactly onto the hardware constraints.
//!
//! Schedule (`tcsense train … --learn-codes`):
//! 1. *relaxed* (`relaxed_epochs`, in `RUN/relaxed/`, itself a run directory): code logits
//!    `θ` ([`CodeLogits`]) and the decoder train together. Each step the measurements are
//!    simulated exactly by the sensor crate with the hard (argmax) codes of `θ` — noise,
//!    clipping and quantisation included — and carry the gradient of `A(θ)·x` with the
//!    straight-through relaxed bits (`y = y_sensor + A(θ)x − stop(A(θ)x)`). The decoder's
//!    own operators (`Aᵀ`, the back-projection, the data-consistency solve) are built on
//!    `A(θ)` too ([`tcsense_models::SensorTensors::with_matrix`]: equal in value to the hard
//!    codes' operators, differentiable in `A`), so the gradient sees what a code change does
//!    to the measurements and to the decoder. This phase runs on burn's block-layout ops; the
//!    fused kernels serve the fine-tuning.
//!    The temperature falls geometrically from `tau_start` to `tau_end`, and the Hamming and
//!    window penalties rise linearly from 0 to `penalty_weight`. `RUN/relaxed/codes_log.csv`
//!    logs per epoch how far the hard codes are from feasible.
//! 2. *projection*: [`tcsense_sensor::project::project`] of `θ` onto the constraints,
//!    pulled towards the start codes by the least amount that keeps the range alias at the
//!    threshold where the plain projection would not ([`project_identifiable`])
//!    (`RUN/relaxed/projection.json`: solver, score, what the projection changed, the pull and
//!    the codes' range alias).
//! 3. *fine-tuning* (`epochs − relaxed_epochs`, in `RUN/`): the decoder, from the relaxed
//!    phase's weights, on the projected codes, which become `RUN/codes.json` (provenance
//!    `learned`).

use burn::module::{Module, ParamId};
use burn::optim::{AdamConfig, GradientsParams, ModuleOptimizer};
use burn::tensor::{Device, Tensor};
use ndarray::Array4;
use serde::{Deserialize, Serialize};
use std::path::Path;
use tcsense_models::learned_codes::{
    alias_penalty, basis_tensor, forward, hamming_penalty, hard_codes, matrix, window_penalty, CodeLogits, CodeRelaxation,
};
use tcsense_models::net::to_tensor;
use tcsense_models::runs::RunSpec;
use tcsense_sensor::Sensor;
use tcsense_sensor::{Codes, Constraints, MeasurementMatrix};

use crate::{file_err, Result, TrainError};

/// The settings of deep sensing (saved in the run's `config.json` as `learn_codes`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LearnCodes {
    /// The constraints the learned codes must meet exactly.
    pub constraints: Constraints,
    /// Epochs of joint training on relaxed codes; the rest of `epochs` fine-tune the decoder.
    pub relaxed_epochs: usize,
    /// Softmax (sigmoid) temperature at the first and the last relaxed step.
    pub tau_start: f64,
    pub tau_end: f64,
    /// Adam learning rate of the logits.
    pub codes_lr: f64,
    /// Weight of the Hamming + window penalties at the end of the relaxed phase.
    pub penalty_weight: f64,
    /// Initial logits: ±margin around the starting codes.
    pub init_margin: f32,
    /// Weight of the identifiability term ([`alias_penalty`]) throughout the relaxed phase; 0
    /// (the runs written before it) leaves it out.
    #[serde(default)]
    pub alias_weight: f64,
    /// The alias distance below which a pair of ranges is pushed apart.
    #[serde(default = "default_alias_threshold")]
    pub alias_threshold: f64,
}

fn default_alias_threshold() -> f64 {
    tcsense_sensor::identify::DEFAULT_ALIAS_THRESHOLD
}

/// Default weight of the identifiability term of new runs.
pub const DEFAULT_ALIAS_WEIGHT: f64 = 1.0;

impl LearnCodes {
    /// One line for people, for a run of `epochs` in all.
    pub fn summary(&self, epochs: usize) -> String {
        format!(
            "learning the codes: {} relaxed epochs (τ {} → {}, codes lr {}, penalty weight {}, alias weight {} at {}), then {} epochs on the codes projected onto {}",
            self.relaxed_epochs,
            self.tau_start,
            self.tau_end,
            self.codes_lr,
            self.penalty_weight,
            self.alias_weight,
            self.alias_threshold,
            epochs.saturating_sub(self.relaxed_epochs),
            self.constraints.label()
        )
    }

    /// Defaults for `epochs` in all: two thirds relaxed.
    pub fn new(constraints: Constraints, epochs: usize) -> Self {
        LearnCodes {
            constraints,
            relaxed_epochs: (2 * epochs).div_ceil(3).max(1),
            tau_start: 1.0,
            tau_end: 0.1,
            codes_lr: 5e-2,
            penalty_weight: 1e-2,
            init_margin: 0.1,
            alias_weight: DEFAULT_ALIAS_WEIGHT,
            alias_threshold: default_alias_threshold(),
        }
    }

    pub fn validate(&self, epochs: usize) -> Result<()> {
        let bad =
            |field: &'static str, got: String, expected: &str| Err(TrainError::InvalidParam { field, got, expected: expected.into() });
        if self.relaxed_epochs == 0 || self.relaxed_epochs > epochs {
            return bad("learn_codes.relaxed_epochs", self.relaxed_epochs.to_string(), "1 to the run's epochs");
        }
        if !(self.tau_start > 0.0 && self.tau_end > 0.0 && self.tau_start.is_finite() && self.tau_end.is_finite()) {
            return bad("learn_codes.tau", format!("{} → {}", self.tau_start, self.tau_end), "positive temperatures");
        }
        if !(self.codes_lr > 0.0 && self.codes_lr.is_finite()) {
            return bad("learn_codes.codes_lr", self.codes_lr.to_string(), "a positive learning rate");
        }
        if !(self.penalty_weight >= 0.0 && self.penalty_weight.is_finite() && self.init_margin.is_finite()) {
            return bad("learn_codes.penalty_weight", self.penalty_weight.to_string(), "a non-negative weight and a finite margin");
        }
        if !(self.alias_weight >= 0.0 && self.alias_weight.is_finite()) {
            return bad("learn_codes.alias_weight", self.alias_weight.to_string(), "a non-negative weight (0: no identifiability term)");
        }
        if !(self.alias_threshold >= 0.0 && self.alias_threshold <= 2f64.sqrt()) {
            return bad(
                "learn_codes.alias_threshold",
                self.alias_threshold.to_string(),
                "a distance in [0, 1.414] between unit signatures",
            );
        }
        Ok(())
    }
}

/// The logits' parameter id: fixed, so same seed, same bytes (the network's are 1, 2, …).
const LOGITS_ID: u64 = 1 << 40;
/// Files of the code learner inside a checkpoint.
pub(crate) const LOGITS_FILE: &str = "code_logits";
pub(crate) const CODE_OPTIM_FILE: &str = "code_optim";

/// The code side of a relaxed run: logits, their optimiser, the basis and the current hard
/// codes.
pub(crate) struct Learner {
    pub lc: LearnCodes,
    relax: CodeRelaxation,
    pub logits: CodeLogits,
    optim: ModuleOptimizer,
    basis: Tensor<2>,
    block: (usize, usize),
    /// Bins two returns must be apart to count as an alias (two masks).
    min_shift: usize,
    /// The hard codes of the logits (no constraints declared).
    pub hard: Codes,
    pub tau: f64,
    pub weight: f64,
}

impl Learner {
    /// Logits at `start` (± the margin) on `device` (an autodiff device).
    pub fn new(lc: &LearnCodes, start: &Codes, spec: &RunSpec, device: &Device) -> Result<Self> {
        let relax = CodeRelaxation { taps: start.taps(), tap: lc.constraints.tap, drain: start.drain() };
        let sensor = Sensor::ideal(start.clone(), spec.sampling, spec.irf)?;
        let basis = basis_tensor(&MeasurementMatrix::code_basis(sensor.spec()), device);
        let mut logits = CodeLogits::from_codes(start, &relax, lc.init_margin, device);
        logits.theta.id = ParamId::from(LOGITS_ID);
        let hard = hard_codes(&logits.to_array(), &relax, start)?;
        let min_shift = (tcsense_sensor::identify::ALIAS_MIN_MASKS * spec.sampling.k()).min(start.length() * spec.sampling.k() / 2).max(1);
        Ok(Learner {
            lc: lc.clone(),
            relax,
            logits,
            optim: AdamConfig::new().init(),
            basis,
            block: start.block(),
            min_shift,
            hard,
            tau: lc.tau_start,
            weight: 0.0,
        })
    }

    /// Temperature and penalty weight at `frac` ∈ [0, 1] of the relaxed phase.
    pub fn schedule(&mut self, frac: f64) {
        let f = frac.clamp(0.0, 1.0);
        self.tau = self.lc.tau_start * (self.lc.tau_end / self.lc.tau_start).powf(f);
        self.weight = self.lc.penalty_weight * f;
    }

    /// Recompute the hard codes; whether they changed.
    pub fn refresh(&mut self) -> Result<bool> {
        let hard = hard_codes(&self.logits.to_array(), &self.relax, &self.hard)?;
        let changed = hard.digest() != self.hard.digest();
        self.hard = hard;
        Ok(changed)
    }

    /// The measurements with the code gradient, `A(θ)` (for the decoder's operators) and the
    /// penalty.
    ///
    /// # Shapes
    /// - `x`: `[B, T, H, W]`, `y`: `[B, M, H, W]` (simulated by the sensor with the hard
    ///   codes) → `[B, M, H, W]`, `[N, M, T]`, `[1]`
    pub fn measurements(&self, x: &Array4<f32>, y: &Array4<f32>, device: &Device) -> (Tensor<4>, Tensor<3>, Tensor<1>) {
        let bits = self.logits.bits(&self.relax, self.tau, true);
        let a = matrix(bits, self.basis.clone()); // [N, M, T], the hard codes' A in value
        let lin = forward(a.clone(), to_tensor(&x.view(), device), self.block);
        // the sensor scales each item to its exposure: the gradient follows that gain
        let y = to_tensor(&y.view(), device);
        let total = |t: Tensor<4>| t.sum_dim(1).sum_dim(2).sum_dim(3); // [B, 1, 1, 1]
        let gain = (total(y.clone()) / total(lin.clone().detach()).clamp_min(1e-12)).detach();
        let lin = lin * gain;
        let y = y + lin.clone() - lin.detach();
        let soft = self.logits.bits(&self.relax, self.tau, false);
        let mut penalty = soft.clone().sum().mul_scalar(0.0);
        if let Some(h) = self.lc.constraints.hamming {
            penalty = penalty + hamming_penalty(soft.clone(), h);
        }
        if let Some(w) = self.lc.constraints.window {
            penalty = penalty + window_penalty(soft, w);
        }
        let mut penalty = penalty.mul_scalar(self.weight);
        if self.lc.alias_weight > 0.0 {
            penalty = penalty + alias_penalty(a.clone(), self.min_shift, self.lc.alias_threshold as f32).mul_scalar(self.lc.alias_weight);
        }
        (y, a, penalty)
    }

    /// One Adam step of the logits.
    pub fn step(&mut self, grads: GradientsParams) {
        self.logits = self.optim.step(self.lc.codes_lr, self.logits.clone(), grads);
    }

    /// Violations of the hard codes under the target constraints: (tap, Hamming, window).
    pub fn distance(&self) -> (usize, usize, usize) {
        use tcsense_sensor::codes::ConstraintKind as K;
        let v = self.hard.violations_of(&self.lc.constraints);
        let count = |k: K| v.iter().filter(|x| x.kind == k).count();
        (count(K::Tap), count(K::Hamming), count(K::Window))
    }

    /// Write the logits and their optimiser into a checkpoint directory.
    pub fn save(&self, dir: &Path) -> Result<()> {
        self.logits.clone().save_file(dir.join(LOGITS_FILE)).map_err(|e| file_err(&dir.join(format!("{LOGITS_FILE}.bpk")), e))?;
        self.optim.save(dir.join(CODE_OPTIM_FILE)).map_err(|e| file_err(&dir.join(format!("{CODE_OPTIM_FILE}.bpk")), e))?;
        Ok(())
    }

    /// Read them back from a checkpoint directory.
    pub fn load(&mut self, dir: &Path) -> Result<()> {
        let logits =
            self.logits.clone().try_load_file(dir.join(LOGITS_FILE)).map_err(|e| file_err(&dir.join(format!("{LOGITS_FILE}.bpk")), e))?;
        self.logits = logits;
        let optim = std::mem::replace(&mut self.optim, AdamConfig::new().init());
        self.optim = optim.load(dir.join(CODE_OPTIM_FILE)).map_err(|e| file_err(&dir.join(format!("{CODE_OPTIM_FILE}.bpk")), e))?;
        self.refresh()?;
        Ok(())
    }
}

/// The relaxed phase's run directory inside the run.
pub const RELAXED_DIR: &str = "relaxed";
/// What the projection did (`RUN/relaxed/projection.json`); its presence marks the relaxed
/// phase done.
pub const PROJECTION_FILE: &str = "projection.json";
/// The codes a learned-codes run started from.
pub const START_CODES_FILE: &str = "start_codes.json";
/// Per-epoch distance of the relaxed codes to feasibility.
pub const CODES_LOG: &str = "codes_log.csv";
const LOG_HEADER: &str = "epoch,step,tau,penalty_weight,tap_violations,hamming_violations,window_violations";

/// A row of `codes_log.csv`.
pub(crate) fn log_line(epoch: usize, step: u64, l: &Learner) -> String {
    let (t, h, w) = l.distance();
    format!("{epoch},{step},{:.6e},{:.6e},{t},{h},{w}", l.tau, l.weight)
}

/// The rows of `codes_log.csv` up to epoch `upto` (none if it is missing).
pub(crate) fn read_log(path: &Path, upto: usize) -> Vec<String> {
    let Ok(text) = std::fs::read_to_string(path) else { return Vec::new() };
    text.lines()
        .skip(1)
        .filter(|l| l.split(',').next().and_then(|e| e.parse::<usize>().ok()).is_some_and(|e| e <= upto))
        .map(str::to_string)
        .collect()
}

pub(crate) fn write_log(path: &Path, rows: &[String]) -> Result<()> {
    let text = std::iter::once(LOG_HEADER.to_string()).chain(rows.iter().cloned()).collect::<Vec<_>>().join("\n") + "\n";
    Ok(tcsense_sensor::npy::write_bytes(path, text.as_bytes())?)
}

/// The range alias of `codes` on an ideal sensor of this sampling and IRF (what the
/// identifiability term is for).
fn alias_of(codes: &Codes, sampling: tcsense_sensor::Sampling, irf: tcsense_sensor::Irf) -> Result<f64> {
    let sensor = Sensor::ideal(codes.clone(), sampling, irf)?;
    Ok(tcsense_sensor::identify::range_alias(&tcsense_sensor::identify::Columns::new(sensor.matrix(), sampling.k())).distance)
}

/// Bits in which two codes of the same shape differ.
fn bits_apart(a: &Codes, b: &Codes) -> usize {
    (0..a.subpixels() * a.taps()).map(|c| a.channel(c).iter().zip(b.channel(c)).filter(|(x, y)| x != y).count()).sum()
}

/// `logits` `[N, C, L]` pulled by `lambda` towards `start`: with the tap constraint its choice of
/// every subpixel and mask gains `lambda`; without, each of its bits gains `lambda` where on and
/// loses it where off. A pull above the logits' spread makes `start` the argmax.
fn pulled(logits: &ndarray::Array3<f32>, start: &Codes, tap: bool, lambda: f32) -> ndarray::Array3<f32> {
    let mut out = logits.clone();
    let (taps, drain) = (start.taps(), start.drain());
    for n in 0..start.subpixels() {
        for l in 0..start.length() {
            if tap {
                let c = (0..taps).find(|&m| start.get(n, m, l)).or(drain.then_some(taps));
                if let Some(c) = c {
                    out[(n, c, l)] += lambda;
                }
            } else {
                for m in 0..taps {
                    out[(n, m, l)] += if start.get(n, m, l) { lambda } else { -lambda };
                }
            }
        }
    }
    out
}

/// The projection of `logits` onto the constraints that also keeps the range alias at the
/// threshold: the plain projection ([`tcsense_sensor::project::project`], blind to the alias)
/// when its alias is at least `threshold` (or the start codes' is not), else the projection of
/// the logits pulled towards the start codes ([`pulled`]) by the least pull, found by doubling
/// then bisection, whose codes' alias reaches it. A large enough pull gives the start codes
/// back, so the answer always holds the alias the start codes hold.
struct Identifiable {
    /// The projection; its `score` and `argmax_score` under the learned logits, not the pulled.
    projection: tcsense_sensor::project::Projection,
    alias: f64,
    /// The pull (0: none was needed).
    pull: f32,
    /// The plain projection's alias.
    alias_without_pull: f64,
    /// Projections solved.
    solved: usize,
}

/// See [`Identifiable`].
fn project_identifiable(
    logits: &ndarray::Array3<f32>,
    start: &Codes,
    constraints: Constraints,
    threshold: f64,
    alias_of: &dyn Fn(&Codes) -> Result<f64>,
) -> Result<Identifiable> {
    let project = |lambda: f32| -> Result<(tcsense_sensor::project::Projection, f64)> {
        let theta = if lambda > 0.0 { pulled(logits, start, constraints.tap, lambda) } else { logits.clone() };
        let p = tcsense_sensor::project::project(start.shape(), start.clock_hz, constraints, &theta.view())?;
        let a = alias_of(&p.codes)?;
        Ok((p, a))
    };
    let (plain, plain_alias) = project(0.0)?;
    if plain_alias >= threshold || alias_of(start)? < threshold {
        return Ok(Identifiable { projection: plain, alias: plain_alias, pull: 0.0, alias_without_pull: plain_alias, solved: 1 });
    }
    // scored under the learned logits, the bound the plain projection's
    let unpulled = |(mut p, a, pull): (tcsense_sensor::project::Projection, f64, f32), solved: usize| {
        p.score = tcsense_sensor::project::score(&p.codes, &logits.view());
        p.argmax_score = plain.argmax_score;
        Identifiable { projection: p, alias: a, pull, alias_without_pull: plain_alias, solved }
    };
    // the logits' spread: a pull of twice it makes the start codes the argmax
    let spread = logits.iter().fold(0f32, |a, &v| a.max(v.abs())).max(1e-6);
    let (mut lo, mut hi) = (0f32, spread / 64.0);
    let mut solved = 1;
    let mut best = loop {
        let (p, a) = project(hi)?;
        solved += 1;
        if a >= threshold {
            break (p, a, hi);
        }
        if hi > 4.0 * spread {
            // (not reached: the start codes hold the alias) the start codes themselves
            let (p, a) = project(1e3 * spread)?;
            return Ok(unpulled((p, a, 1e3 * spread), solved + 1));
        }
        lo = hi;
        hi *= 2.0;
    };
    for _ in 0..6 {
        let mid = 0.5 * (lo + best.2);
        let (p, a) = project(mid)?;
        solved += 1;
        if a >= threshold {
            best = (p, a, mid);
        } else {
            lo = mid;
        }
    }
    Ok(unpulled(best, solved))
}

/// Project the learned logits onto the constraints, keeping the range alias at the threshold
/// ([`project_identifiable`]), record what it did in `RELAXED/projection.json`, and return the
/// codes (provenance `learned`).
pub(crate) fn project_and_record(l: &Learner, start: &Codes, cfg: &crate::TrainConfig, relaxed: &Path) -> Result<Codes> {
    let theta = l.logits.to_array();
    let Identifiable { projection: p, alias, pull, alias_without_pull, solved } =
        project_identifiable(&theta, start, l.lc.constraints, l.lc.alias_threshold, &|c| alias_of(c, cfg.run.sampling, cfg.run.irf))?;
    let (tap, hamming, window) = l.distance();
    let (changed, from_start) = (bits_apart(&p.codes, &l.hard), bits_apart(&p.codes, start));
    let record = serde_json::json!({
        "range_alias": alias,
        "alias_threshold": l.lc.alias_threshold,
        "solver": p.method,
        "score": p.score,
        "argmax_score": p.argmax_score,
        "relaxed_violations": {"tap": tap, "hamming": hamming, "window": window},
        "bits_changed": changed,
        "bits_from_start": from_start,
        "alias_pull": pull,
        "alias_without_pull": alias_without_pull,
        "projections": solved,
        "bits": start.subpixels() * start.taps() * start.length(),
    });
    let mut codes = p.codes;
    codes.provenance = serde_json::json!({
        "method": "learned",
        "decoder": cfg.run.model.name(),
        "seed": cfg.seed,
        "start_codes": start.digest(),
        "schedule": l.lc,
        "projection": record,
    });
    codes.save(&relaxed.join("projected_codes.json"))?;
    let text = serde_json::to_string_pretty(&record).map_err(|e| file_err(&relaxed.join(PROJECTION_FILE), e))? + "\n";
    tcsense_sensor::npy::write_bytes(&relaxed.join(PROJECTION_FILE), text.as_bytes())?;
    Ok(codes)
}

#[cfg(test)]
mod tests {
    use super::*;
    use tcsense_sensor::generate::{prototype_codes, random_codes};
    use tcsense_sensor::{Irf, Sampling};

    /// Logits that prefer codes of poor alias are projected to feasible codes that hold the
    /// start codes' alias, scoring at least the start codes under the learned logits (the pull
    /// trades agreement with the start codes for score, never below them).
    #[test]
    fn the_projection_keeps_the_alias_of_the_start_codes() {
        let proto = prototype_codes(1).expect("the prototype's codes");
        let sampling = Sampling::Oversample(1);
        let alias = |c: &Codes| alias_of(c, sampling, Irf::Physical { laser_fwhm_s: 0.3e-9, tap_tau_s: 0.3e-9 });
        let (shape, constraints) = (proto.shape(), proto.constraints);
        // start from the random feasible codes of the highest alias, learned logits that prefer
        // those of the lowest
        let mut codes: Vec<(f64, Codes)> = (1..24)
            .map(|seed| random_codes(shape, proto.clock_hz, constraints, seed).expect("random codes"))
            .map(|c| (alias(&c).expect("alias"), c))
            .collect();
        codes.sort_by(|a, b| a.0.total_cmp(&b.0));
        let (worst, start) = (codes[0].1.clone(), codes[codes.len() - 1].1.clone());
        let choices = tcsense_sensor::project::choices(&shape, &constraints);
        let logits = ndarray::Array3::from_shape_fn((shape.subpixels(), choices, shape.length), |(n, c, l)| {
            let on = (0..shape.taps).find(|&m| worst.get(n, m, l)) == Some(c);
            (if on { 1.0 } else { 0.0 }) + 0.01 * (((n * 31 + c * 7 + l * 13) % 17) as f32 / 17.0)
        });
        let threshold = alias(&start).expect("alias");
        assert!(alias(&worst).expect("alias") < threshold, "{:?}", codes.iter().map(|c| c.0).collect::<Vec<_>>());
        let r = project_identifiable(&logits, &start, constraints, threshold, &alias).expect("a projection");
        assert!(r.alias_without_pull < threshold && r.pull > 0.0, "the plain projection is the low-alias code");
        assert!(r.alias >= threshold && r.projection.codes.violations_of(&constraints).is_empty(), "{}", r.alias);
        let score = |c: &Codes| tcsense_sensor::project::score(c, &logits.view());
        assert!((r.projection.score - score(&r.projection.codes)).abs() < 1e-9, "scored under the learned logits");
        assert!(r.projection.score >= score(&start) - 1e-9, "{} against the start's {}", r.projection.score, score(&start));
        // with the alias already held no pull is applied
        let plain = project_identifiable(&logits, &start, constraints, 0.0, &alias).expect("a projection");
        assert_eq!((plain.pull, plain.solved), (0.0, 1));
        assert_eq!(plain.projection.codes.digest(), worst.digest());
    }
}
