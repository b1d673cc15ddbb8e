//! Photon-efficiency curves: the rows of a light ladder ([`crate::eval::evaluate_ladder`]) as
//! one series per decoder against the brightest tap's signal electrons, beside the codes'
//! Cramér–Rao bound, drawn with [`crate::figures::photon_curve`]. Used by `tcsense eval --plot`
//! and by the demo's report.

use std::path::Path;
use tcsense_sensor::identify::{lifetime_bound, range_bound, Columns, Light};
use tcsense_sensor::{MeasurementMatrix, NoiseParams};

use crate::eval::EvalRow;
use crate::figures::Series;
use crate::{InferError, Result};

/// One series per decoder of ladder rows (in their order): `f` of each row against the
/// brightest tap's signal electrons of its level.
pub fn decoder_series(rows: &[EvalRow], f: &dyn Fn(&EvalRow) -> Option<f64>) -> Vec<Series> {
    let mut names: Vec<&str> = Vec::new();
    for r in rows {
        if !names.contains(&r.decoder.as_str()) {
            names.push(&r.decoder);
        }
    }
    names
        .iter()
        .map(|n| Series {
            label: n.to_string(),
            points: rows.iter().filter(|r| r.decoder == *n).filter_map(|r| Some((r.light?.signal_electrons, f(r)?))).collect(),
        })
        .collect()
}

/// The largest share of a return's light one tap collects (photons = tap electrons / share).
pub fn brightest_tap_share(a: &MeasurementMatrix) -> f64 {
    let m = a.a();
    let (n, taps, t) = m.dim();
    let mut share = 0f64;
    for i in 0..n {
        for j in 0..t {
            let col: Vec<f64> = (0..taps).map(|k| m[(i, k, j)] as f64).collect();
            let total: f64 = col.iter().sum();
            if total > 0.0 {
                share = share.max(col.iter().fold(0.0, |x: f64, &v| x.max(v)) / total);
            }
        }
    }
    share
}

/// A bound against the light at the ladder levels of `rows` (signal electrons in the brightest
/// tap, sorted): `bound` of the [`Light`] whose photons put those electrons in the brightest tap
/// of `a`, with the noise model's read noise and the ambient light at `sbr`; `None` where no tap
/// collects light.
fn bound_series(
    rows: &[EvalRow],
    a: &MeasurementMatrix,
    noise: &NoiseParams,
    sbr: Option<f64>,
    label: &str,
    bound: impl Fn(&Light) -> f64,
) -> Option<Series> {
    let share = brightest_tap_share(a);
    let mut levels: Vec<f64> = rows.iter().filter_map(|r| r.light.map(|l| l.signal_electrons)).collect();
    levels.sort_by(f64::total_cmp);
    levels.dedup();
    (share > 0.0).then(|| Series {
        label: label.into(),
        points: levels
            .iter()
            .map(|&e| {
                let photons = e / share;
                (e, bound(&Light { photons, ambient: sbr.map_or(0.0, |s| photons / s), read_noise_e: noise.read_noise_e }))
            })
            .collect(),
    })
}

/// Code sets to draw the bound of: a name (for the legend) and the sensor's matrix. One set is
/// drawn as "the codes"; several are named.
pub type CodeSets<'a> = [(&'a str, &'a MeasurementMatrix)];

/// One bound per code set of `codes` (see [`bound_series`]), labelled `what` and, where there
/// are several sets, the set's name; `bound` prepares a set's bound once, then it is read at
/// every level.
fn bounds_of<'c, B: Fn(&Light) -> f64>(
    rows: &[EvalRow],
    codes: &CodeSets<'c>,
    noise: &NoiseParams,
    sbr: Option<f64>,
    what: &str,
    bound: impl Fn(&'c MeasurementMatrix) -> B,
) -> Vec<Series> {
    codes
        .iter()
        .filter_map(|&(name, a)| {
            let label = if codes.len() > 1 {
                format!("Cramér–Rao bound, {name} codes ({what})")
            } else {
                format!("Cramér–Rao bound ({what})")
            };
            bound_series(rows, a, noise, sbr, &label, bound(a))
        })
        .collect()
}

/// The photon-efficiency figure of FLIm ladder rows: each decoder's lifetime MAE (ns) and the
/// share of the fluorophore pixels with a lifetime against the brightest tap's signal
/// electrons, beside each code set's Cramér–Rao bound of a 2 ns lifetime seen by a whole block
/// with its onset known ([`tcsense_sensor::identify::lifetime_bound`], mean over 8 onsets),
/// under the noise model's read noise and the ambient light; `k` is the heterodyne factor.
pub fn lifetime_curve(png: &Path, rows: &[EvalRow], codes: &CodeSets, k: usize, noise: &NoiseParams, sbr: Option<f64>) -> Result<()> {
    let bounds = bounds_of(rows, codes, noise, sbr, "a block, τ = 2 ns, onset known", |a| {
        let (cols, weights) = (Columns::new(a, k), vec![1.0; a.a().dim().0]);
        move |light: &Light| lifetime_bound(&cols, light, &[2e-9], 8, &weights)[0].known_mean_s * 1e9
    });
    let series = |f: &dyn Fn(&EvalRow) -> Option<f64>| decoder_series(rows, f);
    let errors = series(&|r| r.lifetime_mae_s.map(|v| v * 1e9));
    let shares = series(&|r| r.lifetime_coverage.map(|v| 100.0 * v));
    let ambient = sbr.map_or("no ambient light".to_string(), |s| format!("ambient at SBR {s}"));
    crate::figures::photon_curve(
        png,
        &format!("Photon efficiency: lifetime error against the light ({ambient})"),
        "signal electrons in the brightest tap (e⁻)",
        "lifetime MAE (ns)",
        "fluorophore pixels with a lifetime (%)",
        &errors,
        &shares,
        &bounds,
    )?;
    Ok(())
}

/// The photon-efficiency figure of ladder rows: each decoder's median first-return error (bins)
/// and share within half a bin against the brightest tap's signal electrons.
/// Beside them, each code set's Cramér–Rao bound of one return seen by a whole block
/// ([`tcsense_sensor::identify::range_bound`], mean over the cycle) whose brightest tap holds
/// the level's signal electrons, with the noise model's read noise and the ambient light. The
/// sets share a time grid: the bins are the first set's.
pub fn range_curve(png: &Path, rows: &[EvalRow], codes: &CodeSets, noise: &NoiseParams, sbr: Option<f64>) -> Result<()> {
    let Some((_, first)) = codes.first() else {
        return Err(InferError::InvalidParam { field: "photon curve", got: "no codes".into(), expected: "the codes of the rows".into() });
    };
    let bin_m = 299_792_458.0 * first.bin_width_s() / 2.0;
    let bounds = bounds_of(rows, codes, noise, sbr, "a block, one return", |a| move |light: &Light| range_bound(a, light, 2).mean_bins);
    let series = |f: &dyn Fn(&EvalRow) -> Option<f64>| decoder_series(rows, f);
    let errors = series(&|r| r.depth_median_m.first().map(|m| m / bin_m));
    let shares = series(&|r| r.depth_within_half_bin.first().map(|s| 100.0 * s));
    if errors.iter().all(|s| s.points.is_empty()) {
        return Err(InferError::InvalidParam {
            field: "photon curve",
            got: "decoders that gave no first-return ranges nor lifetimes".into(),
            expected: "a LiDAR dataset with depth and decoders of depth or cubes, or a FLIm dataset and lifetime decoders".into(),
        });
    }
    let ambient = sbr.map_or("no ambient light".to_string(), |s| format!("ambient at SBR {s}"));
    crate::figures::photon_curve(
        png,
        &format!("Photon efficiency: first-return range error against the light ({ambient})"),
        "signal electrons in the brightest tap (e⁻)",
        "median first-return error (bins)",
        "first returns within half a bin (%)",
        &errors,
        &shares,
        &bounds,
    )?;
    Ok(())
}
