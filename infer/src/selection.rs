//! Code selection (paper III-D-1 and IV): the TVAL3 reconstruction MSE of a code set over a
//! dataset, random generation under the constraints and selection of the best of several
//! candidates, and the constraint settings of the design sweeps (Fig. 13, Table 1).

use crate::metrics::mse;
use crate::{InferError, Result};
use ndarray::Array3;
use rayon::prelude::*;
use serde::Serialize;
use std::sync::atomic::AtomicBool;
use tcsense_models::{tval3, Tval3Options};
use tcsense_sensor::codes::{CodeShape, Codes, Constraints};
use tcsense_sensor::generate::random_codes;
use tcsense_sensor::{Sensor, SensorParams};

/// Sensor settings that do not come from the codes (sampling, IRF).
#[derive(Debug, Clone, Copy)]
pub struct EvalSetup {
    pub base: SensorParams,
    pub tval3: Tval3Options,
}

/// Mean TVAL3 reconstruction MSE of `codes` over `cubes` (noise-free measurements, as in the
/// paper's §IV).
///
/// # Shapes
/// - `cubes`: each `[T, H, W]`
pub fn evaluate(codes: &Codes, setup: &EvalSetup, cubes: &[Array3<f32>], cancel: &AtomicBool) -> Result<f64> {
    let sensor = Sensor::ideal(codes.clone(), setup.base.sampling, setup.base.irf)?;
    let a = sensor.matrix();
    let mut total = 0.0;
    for x in cubes {
        let (_, h, w) = x.dim();
        let plan = a.plan(h, w)?;
        let y = plan.forward(&x.view())?;
        let (xh, _) = tval3(&a, &plan, &y.view(), &setup.tval3, &|_, _| {}, cancel)?;
        total += mse(xh.as_slice().unwrap_or(&[]), x.as_slice().unwrap_or(&[]));
    }
    Ok(total / cubes.len().max(1) as f64)
}

/// One evaluated candidate.
#[derive(Debug, Clone, Serialize)]
pub struct Candidate {
    pub seed: u64,
    pub mse: f64,
}

/// Generate and evaluate the code sets of `seeds`; returns them with their MSE in seed order,
/// calling `on_candidate` after each (in seed order).
///
/// The candidates are independent solves: they run in parallel, as many at a time as the
/// thread pool has threads, on the same pool as each solve's own bands, so the cores stay busy
/// on small frames without oversubscription. Each solve adds its sums in a fixed order, so the
/// results do not depend on the scheduling.
#[allow(clippy::too_many_arguments)]
pub fn evaluate_candidates(
    shape: CodeShape,
    clock_hz: f64,
    constraints: Constraints,
    seeds: &[u64],
    setup: &EvalSetup,
    cubes: &[Array3<f32>],
    on_candidate: &mut dyn FnMut(&Candidate),
    cancel: &AtomicBool,
) -> Result<Vec<(Candidate, Codes)>> {
    let mut out = Vec::with_capacity(seeds.len());
    for group in seeds.chunks(rayon::current_num_threads().max(1)) {
        let done: Vec<Result<(Codes, f64)>> = group
            .par_iter()
            .map(|&s| {
                let codes = random_codes(shape, clock_hz, constraints, s)?;
                let m = evaluate(&codes, setup, cubes, cancel)?;
                Ok((codes, m))
            })
            .collect();
        for (&s, r) in group.iter().zip(done) {
            let (codes, m) = r?;
            let c = Candidate { seed: s, mse: m };
            on_candidate(&c);
            out.push((c, codes));
        }
    }
    Ok(out)
}

/// Generate `n` candidates (seeds `seed, seed+1, …`), evaluate each ([`evaluate_candidates`]),
/// return them all and the best code set. `on_candidate` is called after each evaluation.
#[allow(clippy::too_many_arguments)]
pub fn select(
    shape: CodeShape,
    clock_hz: f64,
    constraints: Constraints,
    n: usize,
    seed: u64,
    setup: &EvalSetup,
    cubes: &[Array3<f32>],
    on_candidate: &mut dyn FnMut(&Candidate),
    cancel: &AtomicBool,
) -> Result<(Codes, Vec<Candidate>)> {
    let seeds: Vec<u64> = (0..n.max(1) as u64).map(|i| seed.wrapping_add(i)).collect();
    let mut all = Vec::with_capacity(n);
    let mut best: Option<(f64, Codes)> = None;
    for (c, codes) in evaluate_candidates(shape, clock_hz, constraints, &seeds, setup, cubes, on_candidate, cancel)? {
        if best.as_ref().is_none_or(|(b, _)| c.mse < *b) {
            best = Some((c.mse, codes));
        }
        all.push(c);
    }
    let (m, mut codes) = best.ok_or(InferError::InvalidParam { field: "candidates", got: "0".into(), expected: "at least 1".into() })?;
    codes.provenance = serde_json::json!({
        "method": "random+selection",
        "seed": codes.provenance.get("seed").cloned().unwrap_or_default(),
        "candidates": n,
        "first_seed": seed,
        "mse": m,
    });
    Ok((codes, all))
}

/// The five constraint settings of the paper's Table 1, with their labels.
pub fn table1_settings() -> Vec<(&'static str, Constraints)> {
    vec![
        ("no constraint", Constraints::default()),
        ("tap", Constraints { tap: true, ..Default::default() }),
        ("tap + window", Constraints { tap: true, window: Some(2), ..Default::default() }),
        ("tap + hamming", Constraints { tap: true, hamming: Some(2), ..Default::default() }),
        ("tap + hamming + window", Constraints { tap: true, hamming: Some(2), window: Some(2) }),
    ]
}
