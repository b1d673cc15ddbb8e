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
#[derive(Clone)]
pub(super) struct TypeTable {
    pub(super) g: Vec<f32>,
    pub(super) d: Vec<f32>,
    pub(super) inv_dd: Vec<f32>,
    pub(super) points: usize,
    /// The same, point-major for the refinement's reads of two neighbouring points:
    /// `[G][g[M], d[M]]`.
    pm: Vec<f32>,
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
                let mut pm = vec![0f32; 2 * m * points];
                for i in 0..points {
                    for k in 0..m {
                        pm[2 * m * i + k] = g[k * points + i];
                        pm[2 * m * i + m + k] = d[k * points + i];
                    }
                }
                TypeTable { g, d, inv_dd, points, pm }
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

    /// The cost of every lifetime at each background share of `shares` for normalised taps `r`
    /// `[M]` weighted by `w`, into `out` `[G·J]` (lifetime-major: `out[i·J + j]`), `J` the shares.
    pub(super) fn costs_at_shares(&self, r: &[f32], w: f32, shares: &[f32], out: &mut [f32]) {
        let (g, j_n) = (self.points, shares.len());
        for i in 0..g {
            let (mut c0, mut pd, mut dd) = (0f32, 0f32, 0f32);
            for (k, &rk) in r.iter().enumerate() {
                let (e, d) = (rk - self.g[k * g + i], self.d[k * g + i]);
                c0 += e * e;
                pd += e * d;
                dd += d * d;
            }
            for (o, &b) in out[i * j_n..(i + 1) * j_n].iter_mut().zip(shares) {
                *o = w * (c0 - 2.0 * b * pd + b * b * dd).max(0.0);
            }
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
    #[inline]
    pub(super) fn set_one(&mut self, tables: &[TypeTable], t: usize, u: f64) {
        let (m, table) = (self.m, &tables[t]);
        let n = table.points;
        let (i, f) = between_points(u, n);
        let (g, d) = (&mut self.g[t * m..(t + 1) * m], &mut self.d[t * m..(t + 1) * m]);
        let pm = &table.pm[2 * m * i..2 * m * (i + 2)];
        let dd = match m {
            2 => lerp_fixed::<2>(pm, f, g, d),
            4 => lerp_fixed::<4>(pm, f, g, d),
            8 => lerp_fixed::<8>(pm, f, g, d),
            _ => lerp_any(pm, m, f, g, d),
        };
        self.inv_dd[t] = if dd > 0.0 { 1.0 / dd } else { 0.0 };
    }

    /// [`Self::set_one`] as first written, reading the tap-major tables (the reference the
    /// fixed-size paths are tested against).
    #[cfg(test)]
    pub(super) fn set_one_reference(&mut self, tables: &[TypeTable], t: usize, u: f64) {
        let (m, table) = (self.m, &tables[t]);
        let n = table.points;
        let (i, f) = between_points(u, n);
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
        let inv = self.inv_dd[n];
        match self.m {
            2 => cost_fixed::<2>(g, d, inv, r, w, background),
            4 => cost_fixed::<4>(g, d, inv, r, w, background),
            8 => cost_fixed::<8>(g, d, inv, r, w, background),
            _ => cost_any(g, d, inv, r, w, background),
        }
    }

    /// [`Self::cost`] as first written (the reference of the fixed-size paths).
    #[cfg(test)]
    pub(super) fn cost_reference(&self, n: usize, r: &[f32], w: f32, background: bool) -> (f32, f32) {
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

/// Grid position `u` of a grid of `n` points (clamped to it) as the point `i` it follows and
/// the fraction `f` of the way to `i + 1` (the last step's end is `f = 1`).
#[inline]
fn between_points(u: f64, n: usize) -> (usize, f32) {
    let u = u.clamp(0.0, (n - 1) as f64);
    let i = (u as usize).min(n - 2);
    (i, (u - i as f64) as f32)
}

/// Pixels whose refinements run together, one in each lane ([`LaneWindow`]).
pub(super) const LANES: usize = 8;

/// The window's cost of [`LANES`] pixels at once, each at its own point of the grid: the
/// refinement's inner loop with the pixels across the lanes (vectorised), bit for bit
/// [`Between::set`] then the sum of [`Between::cost`] over the window's lit pixels in their
/// order. The lanes' pixels share the subpixel type of every slot of the window (pixels of one
/// row whose columns differ by a multiple of the mosaic's width), so a slot reads one type's
/// templates at every lane's point.
pub(super) struct LaneWindow {
    /// The tables' point-major rows of every type side by side `[G][N][2M]`, and their points
    /// `G`.
    joint: Vec<f32>,
    points: usize,
    types: usize,
    m: usize,
    /// Each slot's subpixel type `[S]`.
    slot_type: Vec<usize>,
    /// Normalised taps `[S·M]` of lanes, weights `[S]` of lanes (0 where the slot is empty) and
    /// whether a slot holds a lit pixel `[S]` of lanes.
    r: Vec<[f32; LANES]>,
    w: Vec<[f32; LANES]>,
    lit: Vec<[bool; LANES]>,
    /// Templates at each lane's point `[N·M]` of lanes and `1/‖d‖²` `[N]` of lanes.
    g: Vec<[f32; LANES]>,
    d: Vec<[f32; LANES]>,
    inv: Vec<[f32; LANES]>,
}

impl LaneWindow {
    /// The lanes of a window of `slots` pixels of `m` taps, over `tables` (one per subpixel
    /// type, on one grid).
    pub(super) fn new(tables: &[TypeTable], m: usize, slots: usize) -> Self {
        let types = tables.len();
        let points = tables.first().map_or(0, |t| t.points);
        // every type's point-major rows side by side: `[G][N][g[M], d[M]]`
        let mut joint = vec![0f32; points * types * 2 * m];
        for i in 0..points {
            for (t, table) in tables.iter().enumerate() {
                joint[(i * types + t) * 2 * m..(i * types + t + 1) * 2 * m].copy_from_slice(&table.pm[2 * m * i..2 * m * (i + 1)]);
            }
        }
        LaneWindow {
            joint,
            points,
            types,
            m,
            slot_type: vec![0; slots],
            r: vec![[0.0; LANES]; slots * m],
            w: vec![[0.0; LANES]; slots],
            lit: vec![[false; LANES]; slots],
            g: vec![[0.0; LANES]; types * m],
            d: vec![[0.0; LANES]; types * m],
            inv: vec![[0.0; LANES]; types],
        }
    }

    /// Slot `s` of lane `l`: a lit pixel's normalised taps `r` `[M]` and weight, or `None` (an
    /// unlit pixel, or beyond the frame); `kind` its subpixel type (the same in every lane).
    pub(super) fn set_slot(&mut self, s: usize, l: usize, kind: usize, pixel: Option<(&[f32], f32)>) {
        let m = self.m;
        self.slot_type[s] = kind;
        match pixel {
            Some((r, w)) => {
                for k in 0..m {
                    self.r[s * m + k][l] = r[k];
                }
                self.w[s][l] = w;
                self.lit[s][l] = true;
            }
            None => {
                for k in 0..m {
                    self.r[s * m + k][l] = 0.0;
                }
                self.w[s][l] = 0.0;
                self.lit[s][l] = false;
            }
        }
    }

    /// The window's cost of every lane at its grid position `u[l]` of the tables it was built
    /// from, into `out` `[LANES]`.
    pub(super) fn costs(&mut self, u: &[f64; LANES], background: bool, out: &mut [f64; LANES]) {
        let (m, n, types) = (self.m, self.points, self.types);
        let row = types * 2 * m;
        // the templates at every lane's point, as `Between::set_one` takes them (every type's
        // from one read of the two neighbouring rows)
        for l in 0..LANES {
            let (i, f) = between_points(u[l], n);
            let (a, b) = self.joint[i * row..(i + 2) * row].split_at(row);
            for t in 0..types {
                let (a, b) = (&a[t * 2 * m..(t + 1) * 2 * m], &b[t * 2 * m..(t + 1) * 2 * m]);
                let mut dd = 0f32;
                for k in 0..m {
                    let dk = a[m + k] + f * (b[m + k] - a[m + k]);
                    self.g[t * m + k][l] = a[k] + f * (b[k] - a[k]);
                    self.d[t * m + k][l] = dk;
                    dd += dk * dk;
                }
                self.inv[t][l] = if dd > 0.0 { 1.0 / dd } else { 0.0 };
            }
        }
        crate::simd(
            #[inline(always)]
            || self.slot_costs(background, out),
        )
    }

    /// The slots' costs summed per lane (the lanes innermost), as `Between::cost` sums them.
    #[inline(always)]
    fn slot_costs(&self, background: bool, out: &mut [f64; LANES]) {
        let m = self.m;
        *out = [-0.0; LANES];
        for (s, &t) in self.slot_type.iter().enumerate() {
            let mut beta = [0f32; LANES];
            if background {
                let mut num = [-0f32; LANES];
                for k in 0..m {
                    let (r, g, d) = (&self.r[s * m + k], &self.g[t * m + k], &self.d[t * m + k]);
                    for l in 0..LANES {
                        num[l] += (r[l] - g[l]) * d[l];
                    }
                }
                let inv = &self.inv[t];
                for l in 0..LANES {
                    beta[l] = (num[l] * inv[l]).clamp(0.0, 1.0);
                }
            }
            let mut c = [-0f32; LANES];
            for k in 0..m {
                let (r, g, d) = (&self.r[s * m + k], &self.g[t * m + k], &self.d[t * m + k]);
                for l in 0..LANES {
                    c[l] += (r[l] - g[l] - beta[l] * d[l]) * (r[l] - g[l] - beta[l] * d[l]);
                }
            }
            let (w, lit) = (&self.w[s], &self.lit[s]);
            for l in 0..LANES {
                if lit[l] {
                    out[l] += (w[l] * c[l]) as f64;
                }
            }
        }
    }
}

/// The templates `g`, `d` `[M]` a fraction `f` of the way from point `i` to `i + 1` of the
/// point-major rows `pm` `[2][2M]`, and `‖d‖²`: the refinement's inner loop with the taps known
/// at compile time (unrolled, no bounds checks), the same operations in the same order as
/// [`lerp_any`].
#[inline(always)]
fn lerp_fixed<const M: usize>(pm: &[f32], f: f32, g: &mut [f32], d: &mut [f32]) -> f32 {
    let fixed = |v: &[f32]| -> [f32; M] { v.try_into().unwrap_or_else(|_| unreachable!("M taps")) };
    let (g0, d0, g1, d1) = (fixed(&pm[..M]), fixed(&pm[M..2 * M]), fixed(&pm[2 * M..3 * M]), fixed(&pm[3 * M..4 * M]));
    let (Ok(g), Ok(d)) = (<&mut [f32; M]>::try_from(g), <&mut [f32; M]>::try_from(d)) else { unreachable!("M taps") };
    let mut dd = 0.0;
    for k in 0..M {
        let dk = d0[k] + f * (d1[k] - d0[k]);
        g[k] = g0[k] + f * (g1[k] - g0[k]);
        d[k] = dk;
        dd += dk * dk;
    }
    dd
}

/// [`lerp_fixed`] for any number of taps.
#[inline]
fn lerp_any(pm: &[f32], m: usize, f: f32, g: &mut [f32], d: &mut [f32]) -> f32 {
    let (a, b) = pm.split_at(2 * m);
    let mut dd = 0.0;
    for k in 0..m {
        let dk = a[m + k] + f * (b[m + k] - a[m + k]);
        g[k] = a[k] + f * (b[k] - a[k]);
        d[k] = dk;
        dd += dk * dk;
    }
    dd
}

/// The cost of normalised taps `r` against template `g` with background direction `d`
/// (`inv = 1/‖d‖²`) weighted by `w`, and the background share: [`cost_any`] with the taps
/// known at compile time.
#[inline(always)]
fn cost_fixed<const M: usize>(g: &[f32], d: &[f32], inv: f32, r: &[f32], w: f32, background: bool) -> (f32, f32) {
    let (Ok(g), Ok(d), Ok(r)) = (<&[f32; M]>::try_from(g), <&[f32; M]>::try_from(d), <&[f32; M]>::try_from(r)) else {
        unreachable!("M taps")
    };
    let beta = if background {
        let num: f32 = r.iter().zip(g).zip(d).map(|((r, g), d)| (r - g) * d).sum();
        (num * inv).clamp(0.0, 1.0)
    } else {
        0.0
    };
    let c: f32 = r.iter().zip(g).zip(d).map(|((r, g), d)| (r - g - beta * d) * (r - g - beta * d)).sum();
    (w * c, beta)
}

/// [`cost_fixed`] for any number of taps.
#[inline]
fn cost_any(g: &[f32], d: &[f32], inv: f32, r: &[f32], w: f32, background: bool) -> (f32, f32) {
    let beta = if background {
        let num: f32 = r.iter().zip(g).zip(d).map(|((r, g), d)| (r - g) * d).sum();
        (num * inv).clamp(0.0, 1.0)
    } else {
        0.0
    };
    let c: f32 = r.iter().zip(g).zip(d).map(|((r, g), d)| (r - g - beta * d) * (r - g - beta * d)).sum();
    (w * c, beta)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Uniform draws in [0, 1) from a xorshift seeded with `state`.
    fn draws(mut state: u64) -> impl FnMut() -> f64 {
        move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 40) as f64 / (1u64 << 24) as f64
        }
    }

    /// The window's cost in lanes is `Between::set` and the sum of `Between::cost` over the
    /// lit slots in their order, bit for bit, for every lane at its own point: 1 to 8 taps,
    /// with and without the background, empty slots, points beyond both ends of the grid.
    #[test]
    fn the_window_cost_in_lanes_is_the_scalar_sum_bit_for_bit() {
        let mut next = draws(0x9e37_79b9_7f4a_7c15);
        for m in [1, 2, 3, 4, 8] {
            let (types, points, slots) = (4, 19, 9);
            let g: Vec<f64> = (0..types * m * points).map(|_| next()).collect();
            let bg: Vec<f64> = (0..types * m).map(|_| next()).collect();
            let tables = TypeTable::build(types, m, points, |n, k, i| g[(n * m + k) * points + i], |n, k| bg[n * m + k]);
            for background in [false, true] {
                let mut lanes = LaneWindow::new(&tables, m, slots);
                let kinds: Vec<usize> = (0..slots).map(|s| (s * 5 + 1) % types).collect();
                // per lane and slot: taps and weight, or an empty slot
                let pixels: Vec<Vec<Option<(Vec<f32>, f32)>>> = (0..LANES)
                    .map(|_| {
                        (0..slots)
                            .map(|_| (next() > 0.25).then(|| ((0..m).map(|_| next() as f32).collect(), 1.0 + 99.0 * next() as f32)))
                            .collect()
                    })
                    .collect();
                for (l, lane) in pixels.iter().enumerate() {
                    for (s, p) in lane.iter().enumerate() {
                        lanes.set_slot(s, l, kinds[s], p.as_ref().map(|(r, w)| (r.as_slice(), *w)));
                    }
                }
                for _ in 0..20 {
                    let u: [f64; LANES] = std::array::from_fn(|_| next() * (points + 2) as f64 - 1.0);
                    let mut got = [f64::NAN; LANES];
                    lanes.costs(&u, background, &mut got);
                    let mut between = Between::new(types, m);
                    for l in 0..LANES {
                        between.set(&tables, u[l]);
                        let want: f64 = pixels[l]
                            .iter()
                            .enumerate()
                            .filter_map(|(s, p)| p.as_ref().map(|(r, w)| between.cost(kinds[s], r, *w, background).0 as f64))
                            .sum();
                        assert_eq!(got[l].to_bits(), want.to_bits(), "m {m}, background {background}, lane {l}: {} against {want}", got[l]);
                    }
                }
            }
        }
    }

    /// The refinement's fixed-size paths (2, 4 and 8 taps) and the general one give the
    /// reference's templates, shares and costs bit for bit, at any point between the grid's.
    #[test]
    fn fixed_size_refinement_paths_equal_the_reference_bit_for_bit() {
        let mut next = draws(0x2545_f491_4f6c_dd1d);
        for m in [1, 2, 3, 4, 5, 8] {
            let (types, points) = (4, 17);
            let g: Vec<f64> = (0..types * m * points).map(|_| next()).collect();
            let bg: Vec<f64> = (0..types * m).map(|_| next()).collect();
            let tables = TypeTable::build(types, m, points, |n, k, i| g[(n * m + k) * points + i], |n, k| bg[n * m + k]);
            let (mut fast, mut reference) = (Between::new(types, m), Between::new(types, m));
            for trial in 0..200 {
                let u = next() * (points + 2) as f64 - 1.0; // beyond both ends too
                let t = trial % types;
                fast.set_one(&tables, t, u);
                reference.set_one_reference(&tables, t, u);
                assert_eq!(
                    fast.g[t * m..(t + 1) * m].iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                    reference.g[t * m..(t + 1) * m].iter().map(|v| v.to_bits()).collect::<Vec<_>>()
                );
                assert_eq!(fast.inv_dd[t].to_bits(), reference.inv_dd[t].to_bits(), "m {m}, u {u}");
                let r: Vec<f32> = (0..m).map(|_| next() as f32).collect();
                for background in [false, true] {
                    let (a, b) = (fast.cost(t, &r, 1.7, background), reference.cost_reference(t, &r, 1.7, background));
                    assert_eq!((a.0.to_bits(), a.1.to_bits()), (b.0.to_bits(), b.1.to_bits()), "m {m}, u {u}, background {background}");
                }
            }
        }
    }
}
