//! Direct 3×3 correlation for passes with few output channels (the delay prior's `C = 4`
//! channels per bin and its single output channel, the U-Net's first level, every input
//! gradient into few channels).
//!
//! ```text
//! out[i, d, y, x] = bias[d] + Σ_s Σ_{ky,kx} K[d, s, ky, kx] · in_i[s, y + ky − 1, x + kx − 1]
//! ```
//!
//! With `c_dst` of a few channels the im2col GEMM of [`crate::conv`] has a handful of rows: it
//! copies its input three times (the shifts) and the GEMM packs that copy once more, then does
//! few multiply-adds per value copied (measured: 46 % of a delay-prior inference in those
//! copies, 30 % in the GEMM). Here every output chunk of two vectors of pixels × up to four
//! output channels is accumulated in registers over all `(s, ky, kx)` from unaligned loads of
//! the input rows, in place: two loads of the input per eight fused multiply-adds, and no copy
//! but a zero-padded window for the chunks at the frame's left and right edges. (Measured and
//! not kept: copying each task's band into zero-padded rows — with the delay taps every frame
//! was copied three times, 22 % of an inference, 2.3–2.6 s against 2.0–2.4 s per 188×212×256
//! frame; the first and last columns in scalar code and every chunk in place, 2.5–2.8 s: the
//! two scalar pixels cost as many instructions as the row's vector chunks.) The sums run in a fixed order, so the result is
//! the same on any number of threads.
#![allow(unsafe_code)] // disjoint parallel writes into the output planes, see `correlate`

use rayon::prelude::*;

use crate::plane::{with_scratch, Kernel, Plane, SharedOut, Source, BAND_ELEMS};

/// Passes with at most this many output channels, from at most [`MAX_SRC`] input channels, run
/// here instead of the im2col GEMM (with more input channels the GEMM's long inner dimension
/// wins: the U-Net's first layer, `T → 8`, measured slower here).
pub(crate) const MAX_DST: usize = 8;
/// See [`MAX_DST`].
pub(crate) const MAX_SRC: usize = 48;
/// Frames narrower than this run the im2col GEMM: their chunks are mostly at the edges, which
/// read through zero-padded copies (measured at 64×64: a delay-prior training step 221–228 ms
/// here against 180–192 ms with the GEMM; at 188×212 inference is faster here).
pub(crate) const MIN_WIDTH: usize = 128;

/// Whether a pass of geometry `p` runs here (see [`MAX_DST`], [`MIN_WIDTH`]).
pub(crate) fn suits(p: Plane) -> bool {
    p.c_dst <= MAX_DST && p.c_src <= MAX_SRC && p.w >= MIN_WIDTH
}
/// The widest output chunk: two vectors, 32 pixels with AVX-512 (16 with AVX2).
const LANES: usize = 32;
/// Output channels accumulated together.
const GROUP: usize = 4;

/// `out_i = K ⋆ in_i (+ bias)` for every item `i`, one task per (item, band of rows).
///
/// # Shapes
/// - `input`: what `src` reads `[c_src, H, W]` items from, `out`: `[B, c_dst, H, W]`
pub(crate) fn correlate(p: Plane, src: Source, input: &[f32], kernel: &Kernel, out: &mut [f32]) {
    let (h, w, c_src, c_dst) = (p.h, p.w, p.c_src, p.c_dst);
    let hw = h * w;
    assert!(kernel.c_src == c_src && kernel.c_dst == c_dst);
    assert_eq!(out.len(), p.batch * c_dst * hw);
    if out.is_empty() {
        return;
    }
    // weights as wd[(s·9 + ky·3 + kx)·c_dst + d], bias[d] (from the GEMM layout k[ky][d][s·3 + kx])
    let ks = 3 * c_src + 1;
    let mut wd = vec![0.0f32; c_src * 9 * c_dst];
    for ky in 0..3 {
        for d in 0..c_dst {
            for s in 0..c_src {
                for kx in 0..3 {
                    wd[(s * 9 + ky * 3 + kx) * c_dst + d] = kernel.k[(ky * c_dst + d) * ks + s * 3 + kx];
                }
            }
        }
    }
    let bias: Vec<f32> = (0..c_dst).map(|d| kernel.k[d * ks + 3 * c_src]).collect();
    // bands of about BAND_ELEMS input values per task (there is no im2col buffer to size)
    let p = p.banded(BAND_ELEMS / (c_src.max(1) * w.max(1)));
    let bands = p.bands();
    let base = SharedOut { ptr: out.as_mut_ptr(), len: out.len() };
    (0..p.batch * bands).into_par_iter().for_each(|task| {
        let (item, (y0, y1)) = (task / bands, p.band(task % bands));
        // SAFETY: each task writes rows y0..y1 of every output plane of its own item: views that
        // no other task touches (the bands partition the rows, each (item, band) is one task),
        // inside `out`, which stays borrowed mutably for the whole loop.
        let mut planes: Vec<&mut [f32]> = (0..c_dst)
            .map(|d| {
                let off = (item * c_dst + d) * hw + y0 * w;
                debug_assert!(off + (y1 - y0) * w <= base.len);
                unsafe { std::slice::from_raw_parts_mut(base.base().add(off), (y1 - y0) * w) }
            })
            .collect();
        let sources: Vec<usize> = (0..c_src).map(|s| src.plane(item, s, c_src, hw)).collect();
        with_scratch(c_src * 3 * EDGE, |edge| {
            let job = BandSums { input, sources: &sources, h, w, y0, y1, wd: &wd, bias: &bias, edge, planes: &mut planes };
            let t0 = std::time::Instant::now();
            pulp::Arch::new().dispatch(job);
            crate::plane::CONV_NANOS.fetch_add(t0.elapsed().as_nanos() as u64, std::sync::atomic::Ordering::Relaxed);
        });
    });
}

/// Elements of one zero-padded edge window: a chunk of [`LANES`] pixels and one each side.
const EDGE: usize = LANES + 2;

/// [`band_sums`] compiled for the best vector extension of this CPU (AVX-512 or AVX2 + FMA),
/// chosen at run time, on pulp's vector types (the compiler did not vectorise the plain loops:
/// they ran as scalar fused multiply-adds).
struct BandSums<'a, 'p> {
    /// The whole input and the offsets of this item's source planes in it.
    input: &'a [f32],
    sources: &'a [usize],
    h: usize,
    w: usize,
    /// The band's rows.
    y0: usize,
    y1: usize,
    /// Weights `wd[(s·9 + ky·3 + kx)·c_dst + d]` and the bias.
    wd: &'a [f32],
    bias: &'a [f32],
    /// Scratch for the zero-padded windows of a chunk at the frame's left or right edge,
    /// `[c_src, 3, EDGE]`.
    edge: &'a mut [f32],
    /// Rows `y0..y1` of each output plane of the item.
    planes: &'a mut [&'p mut [f32]],
}

impl pulp::WithSimd for BandSums<'_, '_> {
    type Output = ();

    /// Every output chunk of the band: rows `y0..y1`, chunks of two vectors of pixels, groups
    /// of up to [`GROUP`] channels. A chunk inside the frame reads the input rows in place; one
    /// that touches a side edge reads a zero-padded copy of its window.
    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, simd: S) {
        let BandSums { input, sources, h, w, y0, y1, wd, bias, edge, planes } = self;
        let lanes = 2 * S::F32_LANES;
        debug_assert!(lanes + 2 <= EDGE);
        for y in y0..y1 {
            let row0 = (y - y0) * w;
            for xc in (0..w).step_by(lanes) {
                let n = lanes.min(w - xc);
                if xc >= 1 && xc + lanes < w {
                    // inside the frame: the rows in place
                    let fetch = |s: usize, ky: usize| -> Option<&[f32]> {
                        let sy = y as isize + ky as isize - 1;
                        if sy < 0 || sy >= h as isize {
                            return None;
                        }
                        let at = sources[s] + sy as usize * w + xc - 1;
                        Some(&input[at..at + lanes + 2])
                    };
                    groups(simd, &fetch, wd, bias, planes, row0 + xc, n);
                    continue;
                }
                // at the left or right edge: a window of pixels xc − 1 .. xc + lanes + 1 of rows
                // y − 1 ..= y + 1, zeros outside the frame
                for (s, &off) in sources.iter().enumerate() {
                    for ky in 0..3 {
                        let win = &mut edge[(s * 3 + ky) * EDGE..(s * 3 + ky + 1) * EDGE];
                        win.fill(0.0);
                        let sy = y as isize + ky as isize - 1;
                        if sy < 0 || sy >= h as isize {
                            continue;
                        }
                        let row = &input[off + sy as usize * w..off + (sy as usize + 1) * w];
                        let (lo, hi) = (xc.saturating_sub(1), (xc + lanes + 1).min(w));
                        let start = lo + 1 - xc; // window column of pixel lo
                        win[start..start + hi - lo].copy_from_slice(&row[lo..hi]);
                    }
                }
                let edge = &*edge;
                groups(
                    simd,
                    &|s: usize, ky: usize| Some(&edge[(s * 3 + ky) * EDGE..(s * 3 + ky) * EDGE + lanes + 2]),
                    wd,
                    bias,
                    planes,
                    row0 + xc,
                    n,
                );
            }
        }
    }
}

/// One output chunk of `n` pixels at offset `at` of every plane: channels in groups of up to
/// [`GROUP`] accumulated together.
#[inline(always)]
fn groups<'r, S: pulp::Simd>(
    simd: S,
    fetch: &impl Fn(usize, usize) -> Option<&'r [f32]>,
    wd: &[f32],
    bias: &[f32],
    planes: &mut [&mut [f32]],
    at: usize,
    n: usize,
) {
    let (c_dst, c_src) = (bias.len(), wd.len() / (9 * bias.len().max(1)));
    let mut d0 = 0;
    while d0 < c_dst {
        let g = GROUP.min(c_dst - d0);
        match g {
            4 => store::<S, 4>(&chunk::<S, 4>(simd, fetch, wd, bias, d0, c_src), planes, d0, at, n),
            3 => store::<S, 3>(&chunk::<S, 3>(simd, fetch, wd, bias, d0, c_src), planes, d0, at, n),
            2 => store::<S, 2>(&chunk::<S, 2>(simd, fetch, wd, bias, d0, c_src), planes, d0, at, n),
            _ => store::<S, 1>(&chunk::<S, 1>(simd, fetch, wd, bias, d0, c_src), planes, d0, at, n),
        }
        d0 += g;
    }
}

/// Write `n` pixels of each accumulated channel `d0 + g` at offset `at` of its plane.
#[inline(always)]
fn store<S: pulp::Simd, const G: usize>(acc: &[[S::f32s; 2]; G], planes: &mut [&mut [f32]], d0: usize, at: usize, n: usize) {
    for (g, a) in acc.iter().enumerate() {
        let values: &[f32] = pulp::bytemuck::cast_slice(a);
        planes[d0 + g][at..at + n].copy_from_slice(&values[..n]);
    }
}

/// One chunk: two vectors of pixels, channels `d0..d0 + G`, accumulated in registers over
/// every source channel and kernel tap. `fetch(s, ky)` is the source row of channel `s` for
/// kernel row `ky` from the pixel left of the chunk (`lanes + 2` values), or `None` outside
/// the frame.
#[inline(always)]
fn chunk<'r, S: pulp::Simd, const G: usize>(
    simd: S,
    fetch: &impl Fn(usize, usize) -> Option<&'r [f32]>,
    wd: &[f32],
    bias: &[f32],
    d0: usize,
    c_src: usize,
) -> [[S::f32s; 2]; G] {
    let c_dst = bias.len();
    let lanes = 2 * S::F32_LANES;
    let mut acc = [[simd.splat_f32s(0.0); 2]; G];
    for (g, a) in acc.iter_mut().enumerate() {
        *a = [simd.splat_f32s(bias[d0 + g]); 2];
    }
    for s in 0..c_src {
        for ky in 0..3 {
            let Some(row) = fetch(s, ky) else { continue };
            for kx in 0..3 {
                let (v, _) = S::as_simd_f32s(&row[kx..kx + lanes]);
                let (v0, v1) = (v[0], v[1]);
                let wt = &wd[(s * 9 + ky * 3 + kx) * c_dst + d0..][..G];
                for (a, &k) in acc.iter_mut().zip(wt) {
                    let k = simd.splat_f32s(k);
                    a[0] = simd.mul_add_e_f32s(k, v0, a[0]);
                    a[1] = simd.mul_add_e_f32s(k, v1, a[1]);
                }
            }
        }
    }
    acc
}
