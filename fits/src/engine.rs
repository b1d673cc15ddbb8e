//! The template-and-window-cost engine every fit of this crate runs on: a cost per pixel and
//! candidate (a range, a lifetime), summed over a square window of lit pixels by one separable
//! box filter ([`window_rows`], then [`window_total`] per pixel), the best candidate by one [`argmin`], and one refinement
//! between candidates: the parabola through the best and its neighbours ([`parabola_min`]),
//! or golden sections where the cost has kinks ([`golden`]).

use rayon::prelude::*;

/// The index of the smallest value (the first of equals; 0 for an empty slice).
pub fn argmin(v: &[f32]) -> usize {
    let mut best = 0;
    for (i, &x) in v.iter().enumerate() {
        if x < v[best] {
            best = i;
        }
    }
    best
}

/// The first pass of the box filter: every pixel's costs summed over the lit pixels of its
/// window's row (clipped at the frame's edges) into `rows`, resized and reused from call to
/// call. Unlit pixels' costs are not read. [`window_total`] is the second pass.
///
/// # Shapes
/// - `cost`: `[H·W·G]` (pixel-major, `G` candidates per pixel), `lit`: `[H·W]` → `rows`
///   `[H·W·G]`
pub fn window_rows(cost: &[f32], lit: &[bool], (h, w): (usize, usize), g: usize, window: usize, rows: &mut Vec<f32>) {
    assert!(cost.len() == h * w * g && lit.len() == h * w, "window_rows: cost [H·W·G], lit [H·W]");
    let half = window / 2;
    rows.clear();
    rows.resize(h * w * g, 0.0);
    rows.par_chunks_mut(w * g).enumerate().for_each(|(i, out)| {
        for j in 0..w {
            let o = &mut out[j * g..(j + 1) * g];
            for jj in j.saturating_sub(half)..(j + half + 1).min(w) {
                let q = i * w + jj;
                if lit[q] {
                    o.iter_mut().zip(&cost[q * g..(q + 1) * g]).for_each(|(a, b)| *a += b);
                }
            }
        }
    });
}

/// The second pass of the box filter for pixel `(i, j)`: its window's row sums
/// ([`window_rows`]) down the column, into `total` — the costs summed over the lit pixels of
/// its `window × window` neighbourhood, ready for [`argmin`].
///
/// # Shapes
/// - `rows`: `[H·W·G]` → `total`: `[G]`
pub fn window_total(rows: &[f32], (i, j): (usize, usize), (h, w): (usize, usize), window: usize, total: &mut [f32]) {
    let (g, half) = (total.len(), window / 2);
    total.fill(0.0);
    for ii in i.saturating_sub(half)..(i + half + 1).min(h) {
        total.iter_mut().zip(&rows[(ii * w + j) * g..(ii * w + j + 1) * g]).for_each(|(a, b)| *a += b);
    }
}

/// Both passes of the box filter for every pixel: its costs summed over the lit pixels of its
/// `window × window` neighbourhood, into `out` (resized; `rows` is the first pass's scratch).
///
/// # Shapes
/// - `cost`: `[H·W·G]`, `lit`: `[H·W]` → `out`: `[H·W·G]`
pub fn window_sums(cost: &[f32], lit: &[bool], (h, w): (usize, usize), g: usize, window: usize, rows: &mut Vec<f32>, out: &mut Vec<f32>) {
    window_rows(cost, lit, (h, w), g, window, rows);
    out.resize(h * w * g, 0.0);
    let rows = &*rows;
    out.par_chunks_mut(w * g).enumerate().for_each(|(i, row)| {
        for (j, total) in row.chunks_mut(g).enumerate() {
            window_total(rows, (i, j), (h, w), window, total);
        }
    });
}

/// The offset (within ±½ of the middle) of the minimum of the parabola through three costs
/// one candidate apart; 0 where they do not curve upwards or one is not finite.
pub fn parabola_min(lo: f64, mid: f64, hi: f64) -> f64 {
    let curv = lo - 2.0 * mid + hi;
    if curv > 0.0 && lo.is_finite() && hi.is_finite() {
        (0.5 * (lo - hi) / curv).clamp(-0.5, 0.5)
    } else {
        0.0
    }
}

/// The minimum over `u ∈ [best − 1, best + 1] ∩ [0, last]` of `cost(u)` by golden-section
/// search (the interval shrinks by 0.618 per iteration): `(u, cost)`.
pub fn golden(best: usize, last: usize, iterations: usize, cost: &mut dyn FnMut(f64) -> f64) -> (f64, f64) {
    let (mut lo, mut hi) = ((best as f64 - 1.0).max(0.0), (best as f64 + 1.0).min(last as f64));
    let phi = 0.5 * (5f64.sqrt() - 1.0);
    let (mut x1, mut x2) = (hi - phi * (hi - lo), lo + phi * (hi - lo));
    let (mut f1, mut f2) = (cost(x1), cost(x2));
    for _ in 0..iterations {
        if f1 <= f2 {
            hi = x2;
            x2 = x1;
            f2 = f1;
            x1 = hi - phi * (hi - lo);
            f1 = cost(x1);
        } else {
            lo = x1;
            x1 = x2;
            f1 = f2;
            x2 = lo + phi * (hi - lo);
            f2 = cost(x2);
        }
    }
    if f1 <= f2 {
        (x1, f1)
    } else {
        (x2, f2)
    }
}

/// [`golden`] for `N` minima at once, lane `l` within one of `best[l]`: `cost` evaluates every
/// lane at its own point (`[N]` → `[N]`). Each lane takes the steps [`golden`] takes, so the
/// answers are its, bit for bit, where the costs are: `[N]` of `(u, cost)`.
pub fn golden_lanes<const N: usize>(
    best: &[usize; N],
    last: usize,
    iterations: usize,
    cost: &mut dyn FnMut(&[f64; N], &mut [f64; N]),
) -> [(f64, f64); N] {
    let phi = 0.5 * (5f64.sqrt() - 1.0);
    let (mut lo, mut hi) = ([0f64; N], [0f64; N]);
    for l in 0..N {
        (lo[l], hi[l]) = ((best[l] as f64 - 1.0).max(0.0), (best[l] as f64 + 1.0).min(last as f64));
    }
    let (mut x1, mut x2) = ([0f64; N], [0f64; N]);
    for l in 0..N {
        (x1[l], x2[l]) = (hi[l] - phi * (hi[l] - lo[l]), lo[l] + phi * (hi[l] - lo[l]));
    }
    let (mut f1, mut f2) = ([0f64; N], [0f64; N]);
    cost(&x1, &mut f1);
    cost(&x2, &mut f2);
    let (mut x, mut f, mut left) = ([0f64; N], [0f64; N], [false; N]);
    for _ in 0..iterations {
        // every lane's next point, on the side golden's comparison sends it
        for l in 0..N {
            left[l] = f1[l] <= f2[l];
            if left[l] {
                hi[l] = x2[l];
                x2[l] = x1[l];
                f2[l] = f1[l];
                x1[l] = hi[l] - phi * (hi[l] - lo[l]);
                x[l] = x1[l];
            } else {
                lo[l] = x1[l];
                x1[l] = x2[l];
                f1[l] = f2[l];
                x2[l] = lo[l] + phi * (hi[l] - lo[l]);
                x[l] = x2[l];
            }
        }
        cost(&x, &mut f);
        for l in 0..N {
            if left[l] {
                f1[l] = f[l];
            } else {
                f2[l] = f[l];
            }
        }
    }
    std::array::from_fn(|l| if f1[l] <= f2[l] { (x1[l], f1[l]) } else { (x2[l], f2[l]) })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_box_filter_equals_the_direct_sum_over_lit_neighbours() {
        let (h, w, g) = (5, 6, 3);
        let cost: Vec<f32> = (0..h * w * g).map(|k| ((k * 7919) % 13) as f32).collect();
        let lit: Vec<bool> = (0..h * w).map(|p| p % 4 != 1).collect();
        let (mut rows, mut total) = (Vec::new(), vec![0f32; g]);
        for window in [1, 3, 5] {
            window_rows(&cost, &lit, (h, w), g, window, &mut rows);
            let half = window / 2;
            for i in 0..h {
                for j in 0..w {
                    window_total(&rows, (i, j), (h, w), window, &mut total);
                    for c in 0..g {
                        let mut want = 0.0;
                        for ii in i.saturating_sub(half)..(i + half + 1).min(h) {
                            for jj in j.saturating_sub(half)..(j + half + 1).min(w) {
                                if lit[ii * w + jj] {
                                    want += cost[(ii * w + jj) * g + c];
                                }
                            }
                        }
                        assert_eq!(total[c], want, "window {window} at ({i}, {j}, {c})");
                    }
                }
            }
        }
    }

    #[test]
    fn argmin_parabola_and_golden_find_minima() {
        assert_eq!(argmin(&[3.0, 1.0, 1.0, 2.0]), 1);
        assert_eq!(argmin(&[]), 0);
        // (x − 0.3)² sampled at −1, 0, 1
        let f = |x: f64| (x - 0.3) * (x - 0.3);
        assert!((parabola_min(f(-1.0), f(0.0), f(1.0)) - 0.3).abs() < 1e-12);
        assert_eq!(parabola_min(1.0, 2.0, 1.0), 0.0);
        assert_eq!(parabola_min(f64::INFINITY, 0.0, 1.0), 0.0);
        let (u, v) = golden(3, 10, 40, &mut |u| (u - 3.4) * (u - 3.4));
        assert!((u - 3.4).abs() < 1e-6 && v < 1e-12);
    }

    /// Golden sections in lanes are each lane's own golden sections, bit for bit: minima
    /// inside and at the ends of the range, a kink, a flat stretch (ties) and a NaN.
    #[test]
    fn golden_in_lanes_is_golden_per_lane() {
        let costs: [&dyn Fn(f64) -> f64; 4] = [
            &|u| (u - 3.4) * (u - 3.4),
            &|u| if u < 7.3 { 4.0 * (7.3 - u) } else { (u - 7.3) * 0.5 },
            &|u| (u - 1.0).abs().min(0.25),
            &|u| if (u - 5.0).abs() < 0.1 { f64::NAN } else { (u - 5.2).powi(2) },
        ];
        let best = [3, 7, 0, 10, 1, 5, 6, 10];
        let pick = |l: usize| costs[l % costs.len()];
        for iterations in [0, 1, 8] {
            let lanes = golden_lanes(&best, 10, iterations, &mut |x: &[f64; 8], out: &mut [f64; 8]| {
                for l in 0..8 {
                    out[l] = pick(l)(x[l]);
                }
            });
            for l in 0..8 {
                let (u, v) = golden(best[l], 10, iterations, &mut |u| pick(l)(u));
                assert_eq!((lanes[l].0.to_bits(), lanes[l].1.to_bits()), (u.to_bits(), v.to_bits()), "lane {l}, {iterations} steps");
            }
        }
    }
}
