//! The frame's onset and IRF width, fitted to its brightest pixels.

use super::*;
use crate::evidence::median;
use std::sync::atomic::{AtomicU64, Ordering};

/// The largest superpixel side (in blocks of the mosaic) that [`TapFitOptions::instrument_blocks`]
/// takes.
pub const MAX_INSTRUMENT_BLOCKS: usize = 64;

/// The photons (as the noise counts them: shot and read noise, and what texture there is) a
/// superpixel of the instrument's fit is to hold. With fewer, the lifetime fitted to each
/// (super)pixel along with the frame's onset fits its noise and biases the onset late (by
/// 0.5–1 ns at 400 e⁻ in the brightest tap, 40 e⁻ of read noise, through
/// `zoo:lifetime-flim-designed`'s codes: about 10 photons by this count). Chosen on the FLIm
/// sets of `scripts/ood.sh`: their frames at 0.8 of the full well count about 300–6 700
/// (every pixel alone), at 0.1 50–500 (1–3 blocks), at 0.02 6–50 (3–4 blocks), at 0.005 3–7
/// (4 blocks).
const INSTRUMENT_PHOTONS: f64 = 250.0;

/// The largest side [`instrument_side`] chooses: wider superpixels mix lifetimes, which biases
/// the IRF's width.
const AUTO_MAX_BLOCKS: usize = 4;

/// The side (in blocks of the mosaic) of the superpixels the instrument is fitted on, from the
/// frame's photons: 1 where its brightest pixels hold [`INSTRUMENT_PHOTONS`], else the side
/// whose superpixels do, up to 4 blocks and half the frame.
///
/// The photons come from the frame alone, whatever its units: two neighbouring pixels of one
/// subpixel type (a block apart) see nearly the same decay, so their normalised taps differ
/// by shot and read noise, `E Σ_k (r_k − r'_k)² ≈ g·(1/s + 1/s')·Σ_k r̄_k (1 − r̄_k)` for
/// charges `s = g·N` of `N` photons. Each of the brightest pixels takes the least of that ratio
/// over its neighbours of its type (an edge between lifetimes, or a texture, counts little);
/// the gain `g` is the median of those over the brightest pixels, corrected for taking the
/// least of four, and `N` their median charge over it.
///
/// # Shapes
/// - `r`: `[H·W][M]`, `weight`: `[H·W]` (0 where unlit), as the fit normalises a frame
pub fn instrument_side(r: &[f32], weight: &[f32], (m, h, w): (usize, usize, usize), (bh, bw): (usize, usize), brightest: usize) -> usize {
    side_of(r, weight, (m, h, w), (bh, bw), &brightest_of(weight, brightest))
}

/// [`instrument_side`] of the brightest pixels `bright` (as [`brightest_of`] gives them).
pub(super) fn side_of(r: &[f32], weight: &[f32], (m, h, w): (usize, usize, usize), (bh, bw): (usize, usize), bright: &[usize]) -> usize {
    side_for(frame_gain(r, weight, (m, h, w), (bh, bw), bright), (h, w), (bh, bw))
}

/// [`instrument_side`] from the frame's gain and its brightest pixels' median charge
/// ([`frame_gain`]'s; `None`: 1) for a frame of `h × w` pixels in blocks of `bh × bw`.
pub(super) fn side_for(gain: Option<(f64, f64)>, (h, w): (usize, usize), (bh, bw): (usize, usize)) -> usize {
    let most = AUTO_MAX_BLOCKS.min((h / bh.max(1)).min(w / bw.max(1)) / 2).max(1);
    match gain {
        Some((gain, charge)) if most > 1 => ((INSTRUMENT_PHOTONS / (charge / gain)).sqrt().ceil() as usize).clamp(1, most),
        _ => 1,
    }
}

/// The frame's gain `g` (charge per photon, as the noise counts photons) and the median charge
/// of the brightest pixels `bright`, from neighbouring pixels of one subpixel type (see
/// [`instrument_side`]); `None` where no pair of them is lit.
pub(super) fn frame_gain(
    r: &[f32],
    weight: &[f32],
    (m, h, w): (usize, usize, usize),
    (bh, bw): (usize, usize),
    bright: &[usize],
) -> Option<(f64, f64)> {
    let pair = |p: usize, q: usize| -> Option<f64> {
        let (sp, sq) = (weight[p] as f64, weight[q] as f64);
        if sq <= 0.0 {
            return None;
        }
        let (rp, rq) = (&r[p * m..(p + 1) * m], &r[q * m..(q + 1) * m]);
        let (mut d, mut v) = (0f64, 0f64);
        for (&a, &b) in rp.iter().zip(rq) {
            let (a, b) = (a as f64, b as f64);
            let mean = 0.5 * (a + b);
            d += (a - b) * (a - b);
            v += mean * (1.0 - mean);
        }
        (v > 0.0).then(|| d / ((1.0 / sp + 1.0 / sq) * v))
    };
    // each pixel's closest neighbour of its type (a block away: left, right, above, below),
    // so that an edge between lifetimes or a texture counts little
    let mut gains: Vec<f64> = bright
        .iter()
        .filter_map(|&p| {
            let (i, j) = (p / w, p % w);
            [(j + bw < w).then(|| p + bw), (j >= bw).then(|| p - bw), (i + bh < h).then(|| p + bh * w), (i >= bh).then(|| p - bh * w)]
                .into_iter()
                .flatten()
                .filter_map(|q| pair(p, q))
                .min_by(f64::total_cmp)
        })
        .collect();
    let mut charges: Vec<f64> = bright.iter().map(|&p| weight[p] as f64).collect();
    let by = |a: &f64, b: &f64| a.total_cmp(b);
    let (least, charge) = (median(&mut gains, by)?, median(&mut charges, by)?);
    // the median of the least of 4 ratios that are each χ² of M − 1 degrees of freedom over
    // M − 1 (times the gain): its quantile 1 − 0.5^¼ = 0.159 (z = −0.998), by Wilson–Hilferty
    let k = m.saturating_sub(1).max(1) as f64;
    let c = (1.0 - 2.0 / (9.0 * k) - 0.998 * (2.0 / (9.0 * k)).sqrt()).max(0.05).powi(3);
    let gain = least / c;
    (gain > 0.0 && gain.is_finite()).then_some((gain, charge))
}

/// The `n` lit (weight above 0) pixels of largest weight, brightest first (ties by index).
pub(super) fn brightest_of(weight: &[f32], n: usize) -> Vec<usize> {
    let mut bright: Vec<usize> = (0..weight.len()).filter(|&p| weight[p] > 0.0).collect();
    bright.sort_by(|&p, &q| weight[q].total_cmp(&weight[p]).then(p.cmp(&q)));
    bright.truncate(n);
    bright
}

/// A normalised frame's superpixels of `side × side` blocks of the mosaic: each subpixel type's
/// taps summed over a superpixel, normalised by their sum (the last row and column of
/// superpixels hold what is left of the frame). Superpixel `q` is of type `q mod (bh·bw)`.
///
/// # Shapes
/// - `f`: of `[M, H, W]` → taps `[Q·bh·bw][M]`, sums `[Q·bh·bw]`
pub(super) fn superpixels(f: &Normalised, (m, h, w): (usize, usize, usize), (bh, bw): (usize, usize), side: usize) -> (Vec<f32>, Vec<f32>) {
    let (sh, sw) = (side * bh, side * bw);
    let (nh, nw) = (h.div_ceil(sh), w.div_ceil(sw));
    let types = bh * bw;
    let n = nh * nw * types;
    let mut sums = vec![0f64; n * m];
    for p in (0..h * w).filter(|&p| f.weight[p] > 0.0) {
        let (i, j) = (p / w, p % w);
        let q = ((i / sh) * nw + j / sw) * types + subpixel_flat(p, w, (bh, bw));
        for k in 0..m {
            sums[q * m + k] += (f.r[p * m + k] * f.weight[p]) as f64;
        }
    }
    let mut r = vec![0f32; n * m];
    let mut weight = vec![0f32; n];
    for q in 0..n {
        let s: f64 = sums[q * m..(q + 1) * m].iter().sum();
        if s > 0.0 {
            weight[q] = s as f32;
            for k in 0..m {
                r[q * m + k] = (sums[q * m + k] / s) as f32;
            }
        }
    }
    (r, weight)
}

/// The frame's onset and IRF width: the cost of the brightest pixels, each at its best
/// lifetime of a coarse grid, over every bin of the cycle and every candidate width (the
/// templates of every shift at once, as a cyclic correlation of the sensor's rows with the
/// decays), then refined to a quarter bin around the best and by golden sections.
#[allow(clippy::too_many_arguments)]
pub(super) fn instrument(
    a: &ArrayView3<'_, f32>,
    c: Cycle,
    opts: &TapFitOptions,
    r: &[f32],
    weight: &[f32],
    bright: &[usize],
    m: usize,
    kind: &(dyn Fn(usize) -> usize + Sync),
    temperature: Option<f64>,
) -> (f64, f64) {
    let widths = &opts.irf_fwhm_s;
    if bright.is_empty() {
        return (opts.onset_s.unwrap_or(0.0).rem_euclid(c.period_s), widths[0]);
    }
    // the brightest pixels' normalised taps, weights and types
    let pixels: Vec<(Vec<f32>, f32, usize)> = bright.iter().map(|&p| (r[p * m..(p + 1) * m].to_vec(), weight[p], kind(p))).collect();
    // (on the grid of half steps: the templates are linear between its points)
    let full = grid(opts, 2 * opts.points - 1);
    let frame_cost = |t0: f64, fwhm: f64| -> f64 {
        brightest_cost(
            &TypeTable::of(&Templates::new(a, &decays(c, &full, t0, fwhm))),
            &pixels,
            usize::MAX,
            16,
            opts.background,
            temperature,
        )
    };
    let score = |cands: &[(f64, f64)]| -> (f64, f64, f64) {
        cands
            .par_iter()
            .map(|&(t0, f)| (frame_cost(t0, f), t0, f))
            .min_by(|x, y| x.0.total_cmp(&y.0).then(x.1.total_cmp(&y.1)).then(x.2.total_cmp(&y.2)))
            .unwrap_or((0.0, 0.0, widths[0]))
    };
    if let Some(t0) = opts.onset_s {
        let known: Vec<(f64, f64)> = widths.iter().map(|&f| (t0.rem_euclid(c.period_s), f)).collect();
        let (_, t0, f) = score(&known);
        return (t0, f);
    }
    // every bin of the cycle and every width: the coarse grid's tables, the same for every
    // frame through this sensor (built once, see `coarse_tables`)
    let bins = c.bins;
    let coarse = coarse_tables(a, c, opts);
    let mut coarse_cands: Vec<(usize, usize)> = (0..widths.len()).flat_map(|wi| (0..bins).map(move |j| (wi, j))).collect();
    // (the candidates in the order of a cheap look, the brightest 16 pixels on the grid alone,
    // so that the first searched set a low bound: a candidate is left as soon as its running
    // cost passes the least total found, which it could then only exceed: the same answer)
    let glance: Vec<f64> = coarse_cands
        .par_iter()
        .map(|&(wi, j)| brightest_cost(&coarse.tables[wi * bins + j], &pixels, 16, 0, opts.background, temperature))
        .collect();
    let mut order: Vec<usize> = (0..coarse_cands.len()).collect();
    order.sort_by(|&x, &y| glance[x].total_cmp(&glance[y]).then(x.cmp(&y)));
    coarse_cands = order.iter().map(|&k| coarse_cands[k]).collect();
    let least = AtomicU64::new(f64::INFINITY.to_bits());
    let (_, _, j) = coarse_cands
        .par_iter()
        .filter_map(|&(wi, j)| {
            let bound = f64::from_bits(least.load(Ordering::Relaxed));
            let cost = brightest_cost_within(&coarse.tables[wi * bins + j], &pixels, 128, 10, opts.background, bound, temperature)?;
            // (non-negative: the bits order as the numbers)
            least.fetch_min(cost.to_bits(), Ordering::Relaxed);
            Some((cost, wi, j))
        })
        .min_by(|x, y| x.0.total_cmp(&y.0).then(x.2.cmp(&y.2)).then(x.1.cmp(&y.1)))
        .unwrap_or((0.0, 0, 0));
    // then every width within a bin of the best, a quarter bin apart
    let t0 = j as f64 * c.dt_s;
    let fine: Vec<(f64, f64)> =
        (-4..=4).flat_map(|q| widths.iter().map(move |&w| ((t0 + q as f64 * 0.25 * c.dt_s).rem_euclid(c.period_s), w))).collect();
    let (_, t0, f) = score(&fine);
    // then continuously, by golden sections: the onset within a quarter bin, the width within a
    // quarter nanosecond
    let q = 0.25 * c.dt_s;
    let t0 = (t0 + (golden(1, 2, 12, &mut |u| frame_cost(t0 + (u - 1.0) * q, f)).0 - 1.0) * q).rem_euclid(c.period_s);
    let max_w = widths.iter().fold(0f64, |a, &b| a.max(b));
    let f = if widths.len() > 1 {
        let (lo, hi) = ((f - 0.25e-9).max(0.0), (f + 0.25e-9).min(max_w));
        lo + (hi - lo) * 0.5 * golden(1, 2, 12, &mut |u| frame_cost(t0, lo + (hi - lo) * 0.5 * u)).0
    } else {
        f
    };
    (t0, f)
}

/// The instrument search's coarse tables: for every candidate width `wi` and onset bin `j`,
/// the tables of every subpixel type on a coarse grid of 32 lifetimes,
/// `tables[wi·T + j]`. They depend on the sensor's matrix and the options only, not on the
/// frame.
struct CoarseTables {
    /// What they were built from: the matrix `[N·M·T]` (bits), its dims, the bin width, the
    /// lifetimes searched and the widths (bits).
    key: (Vec<u32>, [usize; 3], u64, [u64; 2], Vec<u64>),
    tables: Vec<Vec<TypeTable>>,
}

/// The coarse tables of [`CoarseTables`] for this matrix and these options: the last ones
/// built, when they were built from the same (a stream's frames, a training run's items: the
/// search over every onset bin took 168 M multiply-adds a frame at T = 256, whatever its
/// size), else built and kept.
///
/// The decays at onset 0 shifted by whole bins go through every row of the sensor at once:
/// `corr[w][n·M + k][i][j] = Σ_t A[n][k][t]·D_i(t − j)`.
fn coarse_tables(a: &ArrayView3<'_, f32>, c: Cycle, opts: &TapFitOptions) -> std::sync::Arc<CoarseTables> {
    static LAST: std::sync::Mutex<Option<std::sync::Arc<CoarseTables>>> = std::sync::Mutex::new(None);
    let (n_types, m, bins) = a.dim();
    let widths = &opts.irf_fwhm_s;
    let key = (
        a.iter().map(|v| v.to_bits()).collect::<Vec<u32>>(),
        [n_types, m, bins],
        c.dt_s.to_bits(),
        opts.tau_range_s.map(f64::to_bits),
        widths.iter().map(|w| w.to_bits()).collect::<Vec<u64>>(),
    );
    if let Some(last) = LAST.lock().unwrap_or_else(|e| e.into_inner()).as_ref().filter(|t| t.key == key) {
        return last.clone();
    }
    let coarse = grid(opts, 32);
    let g = coarse.len();
    let rows: Vec<Vec<f32>> = (0..n_types * m).map(|nk| (0..bins).map(|t| a[(nk / m, nk % m, t)]).collect()).collect();
    let corr: Vec<Vec<f32>> = widths
        .par_iter()
        .map(|&f| {
            let curves = decays(c, &coarse, 0.0, f);
            let mut out = vec![0f32; n_types * m * g * bins];
            for (i, d) in curves.iter().enumerate() {
                // e[s] = D_i(−s), doubled so that e[j − t + T] needs no wrap: D_i(t − j) = e[j − t]
                let e: Vec<f32> = (0..2 * bins).map(|s| d[(2 * bins - s) % bins] as f32).collect();
                crate::simd(
                    #[inline(always)]
                    || {
                        for (nk, row) in rows.iter().enumerate() {
                            correlate(row, &e, &mut out[(nk * g + i) * bins..(nk * g + i + 1) * bins]);
                        }
                    },
                )
            }
            out
        })
        .collect();
    let sums: Vec<f64> = rows.iter().map(|row| row.iter().map(|&v| v as f64).sum()).collect();
    let tables = (0..widths.len() * bins)
        .into_par_iter()
        .map(|q| {
            let (wi, j) = (q / bins, q % bins);
            let proj: Vec<f64> = (0..n_types * m * g).map(|r| corr[wi][r * bins + j] as f64).collect();
            TypeTable::from_projections(&proj, &sums, n_types, m, g)
        })
        .collect();
    let built = std::sync::Arc::new(CoarseTables { key, tables });
    *LAST.lock().unwrap_or_else(|e| e.into_inner()) = Some(built.clone());
    built
}

/// One row of the sensor `row` `[T]` against one doubled, reversed decay `e` `[2T]`:
/// `o[j] = Σ_t row[t]·e[j − t + T]` `[T]`, summed in the order of `t` (skipping the zeros of
/// the row), sixteen outputs at a time in registers (the plain loop over `j` for every `t`
/// did not vectorise: a fifth of a stream's start-up).
#[inline(always)]
fn correlate(row: &[f32], e: &[f32], o: &mut [f32]) {
    const L: usize = 16;
    let bins = row.len();
    assert!(e.len() == 2 * bins && o.len() == bins, "correlate: [T], [2T] → [T]");
    let taps: Vec<(usize, f32)> = row.iter().copied().enumerate().filter(|&(_, at)| at != 0.0).collect();
    let mut j0 = 0;
    while j0 < bins {
        let l = L.min(bins - j0);
        let mut acc = [0f32; L];
        if l == L {
            for &(t, at) in &taps {
                let seg: &[f32; L] = e[bins - t + j0..bins - t + j0 + L].try_into().expect("L values");
                for (a, &v) in acc.iter_mut().zip(seg) {
                    *a += at * v;
                }
            }
        } else {
            for &(t, at) in &taps {
                for (a, &v) in acc[..l].iter_mut().zip(&e[bins - t + j0..bins - t + j0 + l]) {
                    *a += at * v;
                }
            }
        }
        o[j0..j0 + l].copy_from_slice(&acc[..l]);
        j0 += l;
    }
}

/// The cost of the first `count` of `pixels` (normalised taps, weight, type), each at its best
/// lifetime of `tables`, between the grid's points by `refine` golden sections (a grid's steps
/// bias the onset: at the lower cost of a later onset and a shorter lifetime, the coarse
/// search placed a paper scene's onset 1.2 ns late with a parabola instead).
///
/// At a `temperature`, their [`mixture_cost`] instead: the mixture's components sit on the
/// grid's points, and `refine` is not used.
pub(super) fn brightest_cost(
    tables: &[TypeTable],
    pixels: &[(Vec<f32>, f32, usize)],
    count: usize,
    refine: usize,
    background: bool,
    temperature: Option<f64>,
) -> f64 {
    brightest_cost_within(tables, pixels, count, refine, background, f64::INFINITY, temperature).unwrap_or(f64::INFINITY)
}

/// [`brightest_cost`], left (`None`) as soon as the running total passes `bound`: every
/// pixel's cost is non-negative, so the total would have exceeded `bound`. Otherwise the same
/// number, bit for bit.
pub(super) fn brightest_cost_within(
    tables: &[TypeTable],
    pixels: &[(Vec<f32>, f32, usize)],
    count: usize,
    refine: usize,
    background: bool,
    bound: f64,
    temperature: Option<f64>,
) -> Option<f64> {
    if let Some(t) = temperature {
        return mixture_cost(tables, pixels, count, background, t, bound);
    }
    let g = tables[0].points;
    let mut cost = vec![0f32; g];
    let mut beta = vec![0f32; g];
    let mut between = Between::new(tables.len(), pixels.first().map_or(0, |p| p.0.len()));
    let mut total = 0.0;
    for (r, w, n) in pixels.iter().take(count) {
        tables[*n].costs(r, *w, background, &mut beta, &mut cost);
        let best = argmin(&cost);
        let c0 = cost[best] as f64;
        total += if best == 0 || best + 1 == g {
            c0
        } else if refine > 0 {
            let (_, v) = golden(best, g - 1, refine, &mut |u| {
                between.set_one(tables, *n, u);
                between.cost(*n, r, *w, background).0 as f64
            });
            v.min(c0)
        } else {
            c0
        };
        if total > bound {
            return None;
        }
    }
    Some(total)
}

/// Background shares of the mixture's components ([`mixture_cost`]).
/// (Fine at low shares: a frame's background is most often a few per cent of its charge.)
const SHARES: [f32; 18] = [0.0, 0.01, 0.02, 0.03, 0.05, 0.07, 0.1, 0.13, 0.17, 0.22, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0];

/// EM iterations of the mixture's weights ([`mixture_cost`]).
const MIXTURE_ITERATIONS: usize = 24;

/// The negative log-likelihood of the first `count` of `pixels` under one mixture of
/// (lifetime, background share) components shared by the frame, its weights `π` fitted by EM:
/// pixel `p`'s cost of component `k` is `c_pk` (its taps against the component's, times its
/// charge), its likelihood `exp(−c_pk / 2t)` at the temperature `t` of a tap's noise, and the
/// frame's cost `Σ_p −ln Σ_k π_k exp(−c_pk / 2t)`.
///
/// A lifetime and a background share fitted to each pixel alone (its least cost) bias a dim
/// frame's onset late: the pixels' own nuisances fit the noise the better at later onsets (see
/// docs/lifetimes.md, "Where the dim-light onset's lateness comes from"). The mixture's weights
/// are the frame's, as many as the components whatever the pixels, and the noise does not fit
/// them. `None` as soon as its lower bound, every pixel at its least cost, passes `bound` (each
/// pixel's term is at least that: `π` sums to 1 and every likelihood is at most 1 there).
fn mixture_cost(
    tables: &[TypeTable],
    pixels: &[(Vec<f32>, f32, usize)],
    count: usize,
    background: bool,
    t: f64,
    bound: f64,
) -> Option<f64> {
    let shares: &[f32] = if background { &SHARES } else { &SHARES[..1] };
    let k_n = tables[0].points * shares.len();
    let pixels = &pixels[..count.min(pixels.len())];
    let mut lik = vec![0f64; pixels.len() * k_n];
    let mut cost = vec![0f32; k_n];
    let mut floor = 0.0;
    for (p, (r, w, n)) in pixels.iter().enumerate() {
        tables[*n].costs_at_shares(r, *w, shares, &mut cost);
        let least = cost.iter().fold(f32::INFINITY, |a, &b| a.min(b)) as f64;
        floor += least / (2.0 * t);
        for (l, &c) in lik[p * k_n..(p + 1) * k_n].iter_mut().zip(&cost) {
            *l = (-(c as f64 - least) / (2.0 * t)).exp();
        }
        if floor > bound {
            return None;
        }
    }
    let mut pi = vec![1.0 / k_n as f64; k_n];
    let mut next = vec![0f64; k_n];
    for _ in 0..MIXTURE_ITERATIONS {
        next.fill(0.0);
        for l in lik.chunks_exact(k_n) {
            let z: f64 = l.iter().zip(&pi).map(|(a, b)| a * b).sum();
            if z > 0.0 {
                for ((o, a), b) in next.iter_mut().zip(l).zip(&pi) {
                    *o += a * b / z;
                }
            }
        }
        let total: f64 = next.iter().sum();
        if !(total > 0.0) {
            break;
        }
        pi.iter_mut().zip(&next).for_each(|(p, v)| *p = v / total);
    }
    let evidence: f64 = lik.chunks_exact(k_n).map(|l| -l.iter().zip(&pi).map(|(a, b)| a * b).sum::<f64>().max(1e-300).ln()).sum();
    Some(floor + evidence)
}

#[cfg(test)]
mod tests {
    use super::{brightest_cost, brightest_cost_within, correlate, TypeTable};

    /// A candidate is left only when its total would pass the bound: at or above its total it
    /// gives the total bit for bit, below it nothing (the costs are non-negative, so the
    /// running total only grows); with and without the refinement and the background.
    #[test]
    fn a_search_left_past_its_bound_is_the_total_or_more() {
        let (types, m, points) = (4, 4, 24);
        let value = |i: usize| ((i * 7919 + 13) % 101) as f64 / 101.0 + 0.05;
        let tables = TypeTable::build(types, m, points, |n, k, i| value(n * 1000 + k * 100 + i), |n, k| value(n * 37 + k + 5000));
        let pixels: Vec<(Vec<f32>, f32, usize)> = (0..40)
            .map(|p| {
                let r: Vec<f32> = (0..m).map(|k| value(p * 17 + k * 3 + 900) as f32).collect();
                let total: f32 = r.iter().sum();
                (r.iter().map(|v| v / total).collect(), 50.0 + p as f32, p % types)
            })
            .collect();
        for (refine, background) in [(0, false), (10, true), (16, false)] {
            let full = brightest_cost(&tables, &pixels, usize::MAX, refine, background, None);
            assert!(full > 0.0 && full.is_finite());
            for bound in [full, full * 1.5, f64::INFINITY] {
                let got = brightest_cost_within(&tables, &pixels, usize::MAX, refine, background, bound, None);
                assert_eq!(got.map(f64::to_bits), Some(full.to_bits()), "bound {bound} at total {full}");
            }
            for bound in [full * (1.0 - 1e-9), full * 0.5, 0.0] {
                assert_eq!(
                    brightest_cost_within(&tables, &pixels, usize::MAX, refine, background, bound, None),
                    None,
                    "bound {bound} below {full}"
                );
            }
        }
    }

    /// The register-blocked correlation gives the plain loop's numbers bit for bit (same sum
    /// order per output), on lengths with and without a remainder and rows with zeros.
    #[test]
    fn the_blocked_correlation_is_the_plain_loop_bit_for_bit() {
        for bins in [5usize, 16, 37, 256] {
            let row: Vec<f32> = (0..bins).map(|t| if t % 3 == 1 { 0.0 } else { ((t * 7919) % 101) as f32 / 37.0 - 1.1 }).collect();
            let e: Vec<f32> = (0..2 * bins).map(|s| (((s * 104729) % 997) as f32 / 311.0).exp() * 1e-3).collect();
            let mut plain = vec![0f32; bins];
            for (t, &at) in row.iter().enumerate() {
                if at != 0.0 {
                    plain.iter_mut().zip(&e[bins - t..2 * bins - t]).for_each(|(o, &ev)| *o += at * ev);
                }
            }
            let mut blocked = vec![f32::NAN; bins];
            correlate(&row, &e, &mut blocked);
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&blocked), bits(&plain), "{bins} bins");
            // and it is the correlation: o[j] = Σ_t row[t]·e[j − t + T]
            let j = bins / 2;
            let want: f64 = (0..bins).map(|t| row[t] as f64 * e[j + bins - t] as f64).sum();
            assert!((blocked[j] as f64 - want).abs() <= 1e-4 * want.abs().max(1.0), "{} against {want}", blocked[j]);
        }
    }
}
