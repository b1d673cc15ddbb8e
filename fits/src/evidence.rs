//! The fit's evidence as a network's input: what a learned decoder reads instead of the raw
//! taps — the lifetime network on the lifetime fit's costs ([`crate::lifetime_taps::evidence`])
//! and the depth network on the range fit's ([`crate::depth::RangeTemplates::evidence`]).
//!
//! A fit's costs are squared residuals in the measurements' units (times the charge for the
//! lifetime fit). Divided by twice the frame's noise level they become negative
//! log-likelihoods in nats, whatever the gain, the exposure and the read noise: the level is
//! the median over the lit pixels of the window's least cost per degree of freedom (what a
//! window of `n` lit pixels leaves free after the fit's own parameters, [`CostVolume::dof`]).
//! Then, over the `G` candidates of the fit's grid (lifetimes, or ranges around the cycle):
//!
//! ```text
//! skip     [H, W, G] = −(Ĉ_win − min_g Ĉ_win)                 the fit's log-likelihood of every candidate
//! features [H, W, G/pool + 2] = (G/pool)·Σ_pool softmax_g(−Ĉ_pixel),  ln(I / median I), lit
//! ```
//!
//! The network adds a learned log-prior to `skip` (so with a zero prior its most probable
//! candidate is the fit's), read from the per-pixel posteriors of a neighbourhood, which is
//! what lets it pool pixels of like lifetime or range beyond the fit's fixed window.

use ndarray::{Array2, Array3};
use rayon::prelude::*;

/// Bounds of the log-intensity channel.
const LOG_INTENSITY_CLAMP: f32 = 10.0;

/// The network's input for one frame (see the module's notes), pixel-major.
#[derive(Debug, Clone)]
pub struct Evidence {
    /// The fit's log-likelihood of every candidate of the grid, window summed, `[H, W, G]`
    /// (0 at the best; 0 everywhere at an unlit pixel); with wider windows ([`evidence_with`])
    /// theirs after it, `[H, W, S·G]`.
    pub skip: Array3<f32>,
    /// Per-pixel posteriors pooled over `pool` candidates, log relative intensity and the lit
    /// mask, `[H, W, G/pool + 2]`.
    pub features: Array3<f32>,
    /// The frame's noise level: twice it turns a cost into nats.
    pub noise: f32,
}

/// The storage of an earlier frame's [`Evidence`], written over by the next
/// ([`evidence_into`]): a stream's frames of one size need no fresh memory (a range fit's
/// log-likelihoods of four windows are 80 MB at 188×212, fresh pages and zeroing for every
/// frame otherwise). Empty: allocated.
#[derive(Debug, Default)]
pub struct EvidenceBuffers {
    pub skip: Vec<f32>,
    pub features: Vec<f32>,
}

/// A fit's costs of one frame, pixel-major, as [`evidence`] reads them.
#[derive(Debug, Clone, Copy)]
pub struct CostVolume<'a> {
    /// Each pixel's own cost of every candidate `[H·W·G]` (not read where unlit).
    pub pixel: &'a [f32],
    /// The cost summed over the window around every pixel, what the fit minimises `[H·W·G]`.
    pub window: &'a [f32],
    /// Whether a pixel holds enough charge to be fitted `[H·W]`.
    pub lit: &'a [bool],
    /// `G`, `H`, `W`.
    pub points: usize,
    pub height: usize,
    pub width: usize,
    /// The window's side.
    pub side: usize,
    /// Numbers each lit pixel of the window leaves free after its own parameters (the lifetime
    /// fit: `M − 1`, the amplitude; the range fit: `M − 2`, the amplitude and the ambient).
    pub free_per_pixel: usize,
    /// Parameters the window shares (the lifetime fit: 2, the lifetime and the background; the
    /// range fit: 1, the range).
    pub shared: usize,
}

impl CostVolume<'_> {
    /// Degrees of freedom of a window of `n` lit pixels (at least 1).
    pub fn dof(&self, n: usize) -> usize {
        (n * self.free_per_pixel).saturating_sub(self.shared).max(1)
    }
}

/// Channels of [`Evidence::features`] for a grid of `points` pooled by `pool`.
pub fn feature_channels(points: usize, pool: usize) -> usize {
    points.div_ceil(pool.max(1)) + 2
}

/// Channels of [`Evidence::features`] for a grid of `points` pooled by `pool`, with the
/// posteriors of `wider` windows beside the pixel's ([`evidence_with`]).
pub fn feature_channels_with(points: usize, pool: usize, wider: usize) -> usize {
    (1 + wider) * points.div_ceil(pool.max(1)) + 2
}

/// The evidence of one frame from a fit's costs and its intensity map.
///
/// # Shapes
/// - `costs`: of `[H·W·G]`, `intensity`: `[H, W]` → [`Evidence`]
pub fn evidence(costs: &CostVolume<'_>, intensity: &Array2<f32>, pool: usize) -> Evidence {
    evidence_with(costs, intensity, pool, &[])
}

/// [`evidence`] with the costs summed over wider windows besides (multi-scale context for the
/// network: in dim light a surface's pixels agree over a larger window than the fit's): their
/// log-likelihoods after the fit's window's in `skip`, their posteriors after the pixel's in
/// the features.
///
/// # Shapes
/// - `costs`: of `[H·W·G]`, `intensity`: `[H, W]`, each of `wider`: `[H·W·G]` → [`Evidence`]
///   with skip `[H, W, (1 + wider)·G]`, features `[H, W, (1 + wider)·G/pool + 2]`
pub fn evidence_with(costs: &CostVolume<'_>, intensity: &Array2<f32>, pool: usize, wider: &[&[f32]]) -> Evidence {
    evidence_into(costs, intensity, pool, wider, EvidenceBuffers::default())
}

/// [`evidence_with`] written into `buffers` (every value of them: what they held does not
/// matter; resized where their sizes differ): the same numbers.
///
/// # Shapes
/// - as [`evidence_with`]
pub fn evidence_into(costs: &CostVolume<'_>, intensity: &Array2<f32>, pool: usize, wider: &[&[f32]], buffers: EvidenceBuffers) -> Evidence {
    evidence_at_noise(costs, noise_level(costs), intensity, pool, wider, buffers)
}

/// [`evidence_into`] at a noise level found elsewhere (the fit's window's, for costs pooled by
/// likeness, [`similarity_pool`], whose degrees of freedom are not a window's).
///
/// # Shapes
/// - as [`evidence_with`]
pub fn evidence_at_noise(
    costs: &CostVolume<'_>,
    noise: f32,
    intensity: &Array2<f32>,
    pool: usize,
    wider: &[&[f32]],
    buffers: EvidenceBuffers,
) -> Evidence {
    let (g, h, w) = (costs.points, costs.height, costs.width);
    let pool = pool.max(1);
    let window = costs.window;
    let lit = costs.lit;
    let nats = 1.0 / (2.0 * noise);
    let channels = feature_channels_with(g, pool, wider.len());
    let pooled = g.div_ceil(pool);
    let mut lit_intensity: Vec<f32> = (0..h * w).filter(|&p| lit[p]).map(|p| intensity[(p / w, p % w)]).collect();
    let reference = median(&mut lit_intensity, f32::total_cmp).filter(|v| *v > 0.0).unwrap_or(1.0);
    // the log-likelihoods: the fit's window's, then the wider windows'
    let sg = (1 + wider.len()) * g;
    let sized = |mut v: Vec<f32>, n: usize| {
        if v.len() != n {
            v.clear();
            v.resize(n, 0.0);
        }
        v
    };
    let (mut skip, mut features) = (sized(buffers.skip, h * w * sg), sized(buffers.features, h * w * channels));
    skip.par_chunks_mut(w * sg).zip(features.par_chunks_mut(w * channels)).enumerate().for_each(|(i, (srow, frow))| {
        let mut post = vec![0f32; g];
        for j in 0..w {
            let p = i * w + j;
            let (sp, fp) = (&mut srow[j * sg..(j + 1) * sg], &mut frow[j * channels..(j + 1) * channels]);
            let s = intensity[(i, j)];
            fp[channels - 2] =
                if s > 0.0 { (s / reference).ln().clamp(-LOG_INTENSITY_CLAMP, LOG_INTENSITY_CLAMP) } else { -LOG_INTENSITY_CLAMP };
            if !lit[p] {
                // (no evidence: zeros, whatever the buffer held)
                sp.fill(0.0);
                fp[..channels - 2].fill(0.0);
                fp[channels - 1] = 0.0;
                continue;
            }
            fp[channels - 1] = 1.0;
            for (b, volume) in std::iter::once(window).chain(wider.iter().copied()).enumerate() {
                let win = &volume[p * g..(p + 1) * g];
                let least = win.iter().fold(f32::INFINITY, |a, &b| a.min(b));
                for (o, &c) in sp[b * g..(b + 1) * g].iter_mut().zip(win) {
                    *o = -(c - least) * nats;
                }
            }
            for (b, volume) in std::iter::once(costs.pixel).chain(wider.iter().copied()).enumerate() {
                let own = &volume[p * g..(p + 1) * g];
                let least = own.iter().fold(f32::INFINITY, |a, &b| a.min(b));
                let mut total = 0f32;
                for (q, &c) in post.iter_mut().zip(own) {
                    *q = underflowing_exp(-(c - least) * nats);
                    total += *q;
                }
                let scale = pooled as f32 / total;
                // each pooled channel sums its candidates in order (as one `+=` per candidate)
                for (o, chunk) in fp[b * pooled..(b + 1) * pooled].iter_mut().zip(post.chunks(pool)) {
                    *o = chunk.iter().fold(0.0, |a, &q| a + q * scale);
                }
            }
        }
    });
    let shape = |c: usize, v: Vec<f32>| Array3::from_shape_vec((h, w, c), v).expect("[H, W, C] buffer");
    Evidence { skip: shape(sg, skip), features: shape(channels, features), noise }
}

/// The frame's noise level of a fit's costs (see the module's notes): the median over the lit
/// pixels of the window's least cost per degree of freedom; 1 where there is none.
///
/// # Shapes
/// - `costs`: of `[H·W·G]`
pub fn noise_level(costs: &CostVolume<'_>) -> f32 {
    let (g, h, w) = (costs.points, costs.height, costs.width);
    let window = costs.window;
    let half = costs.side / 2;
    let lit = costs.lit;
    let mut per_dof: Vec<f32> = (0..h)
        .into_par_iter()
        .flat_map_iter(|i| {
            (0..w).filter_map(move |j| {
                let p = i * w + j;
                if !lit[p] {
                    return None;
                }
                let mut n = 0usize;
                for ii in i.saturating_sub(half)..(i + half + 1).min(h) {
                    for jj in j.saturating_sub(half)..(j + half + 1).min(w) {
                        n += lit[ii * w + jj] as usize;
                    }
                }
                let dof = costs.dof(n) as f32;
                let least = window[p * g..(p + 1) * g].iter().fold(f32::INFINITY, |a, &b| a.min(b));
                least.is_finite().then(|| least.max(0.0) / dof)
            })
        })
        .collect();
    median(&mut per_dof, f32::total_cmp).filter(|v| *v > 0.0 && v.is_finite()).unwrap_or(1.0)
}

/// Whether `side` is a neighbourhood the windows of side `window` tile around a pixel's own
/// ([`similarity_pool`]): an odd multiple of it, above it, up to [`crate::range::MAX_WINDOW`].
pub fn pooled_side(side: usize, window: usize) -> bool {
    window > 0 && side > window && side.is_multiple_of(window) && !(side / window).is_multiple_of(2) && side <= crate::range::MAX_WINDOW
}

/// The costs pooled over windows of like evidence: every pixel's window's cost, plus the
/// window costs of the neighbouring windows that tile its `side × side` neighbourhood (their
/// centres a window's side apart, so that no pixel is counted twice), each weighted by how
/// much its posterior overlaps the pixel's window's (their Bhattacharyya coefficient):
///
/// ```text
/// P_p = C_win,p + Σ_{q = p + s·(a, b), 0 < max(|a|, |b|) ≤ k} BC(π_p, π_q) · C_win,q,
/// π_p = softmax(−Ĉ_win,p · nats),   s the window's side,  side = (2k + 1)·s
/// ```
///
/// In bright light the posteriors are sharp and a neighbouring window of another lifetime
/// weighs nothing (the fit's window alone); in dim light, or across a cell of one lifetime,
/// they overlap and the neighbourhood pools as a window of `side` would. `side` is an odd
/// multiple of the window's (9 or 15 for a 3×3 window: 8 or 24 neighbouring windows).
///
/// # Shapes
/// - `costs`: of `[H·W·G]` → `[H·W·G]` (0 where unlit)
pub fn similarity_pool(costs: &CostVolume<'_>, nats: f32, side: usize) -> Vec<f32> {
    let (g, h, w) = (costs.points, costs.height, costs.width);
    let (window, lit) = (costs.window, costs.lit);
    // √π of every lit pixel's window posterior
    let mut roots = vec![0f32; h * w * g];
    roots.par_chunks_mut(g).enumerate().for_each(|(p, root)| {
        if !lit[p] {
            return;
        }
        let win = &window[p * g..(p + 1) * g];
        let least = win.iter().fold(f32::INFINITY, |a, &b| a.min(b));
        let mut total = 0f32;
        for (o, &c) in root.iter_mut().zip(win) {
            *o = underflowing_exp(-(c - least) * nats);
            total += *o;
        }
        let scale = 1.0 / total;
        root.iter_mut().for_each(|o| *o = (*o * scale).sqrt());
    });
    let step = costs.side.max(1) as isize;
    let k = (side / costs.side.max(1) / 2) as isize;
    let mut out = vec![0f32; h * w * g];
    out.par_chunks_mut(w * g).enumerate().for_each(|(i, row)| {
        for j in 0..w {
            let p = i * w + j;
            let o = &mut row[j * g..(j + 1) * g];
            if !lit[p] {
                continue;
            }
            o.copy_from_slice(&window[p * g..(p + 1) * g]);
            let rp = &roots[p * g..(p + 1) * g];
            for a in -k..=k {
                for b in -k..=k {
                    let (ii, jj) = (i as isize + a * step, j as isize + b * step);
                    if (a == 0 && b == 0) || ii < 0 || jj < 0 || ii >= h as isize || jj >= w as isize {
                        continue;
                    }
                    let q = ii as usize * w + jj as usize;
                    if !lit[q] {
                        continue;
                    }
                    let weight = overlap(rp, &roots[q * g..(q + 1) * g]).min(1.0);
                    if weight > 1e-3 {
                        o.iter_mut().zip(&window[q * g..(q + 1) * g]).for_each(|(x, y)| *x += weight * y);
                    }
                }
            }
        }
    });
    out
}

/// `Σ a·b` over eight lanes (vectorised), then the lanes' sum.
#[inline]
fn overlap(a: &[f32], b: &[f32]) -> f32 {
    let mut lanes = [0f32; 8];
    let (ca, cb) = (a.chunks_exact(8), b.chunks_exact(8));
    let tail: f32 = ca.remainder().iter().zip(cb.remainder()).map(|(x, y)| x * y).sum();
    for (x, y) in ca.zip(cb) {
        for k in 0..8 {
            lanes[k] += x[k] * y[k];
        }
    }
    lanes.iter().sum::<f32>() + tail
}

/// `x.exp()` with the arguments whose exponential rounds to 0 in f32 (below −104: under half
/// the least subnormal) answered without the call: most of a posterior's candidates are there,
/// and libm's underflow path (errno, a raised flag) costs several times a plain `expf`. Bit for
/// bit `x.exp()`.
#[inline]
fn underflowing_exp(x: f32) -> f32 {
    if x < -104.0 {
        0.0
    } else {
        x.exp()
    }
}

/// The median of `v` (reordered) in the order `by`, `None` when empty.
pub(crate) fn median<T: Copy>(v: &mut [T], by: impl FnMut(&T, &T) -> std::cmp::Ordering) -> Option<T> {
    if v.is_empty() {
        return None;
    }
    let mid = v.len() / 2;
    let (_, m, _) = v.select_nth_unstable_by(mid, by);
    Some(*m)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_shortcut_exponential_is_exp_bit_for_bit() {
        // across the cutoff, the subnormals and the normal range
        for i in 0..=2_000_000 {
            let x = -130.0 + i as f32 * 7e-5;
            assert_eq!(underflowing_exp(x).to_bits(), x.exp().to_bits(), "at {x}");
        }
        assert_eq!(underflowing_exp(f32::NEG_INFINITY), 0.0);
    }

    /// The pool is its definition, computed plainly: the window's cost plus each lit
    /// neighbouring window a window's side apart times the overlap of the posteriors; a window
    /// whose posterior shares nothing with the pixel's adds nothing.
    #[test]
    fn the_similarity_pool_is_its_definition() {
        let (h, w, g) = (11, 13, 10);
        let value = |p: usize, k: usize, salt: usize| ((p * 31 + k * 7 + salt * 13) % 17) as f32 * 0.25;
        let pixel: Vec<f32> = (0..h * w * g).map(|i| value(i / g, i % g, 1)).collect();
        // (window 70 puts its posterior on the last points, where no one else's is)
        let lone = 70;
        let window: Vec<f32> = (0..h * w * g)
            .map(|i| match (i / g == lone, i % g >= 8) {
                (true, true) => 0.0,
                (false, true) | (true, false) => 500.0,
                (false, false) => 3.0 * value(i / g, i % g, 2),
            })
            .collect();
        let lit: Vec<bool> = (0..h * w).map(|p| p % 6 != 2).collect();
        let volume =
            CostVolume { pixel: &pixel, window: &window, lit: &lit, points: g, height: h, width: w, side: 3, free_per_pixel: 3, shared: 2 };
        let nats = 0.4;
        let got = similarity_pool(&volume, nats, 9);
        let root = |p: usize| -> Vec<f64> {
            let win = &window[p * g..(p + 1) * g];
            let least = win.iter().fold(f32::INFINITY, |a, &b| a.min(b)) as f64;
            let e: Vec<f64> = win.iter().map(|&c| (-(c as f64 - least) * nats as f64).exp()).collect();
            let total: f64 = e.iter().sum();
            e.iter().map(|v| (v / total).sqrt()).collect()
        };
        let mut pooled = 0;
        for i in 0..h {
            for j in 0..w {
                let p = i * w + j;
                let mut want: Vec<f64> = if lit[p] { window[p * g..(p + 1) * g].iter().map(|&v| v as f64).collect() } else { vec![0.0; g] };
                if lit[p] {
                    let rp = root(p);
                    for (a, b) in (-1i64..=1).flat_map(|a| (-1i64..=1).map(move |b| (a, b))).filter(|&d| d != (0, 0)) {
                        let (ii, jj) = (i as i64 + 3 * a, j as i64 + 3 * b);
                        if ii < 0 || jj < 0 || ii >= h as i64 || jj >= w as i64 || !lit[ii as usize * w + jj as usize] {
                            continue;
                        }
                        let q = ii as usize * w + jj as usize;
                        let bc: f64 = rp.iter().zip(root(q)).map(|(a, b)| a * b).sum::<f64>().min(1.0);
                        if p == lone || q == lone {
                            assert!(bc < 1e-3, "({i}, {j}) and its neighbour ({ii}, {jj}) share nothing: {bc}");
                        }
                        if bc > 1e-3 {
                            pooled += 1;
                            want.iter_mut().zip(&window[q * g..(q + 1) * g]).for_each(|(a, &b)| *a += bc * b as f64);
                        }
                    }
                }
                for k in 0..g {
                    let x = got[p * g + k] as f64;
                    assert!((x - want[k]).abs() <= 1e-4 * want[k].abs().max(1.0), "({i}, {j}, {k}): {x} against {}", want[k]);
                }
            }
        }
        assert!(pooled > 100, "{pooled} neighbouring windows pooled");
    }

    /// Evidence written into an earlier frame's buffers (here full of NaN, and of another
    /// size) is the evidence written into fresh ones, bit for bit, unlit pixels included.
    #[test]
    fn evidence_into_used_buffers_is_the_fresh_evidence() {
        let (h, w, g) = (5, 6, 8);
        let value = |p: usize, k: usize, salt: usize| ((p * 31 + k * 7 + salt * 13) % 17) as f32 * 0.75;
        let pixel: Vec<f32> = (0..h * w * g).map(|i| value(i / g, i % g, 1)).collect();
        let window: Vec<f32> = (0..h * w * g).map(|i| 3.0 * value(i / g, i % g, 2)).collect();
        let wide: Vec<f32> = (0..h * w * g).map(|i| 9.0 * value(i / g, i % g, 3)).collect();
        let lit: Vec<bool> = (0..h * w).map(|p| p % 5 != 2).collect();
        let intensity = Array2::from_shape_fn((h, w), |(i, j)| (i * w + j) as f32 + 0.5);
        let volume =
            CostVolume { pixel: &pixel, window: &window, lit: &lit, points: g, height: h, width: w, side: 3, free_per_pixel: 3, shared: 2 };
        let fresh = evidence_with(&volume, &intensity, 2, &[&wide]);
        let bits = |a: &Array3<f32>| a.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
        for (skip, features) in [(fresh.skip.len(), fresh.features.len()), (7, 3)] {
            let used = EvidenceBuffers { skip: vec![f32::NAN; skip], features: vec![f32::NAN; features] };
            let again = evidence_into(&volume, &intensity, 2, &[&wide], used);
            assert_eq!((bits(&again.skip), bits(&again.features)), (bits(&fresh.skip), bits(&fresh.features)));
            assert_eq!(again.noise.to_bits(), fresh.noise.to_bits());
        }
        // an unlit pixel has no evidence: zeros but its intensity
        let p = 2;
        assert!(fresh.skip.slice(ndarray::s![0, p, ..]).iter().all(|&v| v == 0.0));
        assert!(fresh.features.slice(ndarray::s![0, p, ..]).iter().enumerate().all(|(c, &v)| (v == 0.0) != (c == 4 * 2)));
    }
}
