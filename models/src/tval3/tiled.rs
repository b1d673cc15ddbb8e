//! The optimised TVAL3 iteration: the algorithm of [`super::tval3_reference`], with the passes
//! of an iteration fused into two sweeps over bands of frame rows.
//!
//! The solver keeps its cubes in the layout `[H, T, W]`: a band of rows holds every bin of its
//! pixels contiguously, so `A` and `Aᵀ` (per pixel, over all bins) and `D`, `Dᵀ` (periodic in
//! `t` and `x`, one halo row in `y`) are applied inside the band, which stays in cache. Each
//! band is one parallel task; a task writes only its own rows and reads its neighbours' from
//! buffers no task writes in that sweep.
//!
//! Per iteration (step fraction `α = 1`):
//!
//! - **trial sweep** ([`Tiled::trial`]): `u = P(up − τ d)`, `Au − b`, and the sums that make
//!   the objective along the step a quadratic in `α` ([`Trial`]): `‖Du − w‖²`,
//!   `(Du − w)ᵀ(D up − w)`, `σᵀ(Du − w)`, `‖Au − b‖²`, `(Au − b)ᵀ(A up − b)`, `δᵀ(Au − b)`;
//!   `Du` and `D up` are recomputed from `u` and `up`, never stored;
//! - **accept sweep** ([`Tiled::accept`]) at the accepted `u`: the w-step
//!   `w = shrink(Du − σ/β, 1/β)` with `Σ‖w‖`, `‖V‖²`, `σᵀV` for `V = Du − w` (kept only on the
//!   band), the next direction and the next Barzilai–Borwein sums with the stopping test's
//!   norms.
//!
//! `w` itself is not stored: the accepted `u` becomes the next step's `up`, so the trial sweep
//! recomputes `w = shrink(D up − σ/β, 1/β)` from values it reads anyway (bit for bit the accept
//! sweep's). Only a multiplier update, which changes `σ`, stores it ([`Tiled::update_sigma`]).
//!
//! The direction is kept in the form `d = Dᵀ(V − σ/β) + s·Aᵀ((μ/β)(Au − b) − δ/β)`: the
//! multiplier terms `(Dᵀσ + Aᵀδ)/β` of TVAL3 are folded into the band's own terms, so neither
//! they nor the two gradients are stored; with the multipliers fixed between outer updates the
//! Barzilai–Borwein sums use the change of `d` itself. That is about 5 reads and 1 write of the
//! cube in the trial sweep and 6 reads and 1 write in the accept sweep, against about 100
//! passes of the straightforward solver. Every band runs under the kernels' SIMD dispatch (its
//! closure inlined, so AVX-512 or AVX2 code is generated for it), and the bands' sums are added
//! in band order.

use super::{Sums, Trial, TvNorm};
use rayon::prelude::*;
use tcsense_kernels::pixel::simd;
use tcsense_sensor::FramePlan;

/// Solver state in the `[H, T, W]` layout (measurement-sized buffers `[H, M, W]`).
pub(super) struct Tiled<'a> {
    plan: &'a FramePlan,
    /// The scale `s` of `A` (`λ_max(s²AAᵀ) = 1`).
    s: f32,
    t: usize,
    h: usize,
    w: usize,
    m: usize,
    /// Rows per band.
    rows: usize,
    wt: f32,
    wy: f32,
    wx: f32,
    tv: TvNorm,
    nonneg: bool,
    /// `b` `[H, M, W]`.
    pub b: Vec<f32>,
    /// `s·Aᵀb`.
    pub atb: Vec<f32>,
    pub u: Vec<f32>,
    pub up: Vec<f32>,
    /// The direction at `u`: `d = Dᵀ(Du − w − σ/β) + s·Aᵀ((μ/β)(Au − b) − δ/β)`.
    pub d: Vec<f32>,
    /// The next direction, written by the accept sweep while it reads `d`.
    dn: Vec<f32>,
    /// `w` when it is stored (`w_inv` is `None`): only from a multiplier update to the next
    /// accept sweep.
    pub wv: [Vec<f32>; 3],
    /// `Some(1/β)` when `w` is implicit: `w = shrink(D p − σ/β, 1/β)` at the point `p` of the
    /// last accept sweep (`u` until the next step swaps it into `up`), recomputed where it is
    /// needed instead of stored (three cube writes and three reads fewer per iteration).
    w_inv: Option<f32>,
    pub sigma: [Vec<f32>; 3],
    /// `Au − b` `[H, M, W]`.
    pub resid: Vec<f32>,
    pub resid_p: Vec<f32>,
    pub delta: Vec<f32>,
    pub lam1: f64,
    pub lam2: f64,
    pub lam3: f64,
    pub lam4: f64,
    pub lam5: f64,
    /// Per-task sums of the last sweep, added in task order (same bytes on every run, whatever
    /// the scheduling).
    partials: Vec<[f64; 8]>,
}

/// `Σ v` of one row segment in eight lanes (vectorises), in `f64`.
#[inline(always)]
fn lane_sum(v: &[f32]) -> f64 {
    let mut acc = [0f32; 8];
    let chunks = v.chunks_exact(8);
    let tail: f32 = chunks.remainder().iter().sum();
    for ch in chunks {
        for k in 0..8 {
            acc[k] += ch[k];
        }
    }
    acc.iter().map(|&a| a as f64).sum::<f64>() + tail as f64
}

/// Per-task scratch of one row segment: x-differences and the per-column terms of the sums.
struct Scratch<'s> {
    dt: &'s mut [f32],
    dx: &'s mut [f32],
    dt2: &'s mut [f32],
    dx2: &'s mut [f32],
    e0: &'s mut [f32],
    e1: &'s mut [f32],
    e2: &'s mut [f32],
    e3: &'s mut [f32],
}

thread_local! {
    /// Each worker thread's scratch, kept between sweeps: after the first sweep no band
    /// allocates or touches fresh pages.
    static SCRATCH: std::cell::RefCell<Vec<f32>> = const { std::cell::RefCell::new(Vec::new()) };
}

/// Run `f` with this thread's scratch split into buffers of the lengths `sizes` and a
/// [`Scratch`] of row chunks of `w` values. The buffers hold whatever the last band left:
/// every band writes a value before reading it. (A band never calls into the thread pool, so
/// the scratch is never borrowed twice.)
#[inline(always)]
fn with_scratch<const N: usize, R>(sizes: &[usize; N], w: usize, f: impl FnOnce([&mut [f32]; N], &mut Scratch<'_>) -> R) -> R {
    SCRATCH.with(|cell| {
        let mut buf = cell.borrow_mut();
        let total = sizes.iter().sum::<usize>() + 8 * w;
        if buf.len() < total {
            buf.resize(total, 0.0);
        }
        let mut rest: &mut [f32] = &mut buf[..total];
        let parts: [&mut [f32]; N] = std::array::from_fn(|k| {
            let (head, tail) = std::mem::take(&mut rest).split_at_mut(sizes[k]);
            rest = tail;
            head
        });
        let (dt, rest) = rest.split_at_mut(w);
        let (dx, rest) = rest.split_at_mut(w);
        let (dt2, rest) = rest.split_at_mut(w);
        let (dx2, rest) = rest.split_at_mut(w);
        let (e0, rest) = rest.split_at_mut(w);
        let (e1, rest) = rest.split_at_mut(w);
        let (e2, e3) = rest.split_at_mut(w);
        f(parts, &mut Scratch { dt, dx, dt2, dx2, e0, e1, e2, e3 })
    })
}

/// Soft threshold `sign(z)·max(|z| − k, 0)`.
#[inline(always)]
fn shrink1(z: f32, k: f32) -> f32 {
    z.signum() * (z.abs() - k).max(0.0)
}

/// The w-step of one value: `w = shrink(z, k)` for `z = Du − σ/β`, `k = 1/β` (component-wise
/// for the anisotropic TV, on the vector for the isotropic one), and its norm term.
#[inline(always)]
fn w_step<const ISO: bool>(z0: f32, z1: f32, z2: f32, k: f32) -> (f32, f32, f32, f32) {
    if ISO {
        let nrm = (z0 * z0 + z1 * z1 + z2 * z2).sqrt();
        let f = if nrm > 0.0 { (nrm - k).max(0.0) / nrm } else { 0.0 };
        (f * z0, f * z1, f * z2, f * nrm)
    } else {
        let (a, b, e) = (shrink1(z0, k), shrink1(z1, k), shrink1(z2, k));
        (a, b, e, a.abs() + b.abs() + e.abs())
    }
}

/// The sums of every task, added in task order.
fn ordered_sum(partials: &[[f64; 8]]) -> [f64; 8] {
    partials.iter().fold([0.0; 8], |a, p| std::array::from_fn(|k| a[k] + p[k]))
}

/// The t and x forward differences of the values `k0..k1` (whole planes) of one frame row
/// `cur [T, W]` (periodic in both), into `dt[..k1 − k0]`, `dx[..k1 − k0]`:
/// `dt[j, c] = wt·(cur[j+1, c] − cur[j, c])`, `dx[j, c] = wx·(cur[j, c+1] − cur[j, c])`.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn diffs_tx(cur: &[f32], w: usize, k0: usize, k1: usize, wt: f32, wx: f32, dt: &mut [f32], dx: &mut [f32]) {
    let plane = cur.len();
    let n = k1 - k0;
    let inner = (plane - w).min(k1).max(k0) - k0; // values whose next plane is in the row
    let (c, nx) = (&cur[k0..k1], &cur[k0 + w..k0 + w + inner]);
    for k in 0..inner {
        dt[k] = wt * (nx[k] - c[k]);
    }
    for k in inner..n {
        dt[k] = wt * (cur[k0 + k + w - plane] - c[k]);
    }
    for (seg, out) in c.chunks_exact(w).zip(dx[..n].chunks_exact_mut(w)) {
        diff_x(seg, wx, out);
    }
}

/// The t and x parts of `Dᵀ` on the values `k0..k1` (whole planes) of one frame row:
/// `out[j, c] = wt·(vt[j−1, c] − vt[j, c]) + wx·(vx[j, c−1] − vx[j, c])` (periodic), into
/// `out[..k1 − k0]`.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn adjoint_diffs_tx(vt: &[f32], vx: &[f32], w: usize, k0: usize, k1: usize, wt: f32, wx: f32, out: &mut [f32]) {
    let plane = vt.len();
    let n = k1 - k0;
    let wrap = if k0 == 0 { w } else { 0 }; // the first plane's previous plane is the last one
    for k in 0..wrap {
        out[k] = wt * (vt[plane - w + k] - vt[k]);
    }
    let (c, pv) = (&vt[k0 + wrap..k1], &vt[k0 + wrap - w..k1 - w]);
    for ((o, &a), &b) in out[wrap..n].iter_mut().zip(pv).zip(c) {
        *o = wt * (a - b);
    }
    for (seg, o) in vx[k0..k1].chunks_exact(w).zip(out[..n].chunks_exact_mut(w)) {
        o[0] += wx * (seg[w - 1] - seg[0]);
        for c in 1..w {
            o[c] += wx * (seg[c - 1] - seg[c]);
        }
    }
}

/// Values per chunk of a frame row: whole planes, at least 512 values (one plane of a wide
/// frame, several of a narrow one), so the loops run long and their terms stay in L1.
#[inline(always)]
fn chunk_len(w: usize) -> usize {
    (512 / w).max(1) * w
}

/// `out[c] = wx·(cur[c+1] − cur[c])`, periodic.
#[inline(always)]
fn diff_x(cur: &[f32], wx: f32, out: &mut [f32]) {
    let w = cur.len();
    for c in 0..w - 1 {
        out[c] = wx * (cur[c + 1] - cur[c]);
    }
    out[w - 1] = wx * (cur[0] - cur[w - 1]);
}

/// Cube buffers of finished solves, kept for the next solve of the process (a designer's
/// sweep runs thousands): a fresh buffer's pages are mapped on first write, one page fault
/// per 4 KiB, which measured 0.1 s of a 188×212×32 solve's 1 s here. At most
/// [`POOL_BYTES`] are kept.
static POOL: std::sync::Mutex<Vec<Vec<f32>>> = std::sync::Mutex::new(Vec::new());
const POOL_BYTES: usize = 512 << 20;

/// A zeroed buffer of `n` values, from [`POOL`] when it holds one large enough (the smallest).
pub(super) fn pooled(n: usize) -> Vec<f32> {
    let reuse = POOL.lock().ok().and_then(|mut pool| {
        let best = pool.iter().enumerate().filter(|(_, v)| v.capacity() >= n).min_by_key(|(_, v)| v.capacity()).map(|(k, _)| k)?;
        Some(pool.swap_remove(best))
    });
    match reuse {
        Some(mut v) => {
            v.clear();
            v.resize(n, 0.0);
            v
        }
        None => vec![0f32; n],
    }
}

/// Give buffers back to [`POOL`] (dropping them when it is full).
pub(super) fn unpool(bufs: impl IntoIterator<Item = Vec<f32>>) {
    if let Ok(mut pool) = POOL.lock() {
        let mut bytes: usize = pool.iter().map(|v| v.capacity() * 4).sum();
        for v in bufs {
            if v.capacity() > 0 && bytes + v.capacity() * 4 <= POOL_BYTES {
                bytes += v.capacity() * 4;
                pool.push(v);
            }
        }
    }
}

impl Drop for Tiled<'_> {
    fn drop(&mut self) {
        let [w0, w1, w2] = std::mem::take(&mut self.wv);
        let [s0, s1, s2] = std::mem::take(&mut self.sigma);
        let bufs = [
            &mut self.b,
            &mut self.atb,
            &mut self.u,
            &mut self.up,
            &mut self.d,
            &mut self.dn,
            &mut self.resid,
            &mut self.resid_p,
            &mut self.delta,
        ]
        .map(std::mem::take);
        unpool(bufs.into_iter().chain([w0, w1, w2, s0, s1, s2]));
    }
}

impl<'a> Tiled<'a> {
    /// A solver for `y [M, H, W]` (already scaled): `b` in the band layout and `Aᵀb`; every
    /// other buffer zero.
    #[allow(clippy::too_many_arguments)]
    pub fn new(plan: &'a FramePlan, s: f32, b_mhw: &[f32], weights: [f32; 3], tv: TvNorm, nonneg: bool) -> Self {
        let (m, h, w, t) = (plan.taps(), plan.height(), plan.width(), plan.bins());
        let mut b = pooled(m * h * w);
        for mm in 0..m {
            for r in 0..h {
                b[(r * m + mm) * w..][..w].copy_from_slice(&b_mhw[(mm * h + r) * w..][..w]);
            }
        }
        let n = t * h * w;
        let z = || pooled(n);
        let zm = || pooled(m * h * w);
        // bands of about 32k values per buffer (a few hundred kB in cache), at least one row
        let rows = (32_768 / (t * w)).clamp(1, 8).min(h);
        let mut st = Tiled {
            plan,
            s,
            t,
            h,
            w,
            m,
            rows,
            wt: weights[0],
            wy: weights[1],
            wx: weights[2],
            tv,
            nonneg,
            b,
            atb: z(),
            u: z(),
            up: z(),
            d: z(),
            dn: z(),
            wv: [z(), z(), z()],
            w_inv: None,
            sigma: [z(), z(), z()],
            resid: zm(),
            resid_p: zm(),
            delta: zm(),
            lam1: 0.0,
            lam2: 0.0,
            lam3: 0.0,
            lam4: 0.0,
            lam5: 0.0,
            partials: Vec::new(),
        };
        let (plane, mw) = (t * w, m * w);
        let mut atb = std::mem::take(&mut st.atb);
        let (b, this) = (&st.b, &st);
        atb.par_chunks_mut(plane).enumerate().for_each(|(r, out)| this.adjoint_row(r, &b[r * mw..][..mw], out));
        st.atb = atb;
        st
    }

    /// `out [T, W] = s·Aᵀ v` for frame row `r` from `v [M, W]`.
    #[inline(always)]
    fn adjoint_row(&self, r: usize, v: &[f32], out: &mut [f32]) {
        let (t, w, m, s) = (self.t, self.w, self.m, self.s);
        for j in 0..t {
            let o = &mut out[j * w..(j + 1) * w];
            o.fill(0.0);
            for mm in 0..m {
                let cf = self.plan.row_coefficients(r, j, mm);
                for ((o, &c), &y) in o.iter_mut().zip(cf).zip(&v[mm * w..(mm + 1) * w]) {
                    *o += c * y;
                }
            }
            o.iter_mut().for_each(|o| *o *= s);
        }
    }

    /// `out [M, W] = s·A u` for frame row `r` from `u [T, W]`.
    #[inline(always)]
    fn forward_row(&self, r: usize, u: &[f32], out: &mut [f32]) {
        let (t, w, m, s) = (self.t, self.w, self.m, self.s);
        for mm in 0..m {
            let o = &mut out[mm * w..(mm + 1) * w];
            o.fill(0.0);
            for j in 0..t {
                let cf = self.plan.row_coefficients(r, j, mm);
                for ((o, &c), &x) in o.iter_mut().zip(cf).zip(&u[j * w..(j + 1) * w]) {
                    *o += c * x;
                }
            }
            o.iter_mut().for_each(|o| *o *= s);
        }
    }

    /// The initial point `u = P(Aᵀb)` with its `Au − b`.
    pub fn start(&mut self) {
        self.up.copy_from_slice(&self.atb);
        self.d.fill(0.0);
        let _ = self.trial(0.0);
    }

    /// Trial sweep: `u = P(up − τ d)` and `Au − b` (into `u`, `resid`), and the objective along
    /// the step from `up` as a [`Trial`] (`lam*` hold the values at `up`).
    pub fn trial(&mut self, tau: f32) -> Trial {
        match (self.w_inv, self.tv) {
            (None, _) => self.trial_w::<false, false>(tau, 0.0),
            (Some(k), TvNorm::Anisotropic) => self.trial_w::<true, false>(tau, k),
            (Some(k), TvNorm::Isotropic) => self.trial_w::<true, true>(tau, k),
        }
    }

    /// [`Tiled::trial`] with `w` read from `wv` (`IMPLICIT` false) or recomputed from `D up`
    /// and `σ` with threshold `inv` (`ISO`: the isotropic shrinkage).
    fn trial_w<const IMPLICIT: bool, const ISO: bool>(&mut self, tau: f32, inv: f32) -> Trial {
        let (t, h, w, m, rows) = (self.t, self.h, self.w, self.m, self.rows);
        let (wt, wy, wx, nonneg) = (self.wt, self.wy, self.wx, self.nonneg);
        let plane = t * w;
        let mut u = std::mem::take(&mut self.u);
        let mut resid = std::mem::take(&mut self.resid);
        let mut partials = std::mem::take(&mut self.partials);
        let this = &*self;
        let (up, d, wv, sg) = (&this.up, &this.d, &this.wv, &this.sigma);
        let chunk = chunk_len(w);
        u.par_chunks_mut(rows * plane)
            .zip(resid.par_chunks_mut(rows * m * w))
            .enumerate()
            .map(|(bi, (uc, rc))| {
                with_scratch(&[plane], chunk, |[halo], sc| {
                    simd(
                        #[inline(always)]
                        || {
                            let r0 = bi * rows;
                            let nr = uc.len() / plane;
                            // u on the band's rows (in place) and the halo row below (scratch)
                            for rr in 0..=nr {
                                let src = ((r0 + rr) % h) * plane;
                                let o = if rr < nr { &mut uc[rr * plane..(rr + 1) * plane] } else { &mut halo[..] };
                                let (p, dd) = (&up[src..src + plane], &d[src..src + plane]);
                                if nonneg {
                                    o.iter_mut().zip(p).zip(dd).for_each(|((o, &p), &d)| *o = (p - tau * d).max(0.0));
                                } else {
                                    o.iter_mut().zip(p).zip(dd).for_each(|((o, &p), &d)| *o = p - tau * d);
                                }
                            }
                            let (uc, halo) = (&*uc, &*halo);
                            let row = |rr: usize| if rr < nr { &uc[rr * plane..(rr + 1) * plane] } else { halo };
                            let mut acc = [0f64; 8];
                            for rr in 0..nr {
                                let r = r0 + rr;
                                let rn = (r + 1) % h;
                                let (cur, bl) = (row(rr), row(rr + 1));
                                let gi = r * plane;
                                let (pc, pb) = (&up[gi..gi + plane], &up[rn * plane..(rn + 1) * plane]);
                                for k0 in (0..plane).step_by(chunk) {
                                    let k1 = (k0 + chunk).min(plane);
                                    let n = k1 - k0;
                                    diffs_tx(cur, w, k0, k1, wt, wx, sc.dt, sc.dx);
                                    diffs_tx(pc, w, k0, k1, wt, wx, sc.dt2, sc.dx2);
                                    let g = gi + k0;
                                    let (w0, w1, w2) = (&wv[0][g..g + n], &wv[1][g..g + n], &wv[2][g..g + n]);
                                    let (s0, s1, s2) = (&sg[0][g..g + n], &sg[1][g..g + n], &sg[2][g..g + n]);
                                    let (cu, bu, pcu, pbu) = (&cur[k0..k1], &bl[k0..k1], &pc[k0..k1], &pb[k0..k1]);
                                    let (dtt, dxt, dtp, dxp) = (&sc.dt[..n], &sc.dx[..n], &sc.dt2[..n], &sc.dx2[..n]);
                                    let (e0, e1, e2) = (&mut sc.e0[..n], &mut sc.e1[..n], &mut sc.e2[..n]);
                                    for k in 0..n {
                                        let (q0, q1, q2) = (dtp[k], wy * (pbu[k] - pcu[k]), dxp[k]);
                                        let (w0, w1, w2) = if IMPLICIT {
                                            let (a, b, e, _) = w_step::<ISO>(q0 - s0[k] * inv, q1 - s1[k] * inv, q2 - s2[k] * inv, inv);
                                            (a, b, e)
                                        } else {
                                            (w0[k], w1[k], w2[k])
                                        };
                                        let (a0, a1, a2) = (dtt[k] - w0, wy * (bu[k] - cu[k]) - w1, dxt[k] - w2);
                                        let (p0, p1, p2) = (q0 - w0, q1 - w1, q2 - w2);
                                        e0[k] = a0 * a0 + a1 * a1 + a2 * a2;
                                        e1[k] = a0 * p0 + a1 * p1 + a2 * p2;
                                        e2[k] = a0 * s0[k] + a1 * s1[k] + a2 * s2[k];
                                    }
                                    acc[0] += lane_sum(e0);
                                    acc[1] += lane_sum(e1);
                                    acc[2] += lane_sum(e2);
                                }
                                // A u − b of this row
                                let ro = &mut rc[rr * m * w..(rr + 1) * m * w];
                                this.forward_row(r, cur, ro);
                                let off = r * m * w;
                                let (b, rp, dl) =
                                    (&this.b[off..off + m * w], &this.resid_p[off..off + m * w], &this.delta[off..off + m * w]);
                                for mm in 0..m {
                                    let k0 = mm * w;
                                    let (e0, e1, e2) = (&mut sc.e0[..w], &mut sc.e1[..w], &mut sc.e2[..w]);
                                    let o = &mut ro[k0..k0 + w];
                                    for c in 0..w {
                                        let v = o[c] - b[k0 + c];
                                        o[c] = v;
                                        e0[c] = v * v;
                                        e1[c] = v * rp[k0 + c];
                                        e2[c] = v * dl[k0 + c];
                                    }
                                    acc[3] += lane_sum(e0);
                                    acc[4] += lane_sum(e1);
                                    acc[5] += lane_sum(e2);
                                }
                            }
                            acc
                        },
                    )
                })
            })
            .collect_into_vec(&mut partials);
        let sums = ordered_sum(&partials);
        self.partials = partials;
        self.u = u;
        self.resid = resid;
        Trial {
            lam1: self.lam1,
            lam2: [self.lam2, sums[1], sums[0]],
            lam3: [self.lam3, sums[4], sums[3]],
            lam4: [self.lam4, sums[2]],
            lam5: [self.lam5, sums[5]],
        }
    }

    /// Move the accepted point to fraction `α` of the step: `u = up + α(u − up)` and the same
    /// for `Au − b` (both affine in `α`); `lam3`, `lam5` at the new point.
    pub fn lerp(&mut self, alpha: f32) {
        let lerp = |out: &mut [f32], prev: &[f32]| {
            out.par_chunks_mut(8192).zip(prev.par_chunks(8192)).for_each(|(o, p)| {
                for (o, &p) in o.iter_mut().zip(p) {
                    *o = p + alpha * (*o - p);
                }
            });
        };
        lerp(&mut self.u, &self.up);
        lerp(&mut self.resid, &self.resid_p);
        self.resid_sums();
    }

    /// `lam3 = ‖Au − b‖²`, `lam5 = δᵀ(Au − b)`.
    pub fn resid_sums(&mut self) {
        self.lam3 = self.resid.iter().map(|&v| (v * v) as f64).sum();
        self.lam5 = self.resid.iter().zip(&self.delta).map(|(&r, &d)| (r * d) as f64).sum();
    }

    /// Accept sweep at `u` (with `Au − b` in `resid`): the w-step and the next direction
    /// ([`Tiled::band_direction`]); sets `lam1`, `lam2`, `lam4` and returns the direction's sums.
    pub fn accept(&mut self, beta: f64, mdb: f32) -> Sums {
        match self.tv {
            TvNorm::Anisotropic => self.accept_tv::<false>(beta, mdb),
            TvNorm::Isotropic => self.accept_tv::<true>(beta, mdb),
        }
    }

    fn accept_tv<const ISO: bool>(&mut self, beta: f64, mdb: f32) -> Sums {
        let (t, h, w, m, rows) = (self.t, self.h, self.w, self.m, self.rows);
        let (wt, wy, wx) = (self.wt, self.wy, self.wx);
        let inv = (1.0 / beta) as f32;
        let plane = t * w;
        let band = rows * plane;
        let mut dn = std::mem::take(&mut self.dn);
        let mut partials = std::mem::take(&mut self.partials);
        let this = &*self;
        let (u, sg) = (&this.u, &this.sigma);
        let chunk = chunk_len(w);
        dn.par_chunks_mut(band)
            .enumerate()
            .map(|(bi, od)| {
                with_scratch(&[3 * (rows + 1) * plane, m * w], chunk, |[v, rm], sc| {
                    simd(
                        #[inline(always)]
                        || {
                            let r0 = bi * rows;
                            let nr = od.len() / plane;
                            let vs = (nr + 1) * plane; // one component of V on the band and the halo row above
                            let mut acc = [0f64; 8];
                            // w-step and V − σ/β on rows r0 − 1 … r0 + nr − 1 (local row rr = 0 is the halo),
                            // a chunk of planes at a time
                            for rr in 0..=nr {
                                let r = (r0 + h + rr - 1) % h;
                                let rn = (r + 1) % h;
                                let gi = r * plane;
                                let (cur, bl) = (&u[gi..gi + plane], &u[rn * plane..(rn + 1) * plane]);
                                if rr == 0 {
                                    // the halo row: the direction needs only the y component of V − σ/β
                                    let vb = &mut v[vs..2 * vs];
                                    for k0 in (0..plane).step_by(chunk) {
                                        let k1 = (k0 + chunk).min(plane);
                                        let n = k1 - k0;
                                        let g = gi + k0;
                                        let (cu, bu, s1) = (&cur[k0..k1], &bl[k0..k1], &sg[1][g..g + n]);
                                        let v1 = &mut vb[k0..k1];
                                        if ISO {
                                            diffs_tx(cur, w, k0, k1, wt, wx, sc.dt, sc.dx);
                                            let (dtt, dx, s0, s2) = (&sc.dt[..n], &sc.dx[..n], &sg[0][g..g + n], &sg[2][g..g + n]);
                                            for k in 0..n {
                                                let z1 = wy * (bu[k] - cu[k]) - s1[k] * inv;
                                                let (_, b, _, _) = w_step::<true>(dtt[k] - s0[k] * inv, z1, dx[k] - s2[k] * inv, inv);
                                                v1[k] = z1 - b;
                                            }
                                        } else {
                                            for k in 0..n {
                                                let z1 = wy * (bu[k] - cu[k]) - s1[k] * inv;
                                                v1[k] = z1 - shrink1(z1, inv);
                                            }
                                        }
                                    }
                                    continue;
                                }
                                for k0 in (0..plane).step_by(chunk) {
                                    let k1 = (k0 + chunk).min(plane);
                                    let n = k1 - k0;
                                    diffs_tx(cur, w, k0, k1, wt, wx, sc.dt, sc.dx);
                                    let (dtt, dx) = (&sc.dt[..n], &sc.dx[..n]);
                                    let g = gi + k0;
                                    let (s0, s1, s2) = (&sg[0][g..g + n], &sg[1][g..g + n], &sg[2][g..g + n]);
                                    let (cu, bu) = (&cur[k0..k1], &bl[k0..k1]);
                                    let lo = rr * plane + k0;
                                    let (va, rest) = v.split_at_mut(vs);
                                    let (vb, vc) = rest.split_at_mut(vs);
                                    let (v0, v1, v2) = (&mut va[lo..lo + n], &mut vb[lo..lo + n], &mut vc[lo..lo + n]);
                                    let (e0, e1, e2) = (&mut sc.e0[..n], &mut sc.e1[..n], &mut sc.e2[..n]);
                                    for k in 0..n {
                                        let (d0, d1, d2) = (dtt[k], wy * (bu[k] - cu[k]), dx[k]);
                                        let (z0, z1, z2) = (d0 - s0[k] * inv, d1 - s1[k] * inv, d2 - s2[k] * inv);
                                        let (a, b, e, n1) = w_step::<ISO>(z0, z1, z2, inv);
                                        let (p0, p1, p2) = (d0 - a, d1 - b, d2 - e);
                                        // V − σ/β = z − w
                                        v0[k] = z0 - a;
                                        v1[k] = z1 - b;
                                        v2[k] = z2 - e;
                                        e0[k] = n1;
                                        e1[k] = p0 * p0 + p1 * p1 + p2 * p2;
                                        e2[k] = p0 * s0[k] + p1 * s1[k] + p2 * s2[k];
                                    }
                                    acc[0] += lane_sum(e0);
                                    acc[1] += lane_sum(e1);
                                    acc[2] += lane_sum(e2);
                                }
                            }
                            let [a3, a4, a5, a6] = this.band_direction(r0, nr, v, vs, od, rm, sc, mdb, inv);
                            acc[3] = a3;
                            acc[4] = a4;
                            acc[5] = a5;
                            acc[6] = a6;
                            acc
                        },
                    )
                })
            })
            .collect_into_vec(&mut partials);
        let out = ordered_sum(&partials);
        self.partials = partials;
        self.w_inv = Some(inv);
        self.dn = std::mem::replace(&mut self.d, dn);
        self.lam1 = out[0];
        self.lam2 = out[1];
        self.lam4 = out[2];
        Sums { d_norm2: out[3], ss: out[4], sy: out[5], up_norm2: out[6] }
    }

    /// The direction at `u` with `w` kept (after the multiplier update and continuation):
    /// `d = Dᵀ(Du − w − σ/β) + s·Aᵀ(mdb·(Au − b) − δ/β)`; returns `‖d‖²`. Runs after
    /// [`Tiled::update_sigma`], which stores `w`.
    pub fn redirect(&mut self, beta: f64, mdb: f32) -> f64 {
        assert!(self.w_inv.is_none(), "redirect reads the stored w: call update_sigma first");
        let (t, h, w, m, rows) = (self.t, self.h, self.w, self.m, self.rows);
        let (wt, wy, wx) = (self.wt, self.wy, self.wx);
        let inv = (1.0 / beta) as f32;
        let plane = t * w;
        let mut dn = std::mem::take(&mut self.dn);
        let mut partials = std::mem::take(&mut self.partials);
        let this = &*self;
        let (u, sg, wv) = (&this.u, &this.sigma, &this.wv);
        let chunk = chunk_len(w);
        dn.par_chunks_mut(rows * plane)
            .enumerate()
            .map(|(bi, od)| {
                with_scratch(&[3 * (rows + 1) * plane, m * w], chunk, |[v, rm], sc| {
                    simd(
                        #[inline(always)]
                        || {
                            let r0 = bi * rows;
                            let nr = od.len() / plane;
                            let vs = (nr + 1) * plane;
                            for rr in 0..=nr {
                                let r = (r0 + h + rr - 1) % h;
                                let rn = (r + 1) % h;
                                let gi = r * plane;
                                let (cur, bl) = (&u[gi..gi + plane], &u[rn * plane..(rn + 1) * plane]);
                                for k0 in (0..plane).step_by(chunk) {
                                    let k1 = (k0 + chunk).min(plane);
                                    let n = k1 - k0;
                                    diffs_tx(cur, w, k0, k1, wt, wx, sc.dt, sc.dx);
                                    let (dtt, dx) = (&sc.dt[..n], &sc.dx[..n]);
                                    let g = gi + k0;
                                    let (cu, bu) = (&cur[k0..k1], &bl[k0..k1]);
                                    let lo = rr * plane + k0;
                                    let (va, rest) = v.split_at_mut(vs);
                                    let (vb, vc) = rest.split_at_mut(vs);
                                    let (v0, v1, v2) = (&mut va[lo..lo + n], &mut vb[lo..lo + n], &mut vc[lo..lo + n]);
                                    let (w0, w1, w2) = (&wv[0][g..g + n], &wv[1][g..g + n], &wv[2][g..g + n]);
                                    let (s0, s1, s2) = (&sg[0][g..g + n], &sg[1][g..g + n], &sg[2][g..g + n]);
                                    for k in 0..n {
                                        v0[k] = dtt[k] - w0[k] - s0[k] * inv;
                                        v1[k] = wy * (bu[k] - cu[k]) - w1[k] - s1[k] * inv;
                                        v2[k] = dx[k] - w2[k] - s2[k] * inv;
                                    }
                                }
                            }
                            let mut acc = [0f64; 8];
                            acc[0] = this.band_direction(r0, nr, v, vs, od, rm, sc, mdb, inv)[0];
                            acc
                        },
                    )
                })
            })
            .collect_into_vec(&mut partials);
        let dd = ordered_sum(&partials)[0];
        self.partials = partials;
        self.dn = std::mem::replace(&mut self.d, dn);
        dd
    }

    /// The direction on a band from `v = V − σ/β` (3 components of `vs` values each, local row
    /// 0 the halo row above): `dn = Dᵀv + s·Aᵀ(mdb·(Au − b) − δ/β)` for the band's `nr` rows
    /// from `r0`, and `[‖dn‖², ‖u − up‖², (u − up)ᵀ(dn − d), ‖up‖²]` over them (`d` the previous
    /// direction: with the multipliers fixed, `dn − d` is the change of the gradient).
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    fn band_direction(
        &self,
        r0: usize,
        nr: usize,
        v: &[f32],
        vs: usize,
        dn: &mut [f32],
        rm: &mut [f32],
        sc: &mut Scratch<'_>,
        mdb: f32,
        inv_beta: f32,
    ) -> [f64; 4] {
        let (t, w, m) = (self.t, self.w, self.m);
        let (wt, wy, wx) = (self.wt, self.wy, self.wx);
        let plane = t * w;
        let (u, up, d, resid, delta) = (&self.u, &self.up, &self.d, &self.resid, &self.delta);
        let (va, rest) = v.split_at(vs);
        let (vb, vc) = rest.split_at(vs);
        let mut acc = [0f64; 4];
        for rr in 1..=nr {
            let r = r0 + rr - 1;
            let lo = (rr - 1) * plane;
            let off = r * m * w;
            for ((o, &x), &dl) in rm.iter_mut().zip(&resid[off..off + m * w]).zip(&delta[off..off + m * w]) {
                *o = mdb * x - inv_beta * dl;
            }
            self.adjoint_row(r, rm, &mut dn[lo..lo + plane]);
            // Dᵀv of the row, a chunk of planes at a time: t and x parts, then the y part with the
            // row above, and the sums
            let rk = rr * plane;
            let (vt, vy, vy_above, vx) = (&va[rk..rk + plane], &vb[rk..rk + plane], &vb[rk - plane..rk], &vc[rk..rk + plane]);
            let chunk = chunk_len(w);
            for k0 in (0..plane).step_by(chunk) {
                let k1 = (k0 + chunk).min(plane);
                let n = k1 - k0;
                adjoint_diffs_tx(vt, vx, w, k0, k1, wt, wx, sc.dt);
                let g = r * plane + k0;
                let (uc, pc, dc) = (&u[g..g + n], &up[g..g + n], &d[g..g + n]);
                let (vyc, vya) = (&vy[k0..k1], &vy_above[k0..k1]);
                let o = &mut dn[lo + k0..lo + k1];
                let tx = &sc.dt[..n];
                let (e0, e1, e2, e3) = (&mut sc.e0[..n], &mut sc.e1[..n], &mut sc.e2[..n], &mut sc.e3[..n]);
                for k in 0..n {
                    let di = o[k] + tx[k] + wy * (vya[k] - vyc[k]);
                    o[k] = di;
                    let du = uc[k] - pc[k];
                    e0[k] = di * di;
                    e1[k] = du * du;
                    e2[k] = du * (di - dc[k]);
                    e3[k] = pc[k] * pc[k];
                }
                acc[0] += lane_sum(e0);
                acc[1] += lane_sum(e1);
                acc[2] += lane_sum(e2);
                acc[3] += lane_sum(e3);
            }
        }
        acc
    }

    /// Multiplier update at `u` (the point of the last accept sweep): `σ ← σ − β(Du − w)`;
    /// returns the new `σᵀ(Du − w)` (`lam4`). An implicit `w` is stored first (it was shrunk
    /// with the old `σ`, which the next steps can no longer recompute it from).
    pub fn update_sigma(&mut self, beta: f32) -> f64 {
        match (self.w_inv, self.tv) {
            (None, _) => self.update_sigma_w::<false, false>(beta, 0.0),
            (Some(k), TvNorm::Anisotropic) => self.update_sigma_w::<true, false>(beta, k),
            (Some(k), TvNorm::Isotropic) => self.update_sigma_w::<true, true>(beta, k),
        }
    }

    fn update_sigma_w<const IMPLICIT: bool, const ISO: bool>(&mut self, beta: f32, inv: f32) -> f64 {
        let (t, h, w, rows) = (self.t, self.h, self.w, self.rows);
        let (wt, wy, wx) = (self.wt, self.wy, self.wx);
        let plane = t * w;
        let band = rows * plane;
        let [mut s0, mut s1, mut s2] = std::mem::take(&mut self.sigma);
        let [mut w0, mut w1, mut w2] = std::mem::take(&mut self.wv);
        let mut partials = std::mem::take(&mut self.partials);
        let u = &self.u;
        let chunk = chunk_len(w);
        s0.par_chunks_mut(band)
            .zip(s1.par_chunks_mut(band))
            .zip(s2.par_chunks_mut(band))
            .zip(w0.par_chunks_mut(band).zip(w1.par_chunks_mut(band)).zip(w2.par_chunks_mut(band)))
            .enumerate()
            .map(|(bi, (((o0, o1), o2), ((ws0, ws1), ws2)))| {
                with_scratch(&[], chunk, |[], sc| {
                    simd(
                        #[inline(always)]
                        || {
                            let r0 = bi * rows;
                            let mut l4 = [0f64; 8];
                            for rr in 0..o0.len() / plane {
                                let r = r0 + rr;
                                let rn = (r + 1) % h;
                                let gi = r * plane;
                                let (cur, bl) = (&u[gi..gi + plane], &u[rn * plane..(rn + 1) * plane]);
                                for k0 in (0..plane).step_by(chunk) {
                                    let k1 = (k0 + chunk).min(plane);
                                    let n = k1 - k0;
                                    diffs_tx(cur, w, k0, k1, wt, wx, sc.dt, sc.dx);
                                    let (dtt, dx) = (&sc.dt[..n], &sc.dx[..n]);
                                    let (cu, bu) = (&cur[k0..k1], &bl[k0..k1]);
                                    let lo = rr * plane + k0;
                                    let (a0, a1, a2) = (&mut o0[lo..lo + n], &mut o1[lo..lo + n], &mut o2[lo..lo + n]);
                                    let (w0, w1, w2) = (&mut ws0[lo..lo + n], &mut ws1[lo..lo + n], &mut ws2[lo..lo + n]);
                                    let e = &mut sc.e0[..n];
                                    for c in 0..n {
                                        let (d0, d1, d2) = (dtt[c], wy * (bu[c] - cu[c]), dx[c]);
                                        if IMPLICIT {
                                            let (a, b, e, _) = w_step::<ISO>(d0 - a0[c] * inv, d1 - a1[c] * inv, d2 - a2[c] * inv, inv);
                                            w0[c] = a;
                                            w1[c] = b;
                                            w2[c] = e;
                                        }
                                        let v0 = d0 - w0[c];
                                        let v1 = d1 - w1[c];
                                        let v2 = d2 - w2[c];
                                        a0[c] -= beta * v0;
                                        a1[c] -= beta * v1;
                                        a2[c] -= beta * v2;
                                        e[c] = a0[c] * v0 + a1[c] * v1 + a2[c] * v2;
                                    }
                                    l4[0] += lane_sum(e);
                                }
                            }
                            l4
                        },
                    )
                })
            })
            .collect_into_vec(&mut partials);
        let l4 = ordered_sum(&partials)[0];
        self.partials = partials;
        self.sigma = [s0, s1, s2];
        self.wv = [w0, w1, w2];
        self.w_inv = None;
        l4
    }

    /// The exact steepest-descent step along `d`: `dᵀd / (‖Dd‖² + (μ/β)‖s·Ad‖²)`.
    pub fn steepest_tau(&mut self, mdb: f64) -> f64 {
        let (t, h, w, m, rows) = (self.t, self.h, self.w, self.m, self.rows);
        let (wt, wy, wx) = (self.wt, self.wy, self.wx);
        let plane = t * w;
        let mut partials = std::mem::take(&mut self.partials);
        let this = &*self;
        let d = &this.d;
        let chunk = chunk_len(w);
        d.par_chunks(rows * plane)
            .enumerate()
            .map(|(bi, dc)| {
                with_scratch(&[m * w], chunk, |[ad], sc| {
                    simd(
                        #[inline(always)]
                        || {
                            let r0 = bi * rows;
                            let mut acc = [0f64; 8];
                            for rr in 0..dc.len() / plane {
                                let r = r0 + rr;
                                let rn = (r + 1) % h;
                                let gi = r * plane;
                                let (cur, bl) = (&d[gi..gi + plane], &d[rn * plane..(rn + 1) * plane]);
                                for k0 in (0..plane).step_by(chunk) {
                                    let k1 = (k0 + chunk).min(plane);
                                    let n = k1 - k0;
                                    diffs_tx(cur, w, k0, k1, wt, wx, sc.dt, sc.dx);
                                    let (dtt, dx) = (&sc.dt[..n], &sc.dx[..n]);
                                    let (cu, bu) = (&cur[k0..k1], &bl[k0..k1]);
                                    let (e0, e1) = (&mut sc.e0[..n], &mut sc.e1[..n]);
                                    for c in 0..n {
                                        let a1 = wy * (bu[c] - cu[c]);
                                        e0[c] = dtt[c] * dtt[c] + a1 * a1 + dx[c] * dx[c];
                                        e1[c] = cu[c] * cu[c];
                                    }
                                    acc[0] += lane_sum(e0);
                                    acc[2] += lane_sum(e1);
                                }
                                this.forward_row(r, &d[r * plane..(r + 1) * plane], ad);
                                acc[1] += ad.iter().map(|&v| (v * v) as f64).sum::<f64>();
                            }
                            acc
                        },
                    )
                })
            })
            .collect_into_vec(&mut partials);
        let [ddd, ad2, dn, ..] = ordered_sum(&partials);
        self.partials = partials;
        let den = ddd + mdb * ad2;
        if den > 0.0 {
            (dn / den).abs()
        } else {
            0.0
        }
    }

    /// `u` in the layout `[T, H, W]`, times `k`.
    pub fn u_thw(&self, k: f32) -> Vec<f32> {
        let (t, h, w) = (self.t, self.h, self.w);
        let mut out = vec![0f32; t * h * w];
        out.par_chunks_mut(h * w).enumerate().for_each(|(j, o)| {
            for r in 0..h {
                for (o, &v) in o[r * w..(r + 1) * w].iter_mut().zip(&self.u[(r * t + j) * w..][..w]) {
                    *o = v * k;
                }
            }
        });
        out
    }
}
