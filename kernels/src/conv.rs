//! 3×3 "same" convolutions (stride 1, zero padding 1) on contiguous `f32` NCHW buffers:
//! the forward pass and both backward passes, as im2col GEMMs.
//!
//! ```text
//! forward      y_b [C_out, HW]     = Σ_ky W_ky [C_out, 3·C_in] · col_ky(x_b) [3·C_in, HW]  (+ bias)
//! backward x   dx_b [C_in, HW]     = Σ_ky W̃_ky [C_in, 3·C_out] · col_ky(g_b) [3·C_out, HW]
//! backward W   dW_ky [C_out, 3·C_in] = Σ_b g_b [C_out, HW] · col_ky(x_b)ᵀ [HW, 3·C_in]
//! ```
//!
//! `col_ky(x)[c·3 + kx, (y, x)] = x[c, y + ky − 1, x + kx − 1]` (zero outside the frame),
//! `W_ky[co, c·3 + kx] = W[co, c, ky, kx]` and `W̃[c_in, c_out, t] = W[c_out, c_in, 8 − t]` (the
//! kernel transposed and rotated by 180°). The three `col_ky` are views of one buffer holding
//! three column-shifted copies of the band's rows plus one row above and below: moving down
//! one kernel row is moving `W` columns along it. So a pass copies its input three times, not
//! nine, and runs three GEMMs with an inner dimension of `3·C`. The bias is one more column of
//! `W_0` against a row of ones.
//!
//! burn-flex runs the weight gradient of a conv as a generic conv whose GEMM has an inner
//! dimension of `H·W` and 9 columns; here it is GEMMs with `3·C_in` rows and `C_out` columns,
//! which is what the training step of ADMM-Net spent most of its time on.
//!
//! Work is cut into tasks of one batch item × one band of rows, sized so that a band's buffer
//! (about 1 MiB) stays in the L2 cache of the core that builds it and multiplies it. Tasks run
//! on rayon; each thread keeps one scratch buffer, so the hot loop does not allocate.
#![allow(unsafe_code)] // `gemm::gemm` is an unsafe fn; every view is bounds-checked before it

use rayon::prelude::*;

use crate::plane::{with_scratch, Kernel, Plane, SharedOut, Source, BAND_ELEMS, CONV_NANOS};

/// Sizes of one 3×3 convolution over a batch.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Conv3x3 {
    /// Batch `B`.
    pub batch: usize,
    /// Input channels `C_in`.
    pub c_in: usize,
    /// Output channels `C_out`.
    pub c_out: usize,
    /// Frame height `H`.
    pub height: usize,
    /// Frame width `W`.
    pub width: usize,
}

/// Seconds of thread time spent inside the convolutions' multiply-add loops so far (GEMM
/// calls and the direct loops, summed over threads): `bench train` reads it before and after
/// a step to tell the share of the step outside them.
pub fn conv_seconds() -> f64 {
    CONV_NANOS.load(std::sync::atomic::Ordering::Relaxed) as f64 * 1e-9
}

/// Groups the weight gradient's tasks are summed in (see [`Conv3x3::backward_w`]): enough to
/// keep two cores busy with work stealing, few enough that the partials stay small.
const WGRAD_GROUPS: usize = 16;

impl Conv3x3 {
    pub(crate) fn hw(&self) -> usize {
        self.height * self.width
    }
    /// Elements of the input `[B, C_in, H, W]`.
    pub fn x_len(&self) -> usize {
        self.batch * self.c_in * self.hw()
    }
    /// Elements of the output `[B, C_out, H, W]`.
    pub fn y_len(&self) -> usize {
        self.batch * self.c_out * self.hw()
    }
    /// Elements of the kernel `[C_out, C_in, 3, 3]`.
    pub fn w_len(&self) -> usize {
        self.c_out * self.c_in * 9
    }

    /// `y = conv(x, w) + bias`.
    ///
    /// # Shapes
    /// - `x`: `[B, C_in, H, W]`, `w`: `[C_out, C_in, 3, 3]`, `bias`: `[C_out]` → `y`: `[B, C_out, H, W]`
    pub fn forward(&self, x: &[f32], w: &[f32], bias: Option<&[f32]>, y: &mut [f32]) {
        assert_eq!(x.len(), self.x_len(), "conv3x3 forward: x");
        assert_eq!(w.len(), self.w_len(), "conv3x3 forward: w");
        assert_eq!(y.len(), self.y_len(), "conv3x3 forward: y");
        if let Some(b) = bias {
            assert_eq!(b.len(), self.c_out, "conv3x3 forward: bias");
        }
        if self.y_len() == 0 {
            return;
        }
        let kernel = Kernel::new(self.c_out, self.c_in, |co, ci, t| w[(co * self.c_in + ci) * 9 + t], bias);
        correlate(self.plane(self.c_in, self.c_out), Source::Items, x, &kernel, y);
    }

    /// Gradient with respect to the input: `dx = conv(g, W̃)`.
    ///
    /// # Shapes
    /// - `g`: `[B, C_out, H, W]`, `w`: `[C_out, C_in, 3, 3]` → `dx`: `[B, C_in, H, W]`
    pub fn backward_x(&self, g: &[f32], w: &[f32], dx: &mut [f32]) {
        assert_eq!(g.len(), self.y_len(), "conv3x3 backward_x: g");
        assert_eq!(w.len(), self.w_len(), "conv3x3 backward_x: w");
        assert_eq!(dx.len(), self.x_len(), "conv3x3 backward_x: dx");
        if self.x_len() == 0 {
            return;
        }
        // W̃[ci, co, t] = W[co, ci, 8 − t]
        let kernel = Kernel::new(self.c_in, self.c_out, |ci, co, t| w[(co * self.c_in + ci) * 9 + 8 - t], None);
        correlate(self.plane(self.c_out, self.c_in), Source::Items, g, &kernel, dx);
    }

    /// Gradient with respect to the kernel: `dW = Σ_b g_b · col(x_b)ᵀ`.
    ///
    /// # Shapes
    /// - `x`: `[B, C_in, H, W]`, `g`: `[B, C_out, H, W]` → `dw`: `[C_out, C_in, 3, 3]`
    pub fn backward_w(&self, x: &[f32], g: &[f32], dw: &mut [f32]) {
        assert_eq!(x.len(), self.x_len(), "conv3x3 backward_w: x");
        self.backward_w_from(Source::Items, x, g, dw);
    }

    /// [`Conv3x3::backward_w`] for an input whose items are gathered through `src` (`self.c_in`
    /// is the channels of a gathered item).
    pub(crate) fn backward_w_from(&self, src: Source, x: &[f32], g: &[f32], dw: &mut [f32]) {
        assert_eq!(x.len(), src.input_len(self.batch, self.c_in, self.hw()), "conv3x3 backward_w: x");
        assert_eq!(g.len(), self.y_len(), "conv3x3 backward_w: g");
        assert_eq!(dw.len(), self.w_len(), "conv3x3 backward_w: dw");
        dw.fill(0.0);
        if self.y_len() == 0 || self.c_in == 0 {
            return;
        }
        let p = self.plane(self.c_in, self.c_out);
        let (hw, k3) = (self.hw(), self.c_in * 3);
        // Accumulated as dW_kyᵀ: acc[(ky·3C_in + ci·3 + kx)·C_out + co]. The tasks are cut into
        // a fixed number of contiguous groups (set by the problem, not by the threads), each
        // summed in order, and the groups' partials added in order: the same bytes on any
        // number of threads and any scheduling (rayon's adaptive fold/reduce split the sum
        // differently from run to run).
        let tasks = self.batch * p.bands();
        let groups = tasks.min(WGRAD_GROUPS);
        let partials: Vec<Vec<f32>> = (0..groups)
            .into_par_iter()
            .map(|gi| {
                let mut acc = vec![0.0f32; dw.len()];
                for task in gi * tasks / groups..(gi + 1) * tasks / groups {
                    let (b, (y0, y1)) = (task / p.bands(), p.band(task % p.bands()));
                    let n = (y1 - y0) * p.w;
                    let ld = p.ld(y0, y1);
                    with_scratch(k3 * ld, |col| {
                        shifts(x, src, b, p, y0, y1, ld, col);
                        let gb = &g[b * self.c_out * hw..(b + 1) * self.c_out * hw];
                        for ky in 0..3 {
                            // dW_kyᵀ [3C_in, C_out] += col_ky [3C_in, n] · g_bᵀ [n, C_out]
                            sgemm(
                                Dst::Slice(&mut acc, Mat { m: k3, n: self.c_out, rs: self.c_out, cs: 1, off: ky * k3 * self.c_out }),
                                (col, Mat { m: k3, n, rs: ld, cs: 1, off: ky * p.w }),
                                (gb, Mat { m: n, n: self.c_out, rs: 1, cs: hw, off: y0 * p.w }),
                                true,
                            );
                        }
                    });
                }
                acc
            })
            .collect();
        let mut total = vec![0.0f32; dw.len()];
        for part in &partials {
            total.iter_mut().zip(part).for_each(|(u, v)| *u += v);
        }
        for co in 0..self.c_out {
            for ci in 0..self.c_in {
                for ky in 0..3 {
                    for kx in 0..3 {
                        dw[(co * self.c_in + ci) * 9 + ky * 3 + kx] = total[(ky * k3 + ci * 3 + kx) * self.c_out + co];
                    }
                }
            }
        }
    }

    /// Gradient with respect to the bias: `db[c] = Σ_{b,y,x} g[b, c, y, x]`.
    ///
    /// # Shapes
    /// - `g`: `[B, C_out, H, W]` → `db`: `[C_out]`
    pub fn backward_bias(&self, g: &[f32], db: &mut [f32]) {
        assert_eq!(g.len(), self.y_len(), "conv3x3 backward_bias: g");
        assert_eq!(db.len(), self.c_out, "conv3x3 backward_bias: db");
        let hw = self.hw();
        if hw == 0 {
            db.fill(0.0);
            return;
        }
        // one sum per plane, in parallel; each in 16 f32 lanes (vectorised) added up in f64, the
        // planes of a channel added in batch order: the same bytes on any number of threads
        let planes: Vec<f64> = g
            .par_chunks_exact(hw)
            .map(|plane| {
                let mut lanes = [0.0f32; 16];
                let mut chunks = plane.chunks_exact(16);
                for c in &mut chunks {
                    lanes.iter_mut().zip(c).for_each(|(l, &v)| *l += v);
                }
                lanes.iter().map(|&l| l as f64).sum::<f64>() + chunks.remainder().iter().map(|&v| v as f64).sum::<f64>()
            })
            .collect();
        for (c, d) in db.iter_mut().enumerate() {
            *d = (0..self.batch).map(|b| planes[b * self.c_out + c]).sum::<f64>() as f32;
        }
    }

    /// The pass from `c_src` to `c_dst` channels, in bands whose shifted copies fit [`BAND_ELEMS`].
    pub(crate) fn plane(&self, c_src: usize, c_dst: usize) -> Plane {
        let k = c_src * 3 + 1;
        let plane = Plane { batch: self.batch, c_src, c_dst, h: self.height, w: self.width, rows: 1 };
        plane.banded((BAND_ELEMS / (k * self.width.max(1))).saturating_sub(2))
    }
}

/// `out_b = Σ_ky K_ky · col_ky(in_b) (+ bias)` for every batch item, one task per (item, band).
///
/// # Shapes
/// - `input`: `[B, c_src, H, W]`, `out`: `[B, c_dst, H, W]`
pub(crate) fn correlate(p: Plane, src: Source, input: &[f32], kernel: &Kernel, out: &mut [f32]) {
    let hw = p.h * p.w;
    let (k3, ks) = (p.c_src * 3, p.c_src * 3 + 1);
    assert!(kernel.c_src == p.c_src && kernel.c_dst == p.c_dst);
    assert_eq!(input.len(), src.input_len(p.batch, p.c_src, hw));
    assert_eq!(out.len(), p.batch * p.c_dst * hw);
    if crate::direct::suits(p) {
        return crate::direct::correlate(p, src, input, kernel, out);
    }
    let out = SharedOut { ptr: out.as_mut_ptr(), len: out.len() };
    (0..p.batch * p.bands()).into_par_iter().for_each(|task| {
        let (b, (y0, y1)) = (task / p.bands(), p.band(task % p.bands()));
        let n = (y1 - y0) * p.w;
        let ld = p.ld(y0, y1);
        with_scratch(ks * ld, |col| {
            shifts(input, src, b, p, y0, y1, ld, &mut col[..k3 * ld]);
            col[k3 * ld..k3 * ld + n].fill(1.0); // the bias row, read by the ky = 0 product only
                                                 // out_b[:, band] [c_dst, n] (+)= K_ky [c_dst, 3c_src (+1)] · col_ky [3c_src (+1), n].
                                                 // The tasks' views are disjoint: each covers its own band of rows of its own item.
            let dst = Mat { m: p.c_dst, n, rs: hw, cs: 1, off: b * p.c_dst * hw + y0 * p.w };
            for ky in 0..3 {
                let k = if ky == 0 { ks } else { k3 };
                sgemm(
                    Dst::Shared(out, dst),
                    (&kernel.k, Mat { m: p.c_dst, n: k, rs: ks, cs: 1, off: ky * p.c_dst * ks }),
                    (col, Mat { m: k, n, rs: ld, cs: 1, off: ky * p.w }),
                    ky > 0,
                );
            }
        });
    });
}

/// The three column shifts of rows `y0 − 1 ..= y1` of item `item` (zero outside the frame):
/// `col[(c·3 + kx)·ld + (y − y0 + 1)·W + x] = x_item[c, y, x + kx − 1]`, where channel `c` of
/// the item is the plane `src` points at. The im2col matrix of kernel row `ky` is then the
/// strided view starting at column `ky·W` — three copies of the input instead of nine.
///
/// # Shapes
/// - `x`: the whole input (`src` finds the item's `[c_src, H, W]` planes) → `col`: `[c_src·3, ld]`
#[allow(clippy::too_many_arguments)] // the band geometry, spelled out as the callers have it
fn shifts(x: &[f32], src: Source, item: usize, p: Plane, y0: usize, y1: usize, ld: usize, col: &mut [f32]) {
    let (h, w) = (p.h, p.w);
    debug_assert_eq!(col.len(), p.c_src * 3 * ld);
    for (r, dst) in col.chunks_exact_mut(ld).enumerate() {
        let (ci, kx) = (r / 3, r % 3);
        let at = src.plane(item, ci, p.c_src, h * w);
        let plane = &x[at..at + h * w];
        for (k, d) in dst[..(y1 - y0 + 2) * w].chunks_exact_mut(w).enumerate() {
            let sy = (y0 + k) as isize - 1;
            if sy < 0 || sy >= h as isize {
                d.fill(0.0);
                continue;
            }
            let s = &plane[sy as usize * w..(sy as usize + 1) * w];
            match kx {
                0 => {
                    d[0] = 0.0;
                    d[1..].copy_from_slice(&s[..w - 1]);
                }
                1 => d.copy_from_slice(s),
                _ => {
                    d[..w - 1].copy_from_slice(&s[1..]);
                    d[w - 1] = 0.0;
                }
            }
        }
    }
}

/// A strided `m × n` matrix view starting at element `off` of a buffer.
#[derive(Clone, Copy, Debug)]
struct Mat {
    m: usize,
    n: usize,
    rs: usize,
    cs: usize,
    off: usize,
}

impl Mat {
    /// Panics unless every element of the view lies inside a buffer of `len` elements.
    fn check(&self, len: usize, what: &str) {
        assert!(self.m > 0 && self.n > 0, "sgemm: empty {what}");
        let last = self.off + (self.m - 1) * self.rs + (self.n - 1) * self.cs;
        assert!(last < len, "sgemm: {what} view ends at {last}, buffer has {len}");
    }
}

/// Where a product goes: a slice this task owns, or its own disjoint view of a shared buffer.
enum Dst<'a> {
    Slice(&'a mut [f32], Mat),
    Shared(SharedOut, Mat),
}

/// `dst (+)= lhs · rhs` on strided views, single-threaded, through the `gemm` crate (AVX2 or
/// AVX-512 kernels chosen at run time).
fn sgemm(dst: Dst<'_>, (lhs, lv): (&[f32], Mat), (rhs, rv): (&[f32], Mat), accumulate: bool) {
    let (ptr, dv) = match dst {
        Dst::Slice(s, v) => {
            v.check(s.len(), "dst");
            (s.as_mut_ptr(), v)
        }
        Dst::Shared(s, v) => {
            v.check(s.len, "dst");
            (s.ptr, v)
        }
    };
    assert!(dv.m == lv.m && dv.n == rv.n && lv.n == rv.m, "sgemm: shapes {dv:?} = {lv:?} · {rv:?}");
    lv.check(lhs.len(), "lhs");
    rv.check(rhs.len(), "rhs");
    let t0 = std::time::Instant::now();
    // SAFETY: the three views were checked to lie inside their buffers. The destination is
    // either a slice borrowed mutably (so it aliases nothing) or a shared output whose tasks
    // write disjoint views while the caller holds the only other borrow of it.
    unsafe {
        gemm::gemm(
            dv.m,
            dv.n,
            lv.n,
            ptr.add(dv.off),
            dv.cs as isize,
            dv.rs as isize,
            accumulate,
            lhs.as_ptr().add(lv.off),
            lv.cs as isize,
            lv.rs as isize,
            rhs.as_ptr().add(rv.off),
            rv.cs as isize,
            rv.rs as isize,
            1.0,
            1.0,
            false,
            false,
            false,
            gemm::Parallelism::None,
        );
    }
    CONV_NANOS.fetch_add(t0.elapsed().as_nanos() as u64, std::sync::atomic::Ordering::Relaxed);
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// Deterministic values in [−1, 1) (a linear congruential sequence).
    pub(crate) fn lcg(n: usize, seed: u64) -> Vec<f32> {
        let mut s = seed;
        (0..n)
            .map(|_| {
                s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                ((s >> 33) as f64 / (1u64 << 31) as f64 * 2.0 - 1.0) as f32
            })
            .collect()
    }

    /// Direct f64 correlation, the definition.
    fn direct(d: &Conv3x3, x: &[f32], w: &[f32], bias: &[f32]) -> Vec<f64> {
        let (h, wd) = (d.height as isize, d.width as isize);
        let mut y = vec![0.0f64; d.y_len()];
        for b in 0..d.batch {
            for co in 0..d.c_out {
                for yy in 0..h {
                    for xx in 0..wd {
                        let mut s = bias[co] as f64;
                        for ci in 0..d.c_in {
                            for ky in 0..3isize {
                                for kx in 0..3isize {
                                    let (sy, sx) = (yy + ky - 1, xx + kx - 1);
                                    if sy < 0 || sy >= h || sx < 0 || sx >= wd {
                                        continue;
                                    }
                                    let xi = ((b * d.c_in + ci) as isize * h + sy) * wd + sx;
                                    let wi = (co * d.c_in + ci) * 9 + (ky * 3 + kx) as usize;
                                    s += x[xi as usize] as f64 * w[wi] as f64;
                                }
                            }
                        }
                        y[((b * d.c_out + co) as isize * h + yy) as usize * d.width + xx as usize] = s;
                    }
                }
            }
        }
        y
    }

    /// `a` equals the reference `b` within `tol` of `b`'s largest magnitude (at least 1).
    pub(crate) fn close(a: &[f32], b: &[f64], tol: f64, what: &str) {
        assert_eq!(a.len(), b.len(), "{what}: length");
        let scale = b.iter().fold(1.0f64, |m, v| m.max(v.abs()));
        for (i, (&p, &q)) in a.iter().zip(b).enumerate() {
            assert!((p as f64 - q).abs() <= tol * scale, "{what}[{i}]: {p} vs {q}");
        }
    }

    const SIZES: [Conv3x3; 8] = [
        Conv3x3 { batch: 2, c_in: 3, c_out: 5, height: 7, width: 6 },
        Conv3x3 { batch: 1, c_in: 4, c_out: 4, height: 1, width: 9 },
        Conv3x3 { batch: 1, c_in: 2, c_out: 3, height: 8, width: 1 },
        Conv3x3 { batch: 3, c_in: 1, c_out: 2, height: 2, width: 2 },
        Conv3x3 { batch: 2, c_in: 2, c_out: 3, height: 70, width: 100 },
        // 3·32 + 1 rows × 100 columns: 2 bands of 10 rows
        Conv3x3 { batch: 2, c_in: 32, c_out: 3, height: 20, width: 100 },
        // frames wide enough for the direct loops (crate::direct), a partial last chunk
        Conv3x3 { batch: 2, c_in: 3, c_out: 5, height: 4, width: 150 },
        Conv3x3 { batch: 1, c_in: 8, c_out: 8, height: 3, width: 130 },
    ];

    #[test]
    fn bands_cover_the_frame() {
        // (3·32 + 1)·100 elements per row: 25 rows per band at most, so 2 bands of 10 rows
        let p = SIZES[5].plane(32, 3);
        assert_eq!((p.rows, p.bands(), p.band(1)), (10, 2, (10, 20)));
        let d = Conv3x3 { batch: 1, c_in: 32, c_out: 32, height: 188, width: 212 };
        let p = d.plane(32, 32);
        assert!(p.rows * 97 * 212 <= BAND_ELEMS && p.bands() * p.rows >= 188 && (p.bands() - 1) * p.rows < 188, "{p:?}");
    }

    #[test]
    fn forward_equals_the_direct_sum() {
        for (i, d) in SIZES.iter().enumerate() {
            let (x, w, bias) = (lcg(d.x_len(), 1 + i as u64), lcg(d.w_len(), 10 + i as u64), lcg(d.c_out, 20));
            let mut y = vec![f32::NAN; d.y_len()];
            d.forward(&x, &w, Some(&bias), &mut y);
            close(&y, &direct(d, &x, &w, &bias), 1e-5, &format!("{d:?} y"));
        }
    }

    /// The backward passes are the adjoints of the forward map: ⟨conv(x), g⟩ = ⟨x, dx(g)⟩ and
    /// ⟨conv_w(x), g⟩ = ⟨w, dW(x, g)⟩, checked against finite sums over every element.
    #[test]
    fn backward_passes_are_the_exact_gradients() {
        for (i, d) in SIZES.iter().enumerate() {
            let (x, w, g) = (lcg(d.x_len(), 3 + i as u64), lcg(d.w_len(), 30 + i as u64), lcg(d.y_len(), 60 + i as u64));
            let zero = vec![0.0f32; d.c_out];
            // dL/dx[j] for L = ⟨y, g⟩ is Σ_i g_i ∂y_i/∂x_j: compare against the direct map's
            // transpose, built column by column on small sizes and by inner products on the large one.
            let mut dx = vec![f32::NAN; d.x_len()];
            d.backward_x(&g, &w, &mut dx);
            let mut dw = vec![f32::NAN; d.w_len()];
            d.backward_w(&x, &g, &mut dw);
            let mut db = vec![f32::NAN; d.c_out];
            d.backward_bias(&g, &mut db);
            let y = direct(d, &x, &w, &zero);
            let lhs: f64 = y.iter().zip(&g).map(|(a, &b)| a * b as f64).sum();
            let via_x: f64 = dx.iter().zip(&x).map(|(&a, &b)| a as f64 * b as f64).sum();
            let via_w: f64 = dw.iter().zip(&w).map(|(&a, &b)| a as f64 * b as f64).sum();
            assert!((lhs - via_x).abs() <= 1e-4 * lhs.abs().max(1.0), "{d:?}: ⟨y,g⟩ {lhs} vs ⟨x,dx⟩ {via_x}");
            assert!((lhs - via_w).abs() <= 1e-4 * lhs.abs().max(1.0), "{d:?}: ⟨y,g⟩ {lhs} vs ⟨w,dW⟩ {via_w}");
            let sums: Vec<f64> = (0..d.c_out)
                .map(|c| {
                    (0..d.batch).flat_map(|b| g[(b * d.c_out + c) * d.hw()..(b * d.c_out + c + 1) * d.hw()].iter()).map(|&v| v as f64).sum()
                })
                .collect();
            close(&db, &sums, 1e-6, "db");
            if d.x_len() <= 200 {
                // element-wise: dx[j] = ⟨conv(e_j), g⟩, dW[j] = ⟨conv_{e_j}(x), g⟩
                for j in 0..d.x_len() {
                    let mut e = vec![0.0f32; d.x_len()];
                    e[j] = 1.0;
                    let want: f64 = direct(d, &e, &w, &zero).iter().zip(&g).map(|(a, &b)| a * b as f64).sum();
                    assert!((dx[j] as f64 - want).abs() < 1e-5, "{d:?} dx[{j}]: {} vs {want}", dx[j]);
                }
                for j in 0..d.w_len() {
                    let mut e = vec![0.0f32; d.w_len()];
                    e[j] = 1.0;
                    let want: f64 = direct(d, &x, &e, &zero).iter().zip(&g).map(|(a, &b)| a * b as f64).sum();
                    assert!((dw[j] as f64 - want).abs() < 1e-4, "{d:?} dW[{j}]: {} vs {want}", dw[j]);
                }
            }
        }
    }
}
