//! Training data from a dataset directory.

use ndarray::{Array4, Axis, Ix4};
use tcsense_datasets::Dataset;

use crate::{file_err, Result};

/// Load the cubes of a split, `[N, T, H, W]`, at most `max` of them.
pub fn load_cubes(ds: &Dataset, split: &str, max: Option<usize>) -> Result<Array4<f32>> {
    // only the shards that hold the first `max` items are read
    let x = ds.load_first(split, "x", max)?;
    x.into_dimensionality::<Ix4>().map_err(|e| file_err(&ds.dir, format!("field x of split {split}: {e}")))
}

/// Load the range labels of a split's first `k` returns, `[N, K, H, W]` (m, NaN where none),
/// at most `max` items; datasets without a `depth` field (FLIm, imported cubes) cannot train
/// a depth network.
pub fn load_depth(ds: &Dataset, split: &str, max: Option<usize>, k: usize) -> Result<Array4<f32>> {
    if !ds.manifest.fields.contains_key("depth") {
        return Err(file_err(
            &ds.dir,
            "no depth field: a depth network trains on LiDAR data (tcsense dataset lidar or dataset import --depth)",
        ));
    }
    let d = ds
        .load_first(split, "depth", max)?
        .into_dimensionality::<Ix4>()
        .map_err(|e| file_err(&ds.dir, format!("field depth of split {split}: {e}")))?;
    let (_, bounces, _, _) = d.dim();
    if k == 0 || k > bounces {
        return Err(file_err(&ds.dir, format!("the depth field has {bounces} returns per pixel; the network wants {k}")));
    }
    Ok(d.slice(ndarray::s![.., ..k, .., ..]).to_owned())
}

/// Lifetime labels of one pixel from its channel weights `w_i` and lifetimes `τ_i` (s): the
/// amplitude-weighted mean `τ_m` and two components `τ₁ ≤ τ₂` (ns) with the fraction `α₁`.
/// Channels with the same lifetime are one component; of three distinct ones the two closest
/// (in log τ) merge into their amplitude-weighted mean. One component: `τ₁ = τ₂`, `α₁ = 1`.
pub fn components(w: [f32; 3], tau_s: [f32; 3]) -> [f32; 4] {
    let mut comps: Vec<(f64, f64)> = Vec::with_capacity(3); // (τ ns, amplitude)
    for i in 0..3 {
        let (t, a) = (tau_s[i] as f64 * 1e9, w[i] as f64);
        if a <= 0.0 {
            continue;
        }
        match comps.iter_mut().find(|c| (c.0 - t).abs() <= 1e-6 * t) {
            Some(c) => c.1 += a,
            None => comps.push((t, a)),
        }
    }
    comps.sort_by(|a, b| a.0.total_cmp(&b.0));
    let total: f64 = comps.iter().map(|c| c.1).sum();
    if comps.is_empty() || total <= 0.0 {
        return [f32::NAN; 4];
    }
    let mean = comps.iter().map(|c| c.0 * c.1).sum::<f64>() / total;
    if comps.len() == 3 {
        // merge the closest pair (in log τ)
        let j = if (comps[1].0 / comps[0].0).ln() <= (comps[2].0 / comps[1].0).ln() { 0 } else { 1 };
        let (a, b) = (comps[j], comps[j + 1]);
        comps[j] = ((a.0 * a.1 + b.0 * b.1) / (a.1 + b.1), a.1 + b.1);
        comps.remove(j + 1);
    }
    let (t1, t2, a1) = match comps.as_slice() {
        [c] => (c.0, c.0, 1.0),
        [c1, c2] => (c1.0, c2.0, c1.1 / (c1.1 + c2.1)),
        _ => unreachable!("one to three components merged to at most two"),
    };
    [mean as f32, t1 as f32, t2 as f32, a1 as f32]
}

/// Lifetime labels of a split, `[N, 5, H, W]`: `τ_m`, `τ₁`, `τ₂` (ns), `α₁` (NaN where the
/// truth has no lifetime) and the signal mask (1 where a fluorophore is at least
/// [`tcsense_datasets::flim::SIGNAL_REL`] of the item's brightest pixel, else 0), at most `max` items. Datasets without
/// the FLIm fields (LiDAR, imported cubes without lifetimes) cannot train a lifetime network.
pub fn load_lifetime_labels(ds: &Dataset, split: &str, max: Option<usize>) -> Result<Array4<f32>> {
    for f in ["lifetime", "weights", "tau", "intensity"] {
        if !ds.manifest.fields.contains_key(f) {
            return Err(file_err(&ds.dir, format!("no {f} field: a lifetime network trains on FLIm data (tcsense dataset flim)")));
        }
    }
    let bad = |f: &str, e: ndarray::ShapeError| file_err(&ds.dir, format!("field {f} of split {split}: {e}"));
    let life = ds.load_first(split, "lifetime", max)?.into_dimensionality::<ndarray::Ix3>().map_err(|e| bad("lifetime", e))?;
    let w = ds.load_first(split, "weights", max)?.into_dimensionality::<Ix4>().map_err(|e| bad("weights", e))?;
    let tau = ds.load_first(split, "tau", max)?.into_dimensionality::<ndarray::Ix2>().map_err(|e| bad("tau", e))?;
    let inten = ds.load_first(split, "intensity", max)?.into_dimensionality::<ndarray::Ix3>().map_err(|e| bad("intensity", e))?;
    let (n, h, wd) = life.dim();
    if w.dim() != (n, 3, h, wd) || tau.dim() != (n, 3) || inten.dim() != (n, h, wd) {
        return Err(file_err(
            &ds.dir,
            format!(
                "split {split}: weights {:?}, tau {:?}, intensity {:?} do not fit lifetime {:?}",
                w.shape(),
                tau.shape(),
                inten.shape(),
                life.shape()
            ),
        ));
    }
    let mut out = Array4::<f32>::from_elem((n, 5, h, wd), f32::NAN);
    for i in 0..n {
        let peak = inten.index_axis(Axis(0), i).iter().fold(0f32, |m, &v| m.max(v));
        let t = [tau[(i, 0)], tau[(i, 1)], tau[(i, 2)]];
        for r in 0..h {
            for c in 0..wd {
                let signal = tcsense_datasets::flim::holds_fluorophore(life[(i, r, c)], inten[(i, r, c)], peak);
                out[(i, 4, r, c)] = if signal { 1.0 } else { 0.0 };
                if life[(i, r, c)].is_finite() {
                    let l = components([w[(i, 0, r, c)], w[(i, 1, r, c)], w[(i, 2, r, c)]], t);
                    for (k, v) in l.into_iter().enumerate() {
                        out[(i, k, r, c)] = v;
                    }
                }
            }
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn components_merge_shared_and_close_lifetimes() {
        // one lifetime shared by all channels: one component
        let l = components([0.2, 0.3, 0.5], [2e-9, 2e-9, 2e-9]);
        assert!((l[0] - 2.0).abs() < 1e-6 && l[1] == l[2] && l[3] == 1.0);
        // two: amplitudes add up per lifetime
        let l = components([0.2, 0.3, 0.5], [1e-9, 3e-9, 3e-9]);
        assert!(
            (l[0] - (0.2 + 0.8 * 3.0)).abs() < 1e-5 && (l[1] - 1.0).abs() < 1e-6 && (l[2] - 3.0).abs() < 1e-6 && (l[3] - 0.2).abs() < 1e-6
        );
        // three distinct: 1 and 1.2 ns merge (closest in log), the mean is kept
        let l = components([0.25, 0.25, 0.5], [1e-9, 1.2e-9, 4e-9]);
        assert!((l[0] - (0.25 + 0.3 + 2.0)).abs() < 1e-5, "{l:?}");
        assert!((l[1] - 1.1).abs() < 1e-5 && (l[2] - 4.0).abs() < 1e-6 && (l[3] - 0.5).abs() < 1e-6, "{l:?}");
        assert!(components([0.0; 3], [1e-9; 3])[0].is_nan());
    }
}
