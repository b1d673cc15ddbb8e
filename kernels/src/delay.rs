//! The delay-tap convolution of ADMM-Net's delay-equivariant prior, on contiguous `f32`
//! buffers: a 3×3 "same" convolution over the frame whose input channels are the bins
//! `t − d`, `t` and `t + d` of every bin `t`, circular in `t` — read straight from the input,
//! with no rolled or concatenated copy.
//!
//! ```text
//! forward    y[b, t, o]  = Σ_j Σ_c W[o, j·C_in + c] ⋆ x[b, (t + (j − 1)·d) mod T, c]  (+ bias[o])
//! backward x dx[b, s, c] = Σ_j Σ_o W[o, j·C_in + c]ᵀ ⋆ g[b, (s − (j − 1)·d) mod T, o]
//! backward W dW[o, j·C_in + c] = Σ_{b,t} g[b, t, o] · col(x[b, (t + (j − 1)·d) mod T, c])ᵀ
//! ```
//!
//! (`⋆` a 3×3 correlation, `ᵀ⋆` its transpose.) Each pass is the im2col + GEMM correlation of
//! [`crate::conv`] over `B·T` items of `3·C` channels, whose three column-shifted copies are
//! taken from the three delayed frames of each item: the only copy of the input is the one the
//! 3×3 convolution makes anyway. The composed form (`roll` + `cat` into `[B·T, 3·C_in, H, W]`,
//! then a 3×3 conv) is [`crate::delay_op::delay_taps`]; the two are tested equal.

use crate::conv::{correlate, Conv3x3};
use crate::plane::{Kernel, Source};

/// Sizes of one delay-tap convolution over a batch.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct DelayConv3x3 {
    /// Batch `B`.
    pub batch: usize,
    /// Bins `T` (the circular axis).
    pub bins: usize,
    /// Input channels per bin `C_in`.
    pub c_in: usize,
    /// Output channels per bin `C_out`.
    pub c_out: usize,
    /// Frame height `H`.
    pub height: usize,
    /// Frame width `W`.
    pub width: usize,
    /// Dilation `d` in `t` (taken modulo `T`).
    pub dilation: usize,
}

impl DelayConv3x3 {
    /// Elements of the input `[B, T, C_in, H, W]`.
    pub fn x_len(&self) -> usize {
        self.batch * self.bins * self.c_in * self.height * self.width
    }
    /// Elements of the output `[B, T, C_out, H, W]`.
    pub fn y_len(&self) -> usize {
        self.batch * self.bins * self.c_out * self.height * self.width
    }
    /// Elements of the kernel `[C_out, 3·C_in, 3, 3]`.
    pub fn w_len(&self) -> usize {
        self.c_out * 3 * self.c_in * 9
    }

    /// The equivalent 3×3 convolution over `B·T` items of `3·C_in` gathered channels.
    fn items(&self) -> Conv3x3 {
        Conv3x3 { batch: self.batch * self.bins, c_in: 3 * self.c_in, c_out: self.c_out, height: self.height, width: self.width }
    }

    /// The delays of the three groups as read by the forward pass (`t − d`, `t`, `t + d`), or by
    /// the input gradient (`s + d`, `s`, `s − d`).
    fn source(&self, group: usize, forward: bool) -> Source {
        let d = (self.dilation % self.bins.max(1)) as isize;
        let d = if forward { d } else { -d };
        Source::Delay { bins: self.bins, group, off: [-d, 0, d] }
    }

    /// `y = delayconv(x, w) + bias`.
    ///
    /// # Shapes
    /// - `x`: `[B, T, C_in, H, W]`, `w`: `[C_out, 3·C_in, 3, 3]`, `bias`: `[C_out]` → `y`: `[B, T, C_out, H, W]`
    pub fn forward(&self, x: &[f32], w: &[f32], bias: Option<&[f32]>, y: &mut [f32]) {
        assert_eq!(x.len(), self.x_len(), "delay conv forward: x");
        assert_eq!(w.len(), self.w_len(), "delay conv forward: w");
        assert_eq!(y.len(), self.y_len(), "delay conv forward: y");
        if let Some(b) = bias {
            assert_eq!(b.len(), self.c_out, "delay conv forward: bias");
        }
        if self.y_len() == 0 || self.c_in == 0 {
            y.fill(0.0);
            if let Some(b) = bias {
                y.chunks_exact_mut(self.height * self.width).enumerate().for_each(|(i, p)| p.fill(b[i % self.c_out]));
            }
            return;
        }
        let k3 = 3 * self.c_in;
        let kernel = Kernel::new(self.c_out, k3, |o, s, t| w[(o * k3 + s) * 9 + t], bias);
        let items = self.items();
        correlate(items.plane(k3, self.c_out), self.source(self.c_in, true), x, &kernel, y);
    }

    /// Gradient with respect to the input.
    ///
    /// # Shapes
    /// - `g`: `[B, T, C_out, H, W]`, `w`: `[C_out, 3·C_in, 3, 3]` → `dx`: `[B, T, C_in, H, W]`
    pub fn backward_x(&self, g: &[f32], w: &[f32], dx: &mut [f32]) {
        assert_eq!(g.len(), self.y_len(), "delay conv backward_x: g");
        assert_eq!(w.len(), self.w_len(), "delay conv backward_x: w");
        assert_eq!(dx.len(), self.x_len(), "delay conv backward_x: dx");
        if self.x_len() == 0 {
            return;
        }
        if self.c_out == 0 {
            dx.fill(0.0);
            return;
        }
        let (k3, co) = (3 * self.c_in, self.c_out);
        // W̃[c, j·C_out + o, t] = W[o, j·C_in + c, 8 − t]: the kernel transposed and rotated
        let kernel = Kernel::new(self.c_in, 3 * co, |c, s, t| w[((s % co) * k3 + (s / co) * self.c_in + c) * 9 + 8 - t], None);
        let items = Conv3x3 { batch: self.batch * self.bins, c_in: self.c_in, c_out: 3 * co, height: self.height, width: self.width };
        correlate(items.plane(3 * co, self.c_in), self.source(co, false), g, &kernel, dx);
    }

    /// Gradient with respect to the kernel.
    ///
    /// # Shapes
    /// - `x`: `[B, T, C_in, H, W]`, `g`: `[B, T, C_out, H, W]` → `dw`: `[C_out, 3·C_in, 3, 3]`
    pub fn backward_w(&self, x: &[f32], g: &[f32], dw: &mut [f32]) {
        assert_eq!(x.len(), self.x_len(), "delay conv backward_w: x");
        self.items().backward_w_from(self.source(self.c_in, true), x, g, dw);
    }

    /// Gradient with respect to the bias: `db[o] = Σ_{b,t,y,x} g[b, t, o, y, x]`.
    ///
    /// # Shapes
    /// - `g`: `[B, T, C_out, H, W]` → `db`: `[C_out]`
    pub fn backward_bias(&self, g: &[f32], db: &mut [f32]) {
        self.items().backward_bias(g, db);
    }

    /// Floating-point operations of one forward pass (each gradient pass costs the same).
    pub fn flop(&self) -> f64 {
        2.0 * (self.batch * self.bins * self.height * self.width) as f64 * (self.c_out * 3 * self.c_in * 9) as f64
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::conv::tests::{close, lcg};

    /// The definition, in f64: `y[b, t, o, r, c] = bias[o] + Σ_{j, ci, ky, kx} W · x[b, t + (j−1)d, ci, r + ky − 1, c + kx − 1]`.
    fn direct(d: &DelayConv3x3, x: &[f32], w: &[f32], bias: &[f32]) -> Vec<f64> {
        let (h, wd, t_n) = (d.height as isize, d.width as isize, d.bins as isize);
        let mut y = vec![0.0f64; d.y_len()];
        for b in 0..d.batch {
            for t in 0..d.bins {
                for o in 0..d.c_out {
                    for r in 0..h {
                        for c in 0..wd {
                            let mut s = bias[o] as f64;
                            for j in 0..3isize {
                                let tt = (t as isize + (j - 1) * d.dilation as isize).rem_euclid(t_n) as usize;
                                for ci in 0..d.c_in {
                                    for ky in 0..3isize {
                                        for kx in 0..3isize {
                                            let (sr, sc) = (r + ky - 1, c + kx - 1);
                                            if sr < 0 || sr >= h || sc < 0 || sc >= wd {
                                                continue;
                                            }
                                            let xi = (((b * d.bins + tt) * d.c_in + ci) as isize * h + sr) * wd + sc;
                                            let wi = (o * 3 * d.c_in + j as usize * d.c_in + ci) * 9 + (ky * 3 + kx) as usize;
                                            s += x[xi as usize] as f64 * w[wi] as f64;
                                        }
                                    }
                                }
                            }
                            y[((((b * d.bins + t) * d.c_out + o) as isize * h + r) * wd + c) as usize] = s;
                        }
                    }
                }
            }
        }
        y
    }

    const SIZES: [DelayConv3x3; 5] = [
        DelayConv3x3 { batch: 2, bins: 4, c_in: 1, c_out: 3, height: 5, width: 6, dilation: 1 },
        DelayConv3x3 { batch: 1, bins: 8, c_in: 3, c_out: 2, height: 4, width: 3, dilation: 3 },
        DelayConv3x3 { batch: 1, bins: 5, c_in: 2, c_out: 1, height: 3, width: 4, dilation: 9 },
        DelayConv3x3 { batch: 2, bins: 16, c_in: 4, c_out: 4, height: 9, width: 7, dilation: 9 },
        DelayConv3x3 { batch: 1, bins: 3, c_in: 2, c_out: 2, height: 1, width: 1, dilation: 3 },
    ];

    #[test]
    fn forward_equals_the_direct_sum() {
        for (i, d) in SIZES.iter().enumerate() {
            let (x, w, bias) = (lcg(d.x_len(), 1 + i as u64), lcg(d.w_len(), 10 + i as u64), lcg(d.c_out, 20));
            let mut y = vec![f32::NAN; d.y_len()];
            d.forward(&x, &w, Some(&bias), &mut y);
            close(&y, &direct(d, &x, &w, &bias), 1e-5, &format!("{d:?} y"));
        }
    }

    /// Element by element: `dx[j] = ⟨f(e_j), g⟩` and `dW[j] = ⟨f_{e_j}(x), g⟩` for the direct map `f`.
    #[test]
    fn backward_passes_are_the_exact_gradients() {
        for (i, d) in SIZES.iter().enumerate().filter(|(_, d)| d.x_len() <= 300) {
            let (x, w, g) = (lcg(d.x_len(), 3 + i as u64), lcg(d.w_len(), 30 + i as u64), lcg(d.y_len(), 60 + i as u64));
            let zero = vec![0.0f32; d.c_out];
            let mut dx = vec![f32::NAN; d.x_len()];
            d.backward_x(&g, &w, &mut dx);
            let mut dw = vec![f32::NAN; d.w_len()];
            d.backward_w(&x, &g, &mut dw);
            let dot = |y: Vec<f64>| y.iter().zip(&g).map(|(a, &b)| a * b as f64).sum::<f64>();
            for j in 0..d.x_len() {
                let mut e = vec![0.0f32; d.x_len()];
                e[j] = 1.0;
                let want = dot(direct(d, &e, &w, &zero));
                assert!((dx[j] as f64 - want).abs() < 1e-5, "{d:?} dx[{j}]: {} vs {want}", dx[j]);
            }
            for j in 0..d.w_len() {
                let mut e = vec![0.0f32; d.w_len()];
                e[j] = 1.0;
                let want = dot(direct(d, &x, &e, &zero));
                assert!((dw[j] as f64 - want).abs() < 1e-4, "{d:?} dW[{j}]: {} vs {want}", dw[j]);
            }
        }
    }
}
