//! The lifetime fit's templates: for every subpixel type, the taps of a decay of each
//! lifetime of the grid (with the IRF), as tables of cost terms, and the templates between the
//! grid's half steps.

use super::*;

/// Normalised templates `g(τ_i)` per subpixel type and tap, `[G][N·M]`, plus `g(bg)` `[N·M]`.
pub(super) struct Templates {
    pub(super) g: Vec<f64>,
    pub(super) bg: Vec<f64>,
    pub(super) nm: usize,
    pub(super) m: usize,
}

impl Templates {
    /// The templates of decays `curves[i]` (bins of one cycle) through `A`.
    pub(super) fn new(a: &ArrayView3<'_, f32>, curves: &[Vec<f64>]) -> Templates {
        let (n, m, t) = a.dim();
        let nm = n * m;
        let rows: Vec<Vec<f64>> = (0..nm).map(|q| (0..t).map(|j| a[(q / m, q % m, j)] as f64).collect()).collect();
        let project = |d: &[f64]| -> Vec<f64> {
            let mut g = vec![0.0; nm];
            for ni in 0..n {
                let row: Vec<f64> = (0..m).map(|mi| rows[ni * m + mi].iter().zip(d).map(|(a, d)| a * d).sum()).collect();
                let s: f64 = row.iter().sum::<f64>().max(1e-300);
                for mi in 0..m {
                    g[ni * m + mi] = row[mi] / s;
                }
            }
            g
        };
        let g = curves.iter().flat_map(|d| project(d)).collect();
        let bg = project(&vec![1.0; t]);
        Templates { g, bg, nm, m }
    }

    pub(super) fn points(&self) -> usize {
        self.g.len() / self.nm
    }

    #[cfg(test)]
    /// Cost of lifetime `i` for normalised taps `r` of subpixel type `n` weighted by `w`, and
    /// the background share it takes.
    #[inline]
    pub(super) fn cost(&self, i: usize, n: usize, r: &[f64], w: f64, background: bool) -> (f64, f64) {
        self.cost_of(&self.g[i * self.nm + n * self.m..i * self.nm + (n + 1) * self.m], n, r, w, background)
    }

    #[cfg(test)]
    /// The template of type `n` at the fractional grid position `u` (Catmull-Rom between the
    /// grid's templates, which are smooth in `ln τ`), into `out` `[M]`.
    #[inline]
    pub(super) fn at(&self, u: f64, n: usize, out: &mut [f64]) {
        let last = self.points() - 1;
        let u = u.clamp(0.0, last as f64);
        let i = (u.floor() as usize).min(last.saturating_sub(1));
        let f = u - i as f64;
        let idx = |k: isize| (i as isize + k).clamp(0, last as isize) as usize;
        let w = [
            (-f + 2.0 * f * f - f * f * f) / 2.0,
            (2.0 - 5.0 * f * f + 3.0 * f * f * f) / 2.0,
            (f + 4.0 * f * f - 3.0 * f * f * f) / 2.0,
            (-f * f + f * f * f) / 2.0,
        ];
        for (k, o) in out.iter_mut().enumerate() {
            *o = (0..4).map(|q| w[q] * self.g[idx(q as isize - 1) * self.nm + n * self.m + k]).sum();
        }
    }

    #[cfg(test)]
    /// [`Self::cost`] for a given template `g` `[M]` of type `n`.
    #[inline]
    pub(super) fn cost_of(&self, g: &[f64], n: usize, r: &[f64], w: f64, background: bool) -> (f64, f64) {
        let b = &self.bg[n * self.m..(n + 1) * self.m];
        let beta = if background {
            let (mut num, mut den) = (0.0, 0.0);
            for k in 0..self.m {
                let e = b[k] - g[k];
                num += (r[k] - g[k]) * e;
                den += e * e;
            }
            if den > 1e-300 {
                (num / den).clamp(0.0, 1.0)
            } else {
                0.0
            }
        } else {
            0.0
        };
        let mut c = 0.0;
        for k in 0..self.m {
            let e = r[k] - (1.0 - beta) * g[k] - beta * b[k];
            c += e * e;
        }
        (w * c, beta)
    }
}

/// The lifetime grid (log-spaced) of the options.
pub(super) fn grid(opts: &TapFitOptions, points: usize) -> Vec<f64> {
    let (lo, hi) = (opts.tau_range_s[0].ln(), opts.tau_range_s[1].ln());
    (0..points).map(|i| (lo + (hi - lo) * i as f64 / (points - 1) as f64).exp()).collect()
}

/// IRF-convolved periodic decays with onset `t0` for each lifetime of `taus`.
pub(super) fn decays(c: Cycle, taus: &[f64], t0: f64, fwhm: f64) -> Vec<Vec<f64>> {
    let k = IrfKernel::gaussian(c, fwhm);
    taus.iter().map(|&tau| k.apply(&decay_bin_averages(c, tau, t0))).collect()
}

/// The normalised templates of one subpixel type on a lifetime grid, struct of arrays:
/// `g[k·G + i]` (tap `k`, lifetime `i`), `d = g(bg) − g` likewise and `1/‖d_i‖²`.
pub(super) struct TypeTable {
    pub(super) g: Vec<f32>,
    pub(super) d: Vec<f32>,
    pub(super) inv_dd: Vec<f32>,
    pub(super) points: usize,
}

impl TypeTable {
    /// The tables of every subpixel type from `Templates` (`[G][N·M]`).
    pub(super) fn of(t: &Templates) -> Vec<TypeTable> {
        let m = t.m;
        TypeTable::build(t.nm / m, m, t.points(), |n, k, i| t.g[i * t.nm + n * m + k], |n, k| t.bg[n * m + k])
    }

    /// The tables from raw projections `proj` `[N][M][G]` of the curves through the sensor's
    /// rows and the rows' sums `[N·M]` (the background's projection).
    pub(super) fn from_projections(proj: &[f64], sums: &[f64], types: usize, m: usize, points: usize) -> Vec<TypeTable> {
        let curve_sum = |n: usize, i: usize| (0..m).map(|k| proj[(n * m + k) * points + i]).sum::<f64>().max(1e-300);
        let bg_sum = |n: usize| sums[n * m..(n + 1) * m].iter().sum::<f64>().max(1e-300);
        TypeTable::build(types, m, points, |n, k, i| proj[(n * m + k) * points + i] / curve_sum(n, i), |n, k| sums[n * m + k] / bg_sum(n))
    }

    /// The tables of `types` subpixel types from the normalised template of type `n`, tap `k`,
    /// point `i` and the normalised background's of type `n`, tap `k`.
    pub(super) fn build(
        types: usize,
        m: usize,
        points: usize,
        g_at: impl Fn(usize, usize, usize) -> f64,
        bg_at: impl Fn(usize, usize) -> f64,
    ) -> Vec<TypeTable> {
        (0..types)
            .map(|n| {
                let mut g = vec![0f32; m * points];
                let mut d = vec![0f32; m * points];
                let mut inv_dd = vec![0f32; points];
                for i in 0..points {
                    let mut dd = 0.0;
                    for k in 0..m {
                        let gi = g_at(n, k, i);
                        let e = bg_at(n, k) - gi;
                        g[k * points + i] = gi as f32;
                        d[k * points + i] = e as f32;
                        dd += e * e;
                    }
                    inv_dd[i] = if dd > 1e-300 { (1.0 / dd) as f32 } else { 0.0 };
                }
                TypeTable { g, d, inv_dd, points }
            })
            .collect()
    }

    /// The cost of every lifetime for normalised taps `r` `[M]` weighted by `w`, into
    /// `out` `[G]`; `beta` `[G]` is scratch. Loops over the lifetimes innermost (vectorised).
    pub(super) fn costs(&self, r: &[f32], w: f32, background: bool, beta: &mut [f32], out: &mut [f32]) {
        let g = self.points;
        if background {
            beta.fill(0.0);
            for (k, &rk) in r.iter().enumerate() {
                let (gk, dk) = (&self.g[k * g..(k + 1) * g], &self.d[k * g..(k + 1) * g]);
                for i in 0..g {
                    beta[i] += (rk - gk[i]) * dk[i];
                }
            }
            for (b, &inv) in beta.iter_mut().zip(&self.inv_dd) {
                *b = (*b * inv).clamp(0.0, 1.0);
            }
        }
        out.fill(0.0);
        for (k, &rk) in r.iter().enumerate() {
            let (gk, dk) = (&self.g[k * g..(k + 1) * g], &self.d[k * g..(k + 1) * g]);
            if background {
                for i in 0..g {
                    let e = rk - gk[i] - beta[i] * dk[i];
                    out[i] += e * e;
                }
            } else {
                for i in 0..g {
                    let e = rk - gk[i];
                    out[i] += e * e;
                }
            }
        }
        for v in out.iter_mut() {
            *v *= w;
        }
    }

    /// The cost of lifetime `i` alone and its background share.
    pub(super) fn cost_at(&self, i: usize, r: &[f32], w: f32, background: bool) -> (f32, f32) {
        let g = self.points;
        let beta = if background {
            let mut num = 0.0;
            for (k, &rk) in r.iter().enumerate() {
                num += (rk - self.g[k * g + i]) * self.d[k * g + i];
            }
            (num * self.inv_dd[i]).clamp(0.0, 1.0)
        } else {
            0.0
        };
        let mut c = 0.0;
        for (k, &rk) in r.iter().enumerate() {
            let e = rk - self.g[k * g + i] - beta * self.d[k * g + i];
            c += e * e;
        }
        (w * c, beta)
    }
}

/// The templates of every subpixel type at one fractional grid position, linear between the
/// grid's points: `g` and `d` `[N][M]`, `1/‖d‖²` `[N]`.
pub(super) struct Between {
    pub(super) g: Vec<f32>,
    pub(super) d: Vec<f32>,
    pub(super) inv_dd: Vec<f32>,
    pub(super) m: usize,
}

impl Between {
    pub(super) fn new(types: usize, m: usize) -> Self {
        Between { g: vec![0.0; types * m], d: vec![0.0; types * m], inv_dd: vec![0.0; types], m }
    }

    /// The templates at grid position `u` of `tables` (one per type).
    pub(super) fn set(&mut self, tables: &[TypeTable], u: f64) {
        for t in 0..tables.len() {
            self.set_one(tables, t, u);
        }
    }

    /// [`Self::set`] for type `t` alone.
    pub(super) fn set_one(&mut self, tables: &[TypeTable], t: usize, u: f64) {
        let (m, table) = (self.m, &tables[t]);
        let n = table.points;
        let u = u.clamp(0.0, (n - 1) as f64);
        let i = (u as usize).min(n - 2);
        let f = (u - i as f64) as f32;
        let mut dd = 0.0;
        for k in 0..m {
            let (g0, g1) = (table.g[k * n + i], table.g[k * n + i + 1]);
            let (d0, d1) = (table.d[k * n + i], table.d[k * n + i + 1]);
            let d = d0 + f * (d1 - d0);
            self.g[t * m + k] = g0 + f * (g1 - g0);
            self.d[t * m + k] = d;
            dd += d * d;
        }
        self.inv_dd[t] = if dd > 0.0 { 1.0 / dd } else { 0.0 };
    }

    /// The cost of normalised taps `r` `[M]` of type `n` weighted by `w`, and the background
    /// share it takes.
    #[inline]
    pub(super) fn cost(&self, n: usize, r: &[f32], w: f32, background: bool) -> (f32, f32) {
        let (g, d) = (&self.g[n * self.m..(n + 1) * self.m], &self.d[n * self.m..(n + 1) * self.m]);
        let beta = if background {
            let num: f32 = r.iter().zip(g).zip(d).map(|((r, g), d)| (r - g) * d).sum();
            (num * self.inv_dd[n]).clamp(0.0, 1.0)
        } else {
            0.0
        };
        let c: f32 = r.iter().zip(g).zip(d).map(|((r, g), d)| (r - g - beta * d) * (r - g - beta * d)).sum();
        (w * c, beta)
    }
}
