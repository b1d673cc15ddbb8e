//! The reference TVAL3 solver, as written in the paper's reference code: every backtracking
//! step of the line search applies `A`, `Aᵀ` and `D` at the new point. [`super::tval3`] (the
//! fused, banded driver of [`super::tiled`]) is tested against it; `bench tval3` times both.

use ndarray::{Array3, ArrayView3};
use rayon::prelude::*;
use std::sync::atomic::{AtomicBool, Ordering};
use tcsense_sensor::{FramePlan, MeasurementMatrix};

use super::{axpy_into, dist2, dot, dot_chunk, norm2, prepare, shape_err, Prepared, TvNorm, Tval3Options, Tval3Report};
use crate::{ModelError, Result};

/// Per-axis periodic forward differences of a cube `[T, H, W]` (flat), scaled by the weights.
pub(super) struct Grad {
    pub(super) t: usize,
    pub(super) h: usize,
    pub(super) w: usize,
    pub(super) wt: f32,
    pub(super) wy: f32,
    pub(super) wx: f32,
}

impl Grad {
    /// `(dt, dy, dx) = D u`, each `[T, H, W]`.
    pub(super) fn apply(&self, u: &[f32], dt: &mut [f32], dy: &mut [f32], dx: &mut [f32]) {
        let (t, h, w) = (self.t, self.h, self.w);
        let plane = h * w;
        dt.par_chunks_mut(plane).zip(dy.par_chunks_mut(plane)).zip(dx.par_chunks_mut(plane)).enumerate().for_each(|(j, ((pt, py), px))| {
            let cur = &u[j * plane..(j + 1) * plane];
            let next = &u[((j + 1) % t) * plane..((j + 1) % t + 1) * plane];
            for ((o, &a), &b) in pt.iter_mut().zip(cur).zip(next) {
                *o = self.wt * (b - a);
            }
            for r in 0..h {
                let row = &cur[r * w..(r + 1) * w];
                let below = &cur[((r + 1) % h) * w..((r + 1) % h + 1) * w];
                for ((o, &a), &b) in py[r * w..(r + 1) * w].iter_mut().zip(row).zip(below) {
                    *o = self.wy * (b - a);
                }
                let ox = &mut px[r * w..(r + 1) * w];
                for c in 0..w - 1 {
                    ox[c] = self.wx * (row[c + 1] - row[c]);
                }
                ox[w - 1] = self.wx * (row[0] - row[w - 1]);
            }
        });
    }

    /// `out = Dᵀ (pt, py, px)`.
    pub(super) fn adjoint(&self, pt: &[f32], py: &[f32], px: &[f32], out: &mut [f32]) {
        let (t, h, w) = (self.t, self.h, self.w);
        let plane = h * w;
        out.par_chunks_mut(plane).enumerate().for_each(|(j, o)| {
            let prev = (j + t - 1) % t;
            let (ct, pt_prev) = (&pt[j * plane..(j + 1) * plane], &pt[prev * plane..(prev + 1) * plane]);
            for ((v, &a), &b) in o.iter_mut().zip(pt_prev).zip(ct) {
                *v = self.wt * (a - b);
            }
            let cy = &py[j * plane..(j + 1) * plane];
            let cx = &px[j * plane..(j + 1) * plane];
            for r in 0..h {
                let above = ((r + h - 1) % h) * w;
                let orow = &mut o[r * w..(r + 1) * w];
                let (ya, yc) = (&cy[above..above + w], &cy[r * w..(r + 1) * w]);
                for ((v, &a), &b) in orow.iter_mut().zip(ya).zip(yc) {
                    *v += self.wy * (a - b);
                }
                let xr = &cx[r * w..(r + 1) * w];
                orow[0] += self.wx * (xr[w - 1] - xr[0]);
                for c in 1..w {
                    orow[c] += self.wx * (xr[c - 1] - xr[c]);
                }
            }
        });
    }
}

/// The scaled operator `s·A` on flat buffers.
struct Op<'a> {
    plan: &'a FramePlan,
    scale: f32,
    t: usize,
    m: usize,
    h: usize,
    w: usize,
}

impl Op<'_> {
    fn forward(&self, u: &[f32], out: &mut [f32]) -> Result<()> {
        let x = ArrayView3::from_shape((self.t, self.h, self.w), u).map_err(|e| shape_err(e, "u"))?;
        let mut y = ndarray::ArrayViewMut3::from_shape((self.m, self.h, self.w), out).map_err(|e| shape_err(e, "Au"))?;
        self.plan.forward_into(&x, &mut y)?;
        if self.scale != 1.0 {
            out.par_iter_mut().for_each(|v| *v *= self.scale);
        }
        Ok(())
    }
    fn adjoint(&self, v: &[f32], out: &mut [f32]) -> Result<()> {
        let y = ArrayView3::from_shape((self.m, self.h, self.w), v).map_err(|e| shape_err(e, "v"))?;
        let mut x = ndarray::ArrayViewMut3::from_shape((self.t, self.h, self.w), out).map_err(|e| shape_err(e, "Aᵀv"))?;
        self.plan.adjoint_into(&y, &mut x)?;
        if self.scale != 1.0 {
            out.par_iter_mut().for_each(|v| *v *= self.scale);
        }
        Ok(())
    }
}

/// Solver state: every buffer is allocated once.
struct Solver<'a> {
    op: Op<'a>,
    grad: Grad,
    tv: TvNorm,
    nonneg: bool,
    b: Vec<f32>,
    atb: Vec<f32>,
    u: Vec<f32>,
    up: Vec<f32>,
    d: Vec<f32>,
    g: Vec<f32>,
    gp: Vec<f32>,
    g2: Vec<f32>,
    g2p: Vec<f32>,
    dtsatd: Vec<f32>,
    step: Vec<f32>,
    du: [Vec<f32>; 3],
    wv: [Vec<f32>; 3],
    v: [Vec<f32>; 3],
    sigma: [Vec<f32>; 3],
    dd: [Vec<f32>; 3],
    au: Vec<f32>,
    resid: Vec<f32>,
    delta: Vec<f32>,
    ad: Vec<f32>,
    lam1: f64,
    lam2: f64,
    lam3: f64,
    lam4: f64,
    lam5: f64,
}

const CH: usize = 8192;

impl Solver<'_> {
    fn f(&self, beta: f64, mu: f64) -> f64 {
        self.lam1 + beta / 2.0 * self.lam2 + mu / 2.0 * self.lam3 - self.lam4 - self.lam5
    }

    /// `w = shrink(Du − σ/β, 1/β)`; sets `lam1 = Σ‖w_i‖`.
    fn shrink(&mut self, beta: f64) {
        let inv = (1.0 / beta) as f32;
        let tv = self.tv;
        let [wt, wy, wx] = &mut self.wv;
        let [dt, dy, dx] = &self.du;
        let [st, sy, sx] = &self.sigma;
        self.lam1 = wt
            .par_chunks_mut(CH)
            .zip(wy.par_chunks_mut(CH))
            .zip(wx.par_chunks_mut(CH))
            .enumerate()
            .map(|(ci, ((ot, oy), ox))| {
                let base = ci * CH;
                let len = ot.len();
                let (dt, dy, dx) = (&dt[base..base + len], &dy[base..base + len], &dx[base..base + len]);
                let (st, sy, sx) = (&st[base..base + len], &sy[base..base + len], &sx[base..base + len]);
                let mut acc = 0f32;
                match tv {
                    TvNorm::Anisotropic => {
                        let sh = |v: f32| v.signum() * (v.abs() - inv).max(0.0);
                        for k in 0..len {
                            ot[k] = sh(dt[k] - st[k] * inv);
                            oy[k] = sh(dy[k] - sy[k] * inv);
                            ox[k] = sh(dx[k] - sx[k] * inv);
                            acc += ot[k].abs() + oy[k].abs() + ox[k].abs();
                        }
                    }
                    TvNorm::Isotropic => {
                        for k in 0..len {
                            let (vt, vy, vx) = (dt[k] - st[k] * inv, dy[k] - sy[k] * inv, dx[k] - sx[k] * inv);
                            let nrm = (vt * vt + vy * vy + vx * vx).sqrt();
                            let f = if nrm > 0.0 { (nrm - inv).max(0.0) / nrm } else { 0.0 };
                            ot[k] = f * vt;
                            oy[k] = f * vy;
                            ox[k] = f * vx;
                            acc += f * nrm;
                        }
                    }
                }
                acc as f64
            })
            .sum();
    }

    /// `V = Du − w`, `g2 = DᵀV`, `lam2 = ‖V‖²`, `lam4 = σᵀV`.
    fn update_v(&mut self) {
        let (mut lam2, mut lam4) = (0f64, 0f64);
        for k in 0..3 {
            let (l2, l4) = self.v[k]
                .par_chunks_mut(CH)
                .zip(self.du[k].par_chunks(CH))
                .zip(self.wv[k].par_chunks(CH))
                .zip(self.sigma[k].par_chunks(CH))
                .map(|(((v, du), w), sg)| {
                    for ((v, &a), &b) in v.iter_mut().zip(du).zip(w) {
                        *v = a - b;
                    }
                    (dot_chunk(v, v), dot_chunk(v, sg))
                })
                .reduce(|| (0.0, 0.0), |x, y| (x.0 + y.0, x.1 + y.1));
            lam2 += l2;
            lam4 += l4;
        }
        self.lam2 = lam2;
        self.lam4 = lam4;
        self.grad.adjoint(&self.v[0], &self.v[1], &self.v[2], &mut self.g2);
    }

    /// With `u` set: `Du`, `Au`, `g = Aᵀ(Au − b)`, then [`Solver::update_v`], `lam3`, `lam5`.
    fn eval(&mut self) -> Result<()> {
        let [dt, dy, dx] = &mut self.du;
        self.grad.apply(&self.u, dt, dy, dx);
        self.op.forward(&self.u, &mut self.au)?;
        self.resid.par_iter_mut().zip(self.au.par_iter()).zip(self.b.par_iter()).for_each(|((r, &a), &b)| *r = a - b);
        self.op.adjoint(&self.au, &mut self.g)?;
        self.g.par_iter_mut().zip(self.atb.par_iter()).for_each(|(g, &a)| *g -= a);
        self.update_v();
        self.lam3 = norm2(&self.resid);
        self.lam5 = dot(&self.delta, &self.resid);
        Ok(())
    }

    /// `d = g2 + (μ/β) g − DtsAtd`.
    /// Also returns `‖d‖²`.
    fn direction(&mut self, mdb: f32) -> f64 {
        self.d
            .par_chunks_mut(CH)
            .zip(self.g2.par_chunks(CH))
            .zip(self.g.par_chunks(CH))
            .zip(self.dtsatd.par_chunks(CH))
            .map(|(((d, g2), g), q)| {
                for i in 0..d.len() {
                    d[i] = g2[i] + mdb * g[i] - q[i];
                }
                dot_chunk(d, d)
            })
            .sum()
    }

    /// Exact steepest-descent step along `d`: `dᵀd / (‖Dd‖² + (μ/β)‖Ad‖²)`.
    fn steepest_tau(&mut self, mdb: f64) -> Result<f64> {
        let [a, b, c] = &mut self.dd;
        self.grad.apply(&self.d, a, b, c);
        let ddd: f64 = self.dd.iter().map(|x| norm2(x)).sum();
        self.op.forward(&self.d, &mut self.ad)?;
        let den = ddd + mdb * norm2(&self.ad);
        let num = norm2(&self.d);
        Ok(if den > 0.0 { (num / den).abs() } else { 0.0 })
    }

    /// `u = max(up − τ d, 0)` (projection only with `nonneg`).
    fn step_from_up(&mut self, tau: f32) {
        let nonneg = self.nonneg;
        self.u.par_chunks_mut(CH).zip(self.up.par_chunks(CH)).zip(self.d.par_chunks(CH)).for_each(|((u, up), d)| {
            for i in 0..u.len() {
                let v = up[i] - tau * d[i];
                u[i] = if nonneg { v.max(0.0) } else { v };
            }
        });
    }
}

/// [`tval3`] as written in the paper's reference code: every backtracking step of the line
/// search applies `A`, `Aᵀ` and `D` at the new point, and every evaluation forms `Du − w`
/// and `Dᵀ(Du − w)`. The same iterates as [`tval3`] up to rounding (the tests compare them);
/// kept as the reference of the optimised solver and for `bench tval3`.
///
/// # Shapes
/// - `y`: `[M, H, W]` → `x̂`: `[T, H, W]`
pub fn tval3_reference(
    a: &MeasurementMatrix,
    plan: &FramePlan,
    y: &ArrayView3<'_, f32>,
    opts: &Tval3Options,
    progress: &(dyn Fn(usize, usize) + Sync),
    cancel: &AtomicBool,
) -> Result<(Array3<f32>, Tval3Report)> {
    solve(a, plan, y, opts, progress, cancel)
}

/// The straightforward solver ([`tval3_reference`]).
fn solve(
    a: &MeasurementMatrix,
    plan: &FramePlan,
    y: &ArrayView3<'_, f32>,
    opts: &Tval3Options,
    progress: &(dyn Fn(usize, usize) + Sync),
    cancel: &AtomicBool,
) -> Result<(Array3<f32>, Tval3Report)> {
    let Prepared { b, scale_a, scl, b_norm, weights } = prepare(a, plan, y, opts)?;
    let (m, h, w, t) = (plan.taps(), plan.height(), plan.width(), plan.bins());
    let (n, nm) = (t * h * w, m * h * w);
    let op = Op { plan, scale: scale_a, t, m, h, w };
    let grad = Grad { t, h, w, wt: weights[0], wy: weights[1], wx: weights[2] };
    let (muf, betaf) = (opts.mu, opts.beta);
    let mut mu = opts.mu0.unwrap_or(muf).min(muf);
    let mut beta = opts.beta0.unwrap_or(betaf).min(betaf);

    let z = || vec![0f32; n];
    let zm = || vec![0f32; nm];
    let mut atb = z();
    op.adjoint(&b, &mut atb)?;
    let mut s = Solver {
        op,
        grad,
        tv: opts.tv_norm,
        nonneg: opts.nonneg,
        b,
        u: atb.clone(),
        atb,
        up: z(),
        d: z(),
        g: z(),
        gp: z(),
        g2: z(),
        g2p: z(),
        dtsatd: z(),
        step: z(),
        du: [z(), z(), z()],
        wv: [z(), z(), z()],
        v: [z(), z(), z()],
        sigma: [z(), z(), z()],
        dd: [z(), z(), z()],
        au: zm(),
        resid: zm(),
        delta: zm(),
        ad: zm(),
        lam1: 0.0,
        lam2: 0.0,
        lam3: 0.0,
        lam4: 0.0,
        lam5: 0.0,
    };
    if opts.nonneg {
        s.u.par_iter_mut().for_each(|v| *v = v.max(0.0));
    }
    // initial w from Du (σ = 0), then gradient and direction
    {
        let [dt, dy, dx] = &mut s.du;
        s.grad.apply(&s.u, dt, dy, dx);
    }
    s.shrink(beta);
    s.eval()?;
    let mut f = s.f(beta, mu);
    let mut mdb = mu / beta;
    s.direction(mdb as f32);

    let mut report = Tval3Report { outer: 1, ..Default::default() };
    let mut count = 1usize;
    let mut q = 1.0f64;
    let mut c = f;
    let mut gam = opts.gam;
    let mut have_prev = false;
    let mut rcd_u = s.u.clone();
    for ii in 1..=opts.maxit {
        if cancel.load(Ordering::Relaxed) {
            return Err(ModelError::Cancelled);
        }
        // step length: BB after the first iteration, exact steepest descent otherwise
        let tau = if have_prev {
            let (ss, sy) =
                s.u.par_chunks(CH)
                    .zip(s.up.par_chunks(CH))
                    .zip(s.g.par_chunks(CH).zip(s.gp.par_chunks(CH)))
                    .zip(s.g2.par_chunks(CH).zip(s.g2p.par_chunks(CH)))
                    .map(|(((u, up), (g, gp)), (g2, g2p))| {
                        let m = mdb as f32;
                        let (mut a, mut b) = ([0f32; 8], [0f32; 8]);
                        for i in 0..u.len() {
                            let uu = u[i] - up[i];
                            a[i % 8] += uu * uu;
                            b[i % 8] += uu * ((g2[i] - g2p[i]) + m * (g[i] - gp[i]));
                        }
                        (a.iter().map(|&v| v as f64).sum::<f64>(), b.iter().map(|&v| v as f64).sum::<f64>())
                    })
                    .reduce(|| (0.0, 0.0), |x, y| (x.0 + y.0, x.1 + y.1));
            (ss / sy.max(f64::EPSILON)).abs()
        } else {
            s.steepest_tau(mdb)?
        };
        let first_iter = !have_prev;
        // keep previous values
        s.up.copy_from_slice(&s.u);
        s.gp.copy_from_slice(&s.g);
        s.g2p.copy_from_slice(&s.g2);
        // one projected gradient step
        s.step_from_up(tau as f32);
        s.eval()?;
        f = s.f(beta, mu);
        // nonmonotone Armijo line search along step = u − up
        let mut alpha = 1.0f64;
        let cst = opts.c * beta * tau * norm2(&s.d);
        axpy_into(&mut s.step, &s.u, -1.0, &s.up);
        let mut cnt = 0;
        while f > c - alpha * cst {
            if cnt == 5 {
                gam *= opts.rate_gam;
                let tau_sd = s.steepest_tau(mdb)?;
                s.step_from_up(tau_sd as f32);
                {
                    let [dt, dy, dx] = &mut s.du;
                    s.grad.apply(&s.u, dt, dy, dx);
                }
                s.shrink(beta);
                s.eval()?;
                f = s.f(beta, mu);
                alpha = 0.0;
                report.fallbacks += 1;
                break;
            }
            alpha *= opts.gamma;
            let a32 = alpha as f32;
            s.u.par_chunks_mut(CH).zip(s.up.par_chunks(CH)).zip(s.step.par_chunks(CH)).for_each(|((u, up), st)| {
                for i in 0..u.len() {
                    u[i] = up[i] + a32 * st[i];
                }
            });
            s.eval()?;
            f = s.f(beta, mu);
            cnt += 1;
            report.backtracks += 1;
        }
        if alpha != 0.0 {
            // w-step at the accepted u
            s.shrink(beta);
            s.update_v();
            f = s.f(beta, mu);
        }
        // reference value of the nonmonotone search
        let qp = q;
        q = gam * qp + 1.0;
        c = (gam * qp * c + f) / q;
        let (nrm_uup, nrm_up) = (dist2(&s.u, &s.up).sqrt(), norm2(&s.up).sqrt().max(f64::MIN_POSITIVE));
        s.direction(mdb as f32);
        have_prev = true;
        report.iterations = ii;
        progress(ii, opts.maxit);

        if nrm_uup / nrm_up < opts.tol_inn && !first_iter {
            count += 1;
            let rel_out = dist2(&s.u, &rcd_u).sqrt() / nrm_up;
            rcd_u.copy_from_slice(&s.u);
            report.rel_change = rel_out;
            report.outer = count;
            if rel_out < opts.tol || count > opts.maxcnt {
                break;
            }
            // multipliers: σ ← σ − β(Du − w) = σ − βV, δ ← δ − μ(Au − b)
            let (b32, m32) = (beta as f32, mu as f32);
            for k in 0..3 {
                s.sigma[k].par_iter_mut().zip(s.v[k].par_iter()).for_each(|(sg, &v)| *sg -= b32 * v);
            }
            s.delta.par_iter_mut().zip(s.resid.par_iter()).for_each(|(dl, &r)| *dl -= m32 * r);
            s.lam4 = (0..3).map(|k| dot(&s.sigma[k], &s.v[k])).sum();
            s.lam5 = dot(&s.delta, &s.resid);
            // continuation
            let beta0 = beta;
            beta = (beta * opts.rate_ctn).min(betaf);
            mu = (mu * opts.rate_ctn).min(muf);
            mdb = mu / beta;
            f = s.f(beta, mu);
            // (Dᵀσ + Aᵀδ)/β at the new multipliers equals −(β0/β)·d at the old ones
            let r = -(beta0 / beta) as f32;
            s.dtsatd.par_iter_mut().zip(s.d.par_iter()).for_each(|(q, &d)| *q = r * d);
            s.direction(mdb as f32);
            have_prev = false;
            gam = opts.gam;
            q = 1.0;
            c = f;
        }
    }
    report.residual = if b_norm > 0.0 { norm2(&s.resid).sqrt() / b_norm } else { 0.0 };
    let inv = 1.0 / scl;
    let out = Array3::from_shape_vec((t, h, w), s.u.iter().map(|v| v * inv).collect()).map_err(|e| shape_err(e, "x̂"))?;
    Ok((out, report))
}
