//! A U-Net on the range fit's evidence ([`tcsense_models::UnetInput::Costs`]) as one graph
//! from the tap images (`export onnx --from-taps`): the evidence that `tcsense infer` otherwise
//! computes before the graph ([`tcsense_fits::depth::RangeTemplates::evidence`]) as graph
//! nodes, then the network and its posterior's mode, so that any ONNX runtime decodes the taps
//! with the exported file alone.
//!
//! ```text
//! y [B, M, H, W] → per pixel of subpixel type n, every candidate c of the cycle (C = T·oversample):
//!   g_c = A_n P_c, s = A_n 1                       templates (baked, as the fit's dense pass)
//!   cost_c = min_{a, b ≥ 0} ‖y − a g_c − b s‖²      the two-column NNLS, 0 where Σy ≤ 0 (unlit)
//! window sums of the costs (3×3, then 5, 9, 15)    separable box filters (AveragePool × side)
//! ν = 1/(2σ²), σ² = median over lit pixels of min_c window cost / dof     (TopK + GatherElements)
//! the 3×3 window pooled by likeness (Bhattacharyya weights of the window posteriors)
//! features: pooled posteriors of the pixel and the wider windows, log intensity, lit
//! log-likelihoods: −(C_w − min C_w)·ν of the (pooled) window and the wider ones
//! → the U-Net's log-prior + the windows' log-likelihoods → posterior mode (parabola) → range
//! ```
//!
//! What stays with `tcsense infer` (and is not in this graph): the mode refined in the tap
//! domain on a window grown in dim light, and the fit's second return.

use tcsense_fits::depth::{candidate_columns, CONTEXT_WINDOWS, SCALES};
use tcsense_models::Unet;
use tcsense_sensor::MeasurementMatrix;

use super::graph::{Attr, Dim, Graph};
use super::{posterior_mode, trunk_rows, unet_trunk, windowed_likelihood, OnnxMeta};
use crate::{InferError, Result};

/// Outputs of the graph from the taps: the first return (m; NaN where unlit or below half
/// confidence), its confidence, and the posterior's mode (m, before any refinement).
pub const DEPTH_OUTPUT: &str = "depth";
pub const CONFIDENCE_OUTPUT: &str = "confidence";

/// The frame's shape pieces, computed once from `Shape(y)`.
struct FrameShape {
    /// `[1]`: the batch.
    b: String,
    /// `[2]`: `H, W`.
    hw: String,
    /// `[1]` each: `H/bh`, `W/bw`.
    hb: String,
    wb: String,
    /// `[1]`: `H·W`.
    pixels: String,
}

impl FrameShape {
    fn of(g: &mut Graph, y: &str, (bh, bw): (usize, usize)) -> FrameShape {
        let shape = g.op("Shape", &[y]);
        let (s0, s1, s2, s3, s4) = (g.ints("s0", &[0]), g.ints("s1", &[1]), g.ints("s2", &[2]), g.ints("s3", &[3]), g.ints("s4", &[4]));
        let b = g.op("Slice", &[&shape, &s0, &s1]);
        let hw = g.op("Slice", &[&shape, &s2, &s4]);
        let h = g.op("Slice", &[&shape, &s2, &s3]);
        let w = g.op("Slice", &[&shape, &s3, &s4]);
        let (nbh, nbw) = (g.ints("bh", &[bh as i64]), g.ints("bw", &[bw as i64]));
        let hb = g.op("Div", &[&h, &nbh]);
        let wb = g.op("Div", &[&w, &nbw]);
        let pixels = g.op("Mul", &[&h, &w]);
        FrameShape { b, hw, hb, wb, pixels }
    }

    /// A shape vector from the pieces and fixed sizes.
    fn cat(&self, g: &mut Graph, parts: &[Piece]) -> String {
        let names: Vec<String> = parts
            .iter()
            .map(|p| match p {
                Piece::B => self.b.clone(),
                Piece::Hw => self.hw.clone(),
                Piece::Hb => self.hb.clone(),
                Piece::Wb => self.wb.clone(),
                Piece::Fixed(v) => g.ints("dim", &[*v]),
            })
            .collect();
        let refs: Vec<&str> = names.iter().map(String::as_str).collect();
        g.node("Concat", &refs, &[Attr::Int("axis", 0)])
    }
}

enum Piece {
    B,
    Hw,
    Hb,
    Wb,
    Fixed(i64),
}

/// The taps in blocks of the code's mosaic, one row of pixels per subpixel type.
///
/// # Shapes
/// - `y`: `[B, M, H, W]` → `[B, N, M, H/bh·W/bw]` (type `n = di·bw + dj`)
fn to_blocks(g: &mut Graph, fr: &FrameShape, y: &str, m: usize, (bh, bw): (usize, usize)) -> String {
    let s6 = fr.cat(g, &[Piece::B, Piece::Fixed(m as i64), Piece::Hb, Piece::Fixed(bh as i64), Piece::Wb, Piece::Fixed(bw as i64)]);
    let x = g.op("Reshape", &[y, &s6]);
    let x = g.node("Transpose", &[&x], &[Attr::Ints("perm", &[0, 3, 5, 1, 2, 4])]); // [B, bh, bw, M, H', W']
    let s4 = fr.cat(g, &[Piece::B, Piece::Fixed((bh * bw) as i64), Piece::Fixed(m as i64), Piece::Fixed(-1)]);
    g.op("Reshape", &[&x, &s4])
}

/// [`to_blocks`]'s inverse for `k` channels a type.
///
/// # Shapes
/// - `x`: `[B, N, K, H/bh·W/bw]` → `[B, K, H, W]`
fn from_blocks(g: &mut Graph, fr: &FrameShape, x: &str, k: usize, (bh, bw): (usize, usize)) -> String {
    let s6 = fr.cat(g, &[Piece::B, Piece::Fixed(bh as i64), Piece::Fixed(bw as i64), Piece::Fixed(k as i64), Piece::Hb, Piece::Wb]);
    let x = g.op("Reshape", &[x, &s6]);
    let x = g.node("Transpose", &[&x], &[Attr::Ints("perm", &[0, 3, 4, 1, 5, 2])]); // [B, K, H', bh, W', bw]
    let s4 = fr.cat(g, &[Piece::B, Piece::Fixed(k as i64), Piece::Hw]);
    g.op("Reshape", &[&x, &s4])
}

/// The sum of `x` over the `side × side` window around each pixel (zeros outside the frame),
/// as the fit's box filter: two separable average pools, times the window's area.
///
/// # Shapes
/// - `x`: `[B, K, H, W]` → `[B, K, H, W]`
fn box_sum(g: &mut Graph, x: &str, side: usize) -> String {
    if side <= 1 {
        return x.to_string();
    }
    let h = (side / 2) as i64;
    let s = side as i64;
    let pool = |g: &mut Graph, x: &str, kernel: [i64; 2], pads: [i64; 4]| {
        g.node("AveragePool", &[x], &[Attr::Ints("kernel_shape", &kernel), Attr::Ints("pads", &pads), Attr::Int("count_include_pad", 1)])
    };
    let rows = pool(g, x, [1, s], [0, h, 0, h]);
    let both = pool(g, &rows, [s, 1], [h, 0, h, 0]);
    let area = g.scalar("window_area", (side * side) as f32);
    g.op("Mul", &[&both, &area])
}

/// The median over each frame of `v` at its lit pixels (`[B, 1, H, W]`, `lit` bool), the
/// element at rank ⌊n/2⌋ of the `n` sorted (as [`tcsense_fits::evidence`]'s); 1 where there is
/// none, or it is not positive and finite. `[B, 1, 1, 1]`.
fn median_where(g: &mut Graph, fr: &FrameShape, v: &str, lit: &str, litf: &str) -> String {
    let inf = g.scalar("inf", f32::INFINITY);
    let masked = g.op("Where", &[lit, v, &inf]);
    let rows = fr.cat(g, &[Piece::B, Piece::Fixed(-1)]);
    let masked = g.op("Reshape", &[&masked, &rows]); // [B, H·W]
    let sorted = g.node_multi("TopK", &[&masked, &fr.pixels], &[Attr::Int("axis", 1), Attr::Int("largest", 0), Attr::Int("sorted", 1)], 2);
    let count = g.op("Reshape", &[litf, &rows]);
    let axis1 = g.ints("axis1", &[1]);
    let count = g.node("ReduceSum", &[&count, &axis1], &[Attr::Int("keepdims", 1)]); // [B, 1]
    let half = g.scalar("half", 0.5);
    let rank = g.op("Mul", &[&count, &half]);
    let rank = g.op("Floor", &[&rank]);
    let rank = g.node("Cast", &[&rank], &[Attr::Int("to", onnx_protobuf::tensor_proto::DataType::INT64 as i64)]);
    let one_i = g.ints("one", &[1]);
    let last = g.op("Sub", &[&fr.pixels, &one_i]);
    let rank = g.op("Min", &[&rank, &last]);
    let med = g.node("GatherElements", &[&sorted[0], &rank], &[Attr::Int("axis", 1)]); // [B, 1]
    let (nil, big) = (g.scalar("nil", 0.0), g.scalar("largest_finite", f32::MAX));
    let positive = g.op("Greater", &[&med, &nil]);
    let finite = g.op("Less", &[&med, &big]);
    let valid = g.op("And", &[&positive, &finite]);
    let one = g.scalar("unit", 1.0);
    let med = g.op("Where", &[&valid, &med, &one]);
    let shape = g.ints("per_frame", &[-1, 1, 1, 1]);
    g.op("Reshape", &[&med, &shape])
}

/// `e^x / Σ_c e^x` over the channels of `x` `[B, C, H, W]` whose largest is 0 (a centred
/// log-likelihood): no shift needed, and no `Softmax` on an inner axis (which ONNX Runtime
/// computes through transposes).
fn softmax_channels(g: &mut Graph, x: &str) -> String {
    let e = g.op("Exp", &[x]);
    let axis1 = g.ints("axis1", &[1]);
    let total = g.node("ReduceSum", &[&e, &axis1], &[Attr::Int("keepdims", 1)]);
    g.op("Div", &[&e, &total])
}

/// The per-type constants `[N][K]` as `[1, N, K, 1]`.
fn per_type(g: &mut Graph, hint: &str, v: &[Vec<f32>]) -> String {
    let (n, k) = (v.len(), v[0].len());
    let flat: Vec<f32> = v.iter().flatten().copied().collect();
    g.weight(hint, &[1, n, k, 1], &flat)
}

/// Each pixel's single-return cost at every candidate (the fit's dense pass,
/// `tcsense_fits::depth`): `yy − max fit` over `a, b ≥ 0`, the two columns together where the
/// solve is posed and both amplitudes are non-negative, else the better column alone.
///
/// # Shapes
/// - `y`: `[B, M, H, W]` → `[B, C, H, W]` (before the lit mask)
fn pixel_costs(g: &mut Graph, fr: &FrameShape, y: &str, sensor: &MeasurementMatrix, oversample: usize) -> String {
    let a = sensor.a();
    let (n, m, t) = a.dim();
    let block = sensor.block();
    let cols = candidate_columns(t, oversample);
    let c = cols.len();
    // the templates in f64, as the fit's
    let mut gmat = vec![0f32; n * c * m]; // [N, C, M]
    let (mut gg, mut gs, mut inv_det, mut inv_gg) =
        (vec![vec![0f32; c]; n], vec![vec![0f32; c]; n], vec![vec![0f32; c]; n], vec![vec![0f32; c]; n]);
    let (mut svec, mut ss, mut inv_ss) = (vec![0f32; n * m], vec![vec![0f32; 1]; n], vec![vec![0f32; 1]; n]);
    for k in 0..n {
        let s: Vec<f64> = (0..m).map(|mm| (0..t).map(|j| a[(k, mm, j)] as f64).sum()).collect();
        let s2: f64 = s.iter().map(|v| v * v).sum();
        for (mm, v) in s.iter().enumerate() {
            svec[k * m + mm] = *v as f32;
        }
        ss[k][0] = s2 as f32;
        inv_ss[k][0] = if ss[k][0] > 0.0 { 1.0 / ss[k][0] } else { 0.0 };
        for (ci, &(t0, t1, f)) in cols.iter().enumerate() {
            let gv: Vec<f64> = (0..m).map(|mm| (1.0 - f) * a[(k, mm, t0)] as f64 + f * a[(k, mm, t1)] as f64).collect();
            for (mm, v) in gv.iter().enumerate() {
                gmat[(k * c + ci) * m + mm] = *v as f32;
            }
            let p: f64 = gv.iter().map(|v| v * v).sum();
            let q: f64 = gv.iter().zip(&s).map(|(x, y)| x * y).sum();
            let det = p * s2 - q * q;
            gg[k][ci] = p as f32;
            gs[k][ci] = q as f32;
            inv_det[k][ci] = if det > 1e-12 * p * s2 { (1.0 / det) as f32 } else { 0.0 };
            inv_gg[k][ci] = if p > 0.0 { (1.0 / p) as f32 } else { 0.0 };
        }
    }
    let yb = to_blocks(g, fr, y, m, block); // [B, N, M, P]
    let gw = g.weight("templates", &[n, c, m], &gmat);
    let sw = g.weight("ambient_template", &[n, 1, m], &svec);
    let gy = g.op("MatMul", &[&gw, &yb]); // [B, N, C, P]
    let sy = g.op("MatMul", &[&sw, &yb]); // [B, N, 1, P]
    let y2 = g.op("Mul", &[&yb, &yb]);
    let axis2 = g.ints("axis2", &[2]);
    let yy = g.node("ReduceSum", &[&y2, &axis2], &[Attr::Int("keepdims", 1)]); // [B, N, 1, P]
    let (gg, gs, inv_det, inv_gg) =
        (per_type(g, "gram_gg", &gg), per_type(g, "gram_gs", &gs), per_type(g, "inv_det", &inv_det), per_type(g, "inv_gg", &inv_gg));
    let (ss, inv_ss) = (per_type(g, "gram_ss", &ss), per_type(g, "inv_ss", &inv_ss));
    let (ss_gy, gs_sy) = (g.op("Mul", &[&ss, &gy]), g.op("Mul", &[&gs, &sy]));
    let amp_g = g.op("Sub", &[&ss_gy, &gs_sy]);
    let amp_g = g.op("Mul", &[&amp_g, &inv_det]);
    let (gg_sy, gs_gy) = (g.op("Mul", &[&gg, &sy]), g.op("Mul", &[&gs, &gy]));
    let amp_s = g.op("Sub", &[&gg_sy, &gs_gy]);
    let amp_s = g.op("Mul", &[&amp_s, &inv_det]);
    let (ag, bs) = (g.op("Mul", &[&amp_g, &gy]), g.op("Mul", &[&amp_s, &sy]));
    let inside = g.op("Sub", &[&yy, &ag]);
    let inside = g.op("Sub", &[&inside, &bs]);
    let rg = g.op("Relu", &[&gy]);
    let only_g = g.op("Mul", &[&rg, &rg]);
    let only_g = g.op("Mul", &[&only_g, &inv_gg]);
    let rs = g.op("Relu", &[&sy]);
    let only_s = g.op("Mul", &[&rs, &rs]);
    let only_s = g.op("Mul", &[&only_s, &inv_ss]);
    let best = g.op("Max", &[&only_g, &only_s]);
    let boundary = g.op("Sub", &[&yy, &best]);
    let nil = g.scalar("nil", 0.0);
    let (ga, gb, posed) =
        (g.op("GreaterOrEqual", &[&amp_g, &nil]), g.op("GreaterOrEqual", &[&amp_s, &nil]), g.op("Greater", &[&inv_det, &nil]));
    let both = g.op("And", &[&ga, &gb]);
    let both = g.op("And", &[&both, &posed]);
    let v = g.op("Where", &[&both, &inside, &boundary]);
    let cost = g.op("Relu", &[&v]); // [B, N, C, P]
    from_blocks(g, fr, &cost, c, block)
}

/// The U-Net on the range fit's evidence as one graph from the taps (see the module's notes).
///
/// # Shapes
/// - `measurements [B, M, H, W]` → `depth [B, 1, H, W]` (m), `confidence [B, 1, H, W]`
pub(super) fn unet_from_taps(net: &Unet, sensor: &MeasurementMatrix, meta: &OnnxMeta, window: usize) -> Result<Vec<u8>> {
    let (c, pool) = net.grid();
    let (m, block) = (meta.taps, meta.block);
    let os = net.grid_oversample();
    if c != meta.bins * os || sensor.a().dim().1 != m {
        return Err(InferError::InvalidParam {
            field: "model",
            got: format!("{c} candidates over {} bins, {} taps", meta.bins, sensor.a().dim().1),
            expected: format!("{} candidates a bin and {m} taps", os),
        });
    }
    let pool_like = net.pool_like();
    let mut g = Graph::new(tcsense_models::runs::network_names::UNET);
    let frame = [Dim::Named("batch"), Dim::Fixed(1), Dim::Named("height"), Dim::Named("width")];
    let y = g.input(super::INPUT, &[Dim::Named("batch"), Dim::Fixed(m), Dim::Named("height"), Dim::Named("width")]);
    let fr = FrameShape::of(&mut g, &y, block);
    // lit: the pixels with charge
    let axis1 = g.ints("axis1", &[1]);
    let intensity = g.node("ReduceSum", &[&y, &axis1], &[Attr::Int("keepdims", 1)]); // [B, 1, H, W]
    let nil = g.scalar("nil", 0.0);
    let lit = g.op("Greater", &[&intensity, &nil]);
    let litf = g.node("Cast", &[&lit], &[Attr::Int("to", onnx_protobuf::tensor_proto::DataType::FLOAT as i64)]);
    let cost = pixel_costs(&mut g, &fr, &y, sensor, os);
    let cost = g.op("Mul", &[&cost, &litf]); // [B, C, H, W]
                                             // the fit's window and the frame's noise level: the median least window cost per degree of
                                             // freedom (each pixel's amplitude and ambient its own, the window's range shared)
    let win = box_sum(&mut g, &cost, window);
    let lit_count = box_sum(&mut g, &litf, window);
    let lit_count = g.op("Round", &[&lit_count]);
    let least = g.node("ReduceMin", &[&win], &[Attr::Ints("axes", &[1]), Attr::Int("keepdims", 1)]);
    let free = g.scalar("free_per_pixel", m.saturating_sub(2) as f32);
    let (shared, one) = (g.scalar("shared", 1.0), g.scalar("unit", 1.0));
    let dof = g.op("Mul", &[&lit_count, &free]);
    let dof = g.op("Sub", &[&dof, &shared]);
    let dof = g.op("Max", &[&dof, &one]);
    let per_dof = g.op("Relu", &[&least]);
    let per_dof = g.op("Div", &[&per_dof, &dof]);
    let noise = median_where(&mut g, &fr, &per_dof, &lit, &litf); // [B, 1, 1, 1]
    let neg_half = g.scalar("neg_half", -0.5);
    let neg_nats = g.op("Div", &[&neg_half, &noise]); // −ν = −1/(2σ²)
                                                      // the fit's window pooled by likeness with the windows that tile pool_like × pool_like
    let window_ll = if pool_like > window {
        let least = g.node("ReduceMin", &[&win], &[Attr::Ints("axes", &[1]), Attr::Int("keepdims", 1)]);
        let d = g.op("Sub", &[&win, &least]);
        let d = g.op("Mul", &[&d, &neg_nats]);
        let post = softmax_channels(&mut g, &d);
        let roots = g.op("Sqrt", &[&post]);
        let roots = g.op("Mul", &[&roots, &litf]);
        let k = (pool_like / window / 2) as i64;
        let pad = k * window as i64;
        let pads = g.ints("pads", &[0, 0, pad, pad, 0, 0, pad, pad]);
        let (roots_p, win_p) = (g.op("Pad", &[&roots, &pads]), g.op("Pad", &[&win, &pads]));
        let axes = g.ints("axes23", &[2, 3]);
        let end = |d: i64| if pad - d > 0 { -(pad - d) } else { i64::MAX };
        let (unit, floor) = (g.scalar("unit", 1.0), g.scalar("pool_floor", 1e-3));
        let mut acc = win.clone();
        for a in -k..=k {
            for b in -k..=k {
                if a == 0 && b == 0 {
                    continue;
                }
                let (di, dj) = (a * window as i64, b * window as i64);
                let (st, en) = (g.ints("starts", &[pad + di, pad + dj]), g.ints("ends", &[end(di), end(dj)]));
                let rq = g.op("Slice", &[&roots_p, &st, &en, &axes]);
                let wq = g.op("Slice", &[&win_p, &st, &en, &axes]);
                let bc = g.op("Mul", &[&roots, &rq]);
                let bc = g.node("ReduceSum", &[&bc, &axis1], &[Attr::Int("keepdims", 1)]);
                let bc = g.op("Min", &[&bc, &unit]);
                let keep = g.op("Greater", &[&bc, &floor]);
                let bc = g.op("Where", &[&keep, &bc, &nil]);
                let add = g.op("Mul", &[&bc, &wq]);
                acc = g.op("Add", &[&acc, &add]);
            }
        }
        g.op("Mul", &[&acc, &litf])
    } else {
        win.clone()
    };
    let wider: Vec<String> = CONTEXT_WINDOWS.iter().map(|&side| box_sum(&mut g, &cost, side)).collect();
    // the log-likelihoods, window-major: −(v − min v)·ν, 0 where unlit
    // (the log-likelihood before the mask, −(v − min v)·ν: a posterior's exponent too)
    let centred = |g: &mut Graph, v: &str| {
        let least = g.node("ReduceMin", &[v], &[Attr::Ints("axes", &[1]), Attr::Int("keepdims", 1)]);
        let d = g.op("Sub", &[v, &least]);
        g.op("Mul", &[&d, &neg_nats])
    };
    let skip_of = |g: &mut Graph, v: &str| {
        let d = centred(g, v);
        g.op("Mul", &[&d, &litf])
    };
    let mut skips = vec![skip_of(&mut g, &window_ll)];
    for v in &wider {
        skips.push(skip_of(&mut g, v));
    }
    let refs: Vec<&str> = skips.iter().map(String::as_str).collect();
    let skip = g.node("Concat", &refs, &[Attr::Int("axis", 1)]); // [B, S·C, H, W]
                                                                 // the posteriors of the pixel and of the wider windows, pooled `pool` candidates a channel
    let pooled = c.div_ceil(pool);
    let post_of = |g: &mut Graph, v: &str| {
        let d = centred(g, v);
        let p = softmax_channels(g, &d);
        let scale = g.scalar("pooled_channels", pooled as f32);
        let p = g.op("Mul", &[&p, &scale]);
        let p = if pooled * pool > c {
            let pads = g.ints("pads", &[0, 0, 0, 0, 0, (pooled * pool - c) as i64, 0, 0]);
            g.op("Pad", &[&p, &pads])
        } else {
            p
        };
        let s5 = fr.cat(g, &[Piece::B, Piece::Fixed(pooled as i64), Piece::Fixed(pool as i64), Piece::Hw]);
        let p = g.op("Reshape", &[&p, &s5]);
        let axis2 = g.ints("axis2", &[2]);
        let p = g.node("ReduceSum", &[&p, &axis2], &[Attr::Int("keepdims", 0)]);
        g.op("Mul", &[&p, &litf])
    };
    let mut features = vec![post_of(&mut g, &cost)];
    for v in &wider {
        features.push(post_of(&mut g, v));
    }
    // the log intensity against the frame's median lit intensity, clamped; and the lit mask
    let reference = median_where(&mut g, &fr, &intensity, &lit, &litf);
    let rel = g.op("Div", &[&intensity, &reference]);
    let log = g.op("Log", &[&rel]);
    let (lo, hi) = (g.scalar("log_intensity_lo", -10.0), g.scalar("log_intensity_hi", 10.0));
    let log = g.op("Clip", &[&log, &lo, &hi]);
    let log = g.op("Where", &[&lit, &log, &lo]);
    features.push(log);
    features.push(litf.clone());
    let refs: Vec<&str> = features.iter().map(String::as_str).collect();
    let features = g.node("Concat", &refs, &[Attr::Int("axis", 1)]); // [B, F, H, W]
                                                                     // the network, as `unet_on_evidence` on the evidence it would read
    let f = tcsense_fits::depth::range_feature_channels(c, pool);
    debug_assert_eq!(f, SCALES * pooled + 2);
    let skip_t = g.node("Transpose", &[&skip], &[Attr::Ints("perm", &[0, 2, 3, 1])]);
    let rows = g.ints("rows_shape", &[-1, (SCALES * c) as i64]);
    let skip_rows = g.op("Reshape", &[&skip_t, &rows]); // [N, S·C]
    let frame_shape = fr.cat(&mut g, &[Piece::B, Piece::Fixed(1), Piece::Hw]);
    let trunk = unet_trunk(&mut g, net.down(), net.up(), &features)?;
    let trunk = trunk_rows(&mut g, &trunk, net.head().weight.dims()[1]);
    let bound = g.scalar("prior_bound", tcsense_models::depth_evidence::PRIOR_BOUND as f32);
    let prior = super::head_rows(&mut g, net.head(), &trunk, 0, c)?;
    let prior = g.op("Div", &[&prior, &bound]);
    let prior = g.op("Tanh", &[&prior]);
    let prior = g.op("Mul", &[&prior, &bound]);
    let logit = super::head_rows(&mut g, net.head(), &trunk, c, 1)?;
    let logit = g.op("Reshape", &[&logit, &frame_shape]);
    let wide = SCALES - 1;
    let o_s = super::head_rows(&mut g, net.head(), &trunk, c + 1, wide)?;
    let likelihood = windowed_likelihood(&mut g, &o_s, &skip_rows, c, wide);
    let logits = g.op("Add", &[&likelihood, &prior]);
    let u = posterior_mode(&mut g, &logits, c, true);
    let u = g.op("Reshape", &[&u, &frame_shape]);
    let (half_os, per) =
        (g.scalar("half_oversample", 0.5 * os as f32), g.scalar("metres_per_candidate", (net.range_m() / c as f64) as f32));
    let r = g.op("Add", &[&u, &half_os]);
    let r = g.op("Mul", &[&r, &per]);
    let period = g.scalar("range_m", net.range_m() as f32);
    let r = g.node("Mod", &[&r, &period], &[Attr::Int("fmod", 1)]);
    let conf = g.op("Sigmoid", &[&logit]);
    let conf = g.op("Mul", &[&conf, &litf]);
    // a return where lit and at least half confident (as `tcsense infer` writes the first)
    let half = g.scalar("half", 0.5);
    let sure = g.op("GreaterOrEqual", &[&conf, &half]);
    let sure = g.op("And", &[&sure, &lit]);
    let nan = g.scalar("nan", f32::NAN);
    let depth = g.op("Where", &[&sure, &r, &nan]);
    g.output(&depth, DEPTH_OUTPUT, &frame);
    g.output(&conf, CONFIDENCE_OUTPUT, &frame);
    let doc = format!(
        "tcsense U-Net on the range fit's evidence, one graph from the taps ({c} candidate ranges over {:.3} m, {} levels{}): measurements [B, {m}, H, W] -> depth (m) [B, 1, H, W] (the posterior's mode; NaN where unlit or below half confidence), confidence [B, 1, H, W]",
        net.range_m(),
        net.down().len(),
        if pool_like > window { format!(", the {window}×{window} window pooled by likeness over {pool_like}×{pool_like}") } else { String::new() },
    );
    let model = g.into_model(&doc, &meta.to_props());
    protobuf::Message::write_to_bytes(&model).map_err(|e| InferError::InvalidParam {
        field: "ONNX model",
        got: e.to_string(),
        expected: "a serialisable model".into(),
    })
}
