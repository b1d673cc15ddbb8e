//! A U-Net on the range fit's evidence ([`tcsense_models::UnetInput::Costs`]) as one graph
//! from the tap images (`export onnx --from-taps`): the evidence that `tcsense infer` otherwise
//! computes before the graph ([`tcsense_fits::depth::RangeTemplates::evidence`]) as graph
//! nodes, then the network and its posterior's mode, so that any ONNX runtime decodes the taps
//! with the exported file alone.
//!
//! ```text
//! y [B, M, H, W] → each frame times the power of two that brings its largest tap into [1, 2)
//!   (exact; no square overflows or underflows f32 at any scale of the taps)
//! → per pixel of subpixel type n, every candidate c of the cycle (C = T·oversample):
//!   g_c = A_n P_c, s = A_n 1                       templates (baked, as the fit's dense pass)
//!   cost_c = min_{a, b ≥ 0} ‖y − a g_c − b s‖²      the two-column NNLS, 0 where Σy ≤ 0 (unlit)
//! window sums of the costs (3×3, then 5, 9, 15)    separable box filters (AveragePool × side)
//! ν = 1/(2σ²), σ² = median over lit pixels of min_c window cost / dof     (TopK + GatherElements)
//! the 3×3 window pooled by likeness (Bhattacharyya weights of the window posteriors)
//! features: pooled posteriors of the pixel and the wider windows, log intensity, lit
//! log-likelihoods: −(C_w − min C_w)·ν of the (pooled) window and the wider ones
//! → the U-Net's log-prior + the windows' log-likelihoods → posterior mode (parabola)
//! → refined in the tap domain: the window's cost (like-range neighbours, templates linear
//!   between the bins) at 13 positions ±1.5 candidates around the mode, on the smallest window
//!   of 3×3, 5×5, 7×7 whose least position the cost pins to 0.12 bins (else the mode stands)
//! → range (m), NaN where unlit or below half confidence
//! ```
//!
//! As `tcsense infer` refines the split graph's mode ([`tcsense_fits::depth::RangeTemplates::ranges`]),
//! but with a parabola through the positions instead of golden sections, and where the
//! window pins the range rather than wherever its least grid point is within one of the mode.
//! The fit's second return stays with `tcsense infer` on the split export; this graph gives one.

use tcsense_fits::depth::{candidate_columns, CONTEXT_WINDOWS, SCALES};
use tcsense_models::Unet;
use tcsense_sensor::MeasurementMatrix;

use super::graph::{Attr, Dim, Graph};
use super::{posterior_mode, trunk_rows, unet_trunk, windowed_likelihood, OnnxMeta};
use crate::{InferError, Result};

/// Outputs of the graph from the taps: the first return (m; NaN where unlit or below half
/// confidence) and its confidence.
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

/// Each frame of `y` `[B, M, H, W]` times the power of two that brings its largest magnitude
/// into [1, 2): exact in floating point, so the products are those of the frame as given, and
/// the squares and sums of the cost volume neither overflow nor underflow f32 at any scale of
/// the taps (every product of the graph is invariant to the frame's scale).
fn unit_scale(g: &mut Graph, y: &str) -> String {
    let abs = g.op("Abs", &[y]);
    let top = g.node("ReduceMax", &[&abs], &[Attr::Ints("axes", &[1, 2, 3]), Attr::Int("keepdims", 1)]); // [B, 1, 1, 1]
    let tiny = g.scalar("least_normal", f32::MIN_POSITIVE);
    let top = g.op("Max", &[&top, &tiny]);
    let log2 = g.op("Log", &[&top]);
    let ln2 = g.scalar("ln2", std::f32::consts::LN_2);
    let log2 = g.op("Div", &[&log2, &ln2]);
    let e = g.op("Floor", &[&log2]);
    let e = g.op("Neg", &[&e]);
    let two = g.scalar("two", 2.0);
    let scale = g.op("Pow", &[&two, &e]);
    g.op("Mul", &[y, &scale])
}

/// The per-type constants `[N][K]` as `[1, N, K, 1]`.
fn per_type(g: &mut Graph, hint: &str, v: &[Vec<f32>]) -> String {
    let (n, k) = (v.len(), v[0].len());
    let flat: Vec<f32> = v.iter().flatten().copied().collect();
    g.weight(hint, &[1, n, k, 1], &flat)
}

/// A pixel's products with a template `g` and the ambient's column `s` (`yy`, `g·y`, `s·y`) and
/// their Gram entries, broadcasting over candidates or positions.
struct Gram<'a> {
    yy: &'a str,
    gy: &'a str,
    sy: &'a str,
    gg: &'a str,
    gs: &'a str,
    ss: &'a str,
}

/// `1/det` of the Gram matrix (0 where not `posed`), `1/g·g` and `1/s·s` (0 where 0).
struct Inverses<'a> {
    det: &'a str,
    posed: &'a str,
    gg: &'a str,
    ss: &'a str,
}

/// The least squares of `y` against a non-negative combination of `g` and `s` (the fit's
/// `nnls2`): `yy − a·g·y − b·s·y` where the solve is posed and both amplitudes are ≥ 0, else
/// `yy` less what the better column alone removes; at least 0.
fn nnls2(g: &mut Graph, p: Gram<'_>, inv: Inverses<'_>) -> String {
    let (ss_gy, gs_sy) = (g.op("Mul", &[p.ss, p.gy]), g.op("Mul", &[p.gs, p.sy]));
    let amp_g = g.op("Sub", &[&ss_gy, &gs_sy]);
    let amp_g = g.op("Mul", &[&amp_g, inv.det]);
    let (gg_sy, gs_gy) = (g.op("Mul", &[p.gg, p.sy]), g.op("Mul", &[p.gs, p.gy]));
    let amp_s = g.op("Sub", &[&gg_sy, &gs_gy]);
    let amp_s = g.op("Mul", &[&amp_s, inv.det]);
    let (ag, bs) = (g.op("Mul", &[&amp_g, p.gy]), g.op("Mul", &[&amp_s, p.sy]));
    let inside = g.op("Sub", &[p.yy, &ag]);
    let inside = g.op("Sub", &[&inside, &bs]);
    let rg = g.op("Relu", &[p.gy]);
    let only_g = g.op("Mul", &[&rg, &rg]);
    let only_g = g.op("Mul", &[&only_g, inv.gg]);
    let rs = g.op("Relu", &[p.sy]);
    let only_s = g.op("Mul", &[&rs, &rs]);
    let only_s = g.op("Mul", &[&only_s, inv.ss]);
    let best = g.op("Max", &[&only_g, &only_s]);
    let boundary = g.op("Sub", &[p.yy, &best]);
    let nil = g.scalar("nil", 0.0);
    let (ga, gb) = (g.op("GreaterOrEqual", &[&amp_g, &nil]), g.op("GreaterOrEqual", &[&amp_s, &nil]));
    let both = g.op("And", &[&ga, &gb]);
    let both = g.op("And", &[&both, inv.posed]);
    let v = g.op("Where", &[&both, &inside, &boundary]);
    g.op("Relu", &[&v])
}

/// The taps in the code's blocks and their products that every template fit of the graph
/// reads, computed once a frame: `y·y` and the ambient's column's `s·y` per pixel, with the
/// column `s = A_n 1` (f64, as the fit's) per subpixel type.
struct Taps {
    /// `[B, N, M, P]` ([`to_blocks`]).
    blocks: String,
    /// `y·y` and `s·y`, `[B, N, 1, P]` each.
    yy: String,
    sy: String,
    /// `s` per type `[N][M]`.
    s: Vec<Vec<f64>>,
}

impl Taps {
    fn of(g: &mut Graph, fr: &FrameShape, y: &str, sensor: &MeasurementMatrix) -> Taps {
        let a = sensor.a();
        let (n, m, t) = a.dim();
        let blocks = to_blocks(g, fr, y, m, sensor.block());
        let s: Vec<Vec<f64>> = (0..n).map(|k| (0..m).map(|mm| (0..t).map(|j| a[(k, mm, j)] as f64).sum()).collect()).collect();
        let flat: Vec<f32> = s.iter().flatten().map(|&v| v as f32).collect();
        let sw = g.weight("ambient_template", &[n, 1, m], &flat);
        let sy = g.op("MatMul", &[&sw, &blocks]);
        let y2 = g.op("Mul", &[&blocks, &blocks]);
        let axis2 = g.ints("axis2", &[2]);
        let yy = g.node("ReduceSum", &[&y2, &axis2], &[Attr::Int("keepdims", 1)]);
        Taps { blocks, yy, sy, s }
    }

    /// `sᵀs` of type `k`.
    fn ss(&self, k: usize) -> f64 {
        self.s[k].iter().map(|v| v * v).sum()
    }
}

/// Each pixel's single-return cost at every candidate (the fit's dense pass,
/// `tcsense_fits::depth`): `yy − max fit` over `a, b ≥ 0`, the two columns together where the
/// solve is posed and both amplitudes are non-negative, else the better column alone.
///
/// # Shapes
/// - `taps`: of `[B, M, H, W]` ([`Taps`]) → `[B, C, H, W]` (before the lit mask)
fn pixel_costs(g: &mut Graph, fr: &FrameShape, taps: &Taps, sensor: &MeasurementMatrix, oversample: usize) -> String {
    let a = sensor.a();
    let (n, m, t) = a.dim();
    let block = sensor.block();
    let cols = candidate_columns(t, oversample);
    let c = cols.len();
    // the templates in f64, as the fit's
    let mut gmat = vec![0f32; n * c * m]; // [N, C, M]
    let (mut gg, mut gs, mut inv_det, mut inv_gg) =
        (vec![vec![0f32; c]; n], vec![vec![0f32; c]; n], vec![vec![0f32; c]; n], vec![vec![0f32; c]; n]);
    let (mut ss, mut inv_ss) = (vec![vec![0f32; 1]; n], vec![vec![0f32; 1]; n]);
    for k in 0..n {
        let (s, s2) = (&taps.s[k], taps.ss(k));
        ss[k][0] = s2 as f32;
        inv_ss[k][0] = if ss[k][0] > 0.0 { 1.0 / ss[k][0] } else { 0.0 };
        for (ci, &(t0, t1, f)) in cols.iter().enumerate() {
            let gv: Vec<f64> = (0..m).map(|mm| (1.0 - f) * a[(k, mm, t0)] as f64 + f * a[(k, mm, t1)] as f64).collect();
            for (mm, v) in gv.iter().enumerate() {
                gmat[(k * c + ci) * m + mm] = *v as f32;
            }
            let p: f64 = gv.iter().map(|v| v * v).sum();
            let q: f64 = gv.iter().zip(s).map(|(x, y)| x * y).sum();
            let det = p * s2 - q * q;
            gg[k][ci] = p as f32;
            gs[k][ci] = q as f32;
            inv_det[k][ci] = if det > 1e-12 * p * s2 { (1.0 / det) as f32 } else { 0.0 };
            inv_gg[k][ci] = if p > 0.0 { (1.0 / p) as f32 } else { 0.0 };
        }
    }
    let gw = g.weight("templates", &[n, c, m], &gmat);
    let gy = g.op("MatMul", &[&gw, &taps.blocks]); // [B, N, C, P]
    let (yy, sy) = (taps.yy.as_str(), taps.sy.as_str());
    let (gg, gs, inv_det, inv_gg) =
        (per_type(g, "gram_gg", &gg), per_type(g, "gram_gs", &gs), per_type(g, "inv_det", &inv_det), per_type(g, "inv_gg", &inv_gg));
    let (ss, inv_ss) = (per_type(g, "gram_ss", &ss), per_type(g, "inv_ss", &inv_ss));
    let nil = g.scalar("nil", 0.0);
    let posed = g.op("Greater", &[&inv_det, &nil]);
    let cost =
        nnls2(g, Gram { yy, gy: &gy, sy, gg: &gg, gs: &gs, ss: &ss }, Inverses { det: &inv_det, posed: &posed, gg: &inv_gg, ss: &inv_ss }); // [B, N, C, P]
    from_blocks(g, fr, &cost, c, block)
}

/// Positions of the refinement around a mode: `REFINE_POINTS` candidates `REFINE_STEP` apart
/// (±1.5 candidates of the grid: the fit's best within one of the mode, refined within one of it).
const REFINE_POINTS: usize = 13;
const REFINE_STEP: f32 = 0.25;

/// The first return refined in the tap domain where the fit's window pins it, as `tcsense
/// infer` refines a mode on a window that stays `window × window` in bright light: the
/// window's single-return cost (each pixel its own amplitude and ambient, the templates
/// between the bins linear as the fit's, the neighbours of like range alone: within
/// `edge_bins` of the pixel's mode) at [`REFINE_POINTS`] positions around the mode, the
/// parabola through the least and its neighbours; taken where the least is inside the
/// positions and the cost's curvature there places it to [`tcsense_fits::depth::MODE_PRECISION_BINS`]
/// in the frame's nats, elsewhere (dim light) the mode stands.
///
/// # Shapes
/// - `taps`: of `[B, M, H, W]` ([`Taps`]), `u`: modes `[B, 1, H, W]` (candidates), `litf`: the
///   lit mask `[B, 1, H, W]` (the evidence's), `neg_nats`: `−ν` `[B, 1, 1, 1]` → `[B, 1, H, W]`
///   (candidates)
#[allow(clippy::too_many_arguments)]
fn refine_first(
    g: &mut Graph,
    fr: &FrameShape,
    taps: &Taps,
    sensor: &MeasurementMatrix,
    os: usize,
    window: usize,
    (u, litf): (&str, &str),
    neg_nats: &str,
) -> String {
    let a = sensor.a();
    let (n, m, t) = a.dim();
    let block = sensor.block();
    let c = (t * os) as f32;
    // per type: Aᵀ [N, T, M] and the tables of the templates' Gram entries between
    // neighbouring bins: A_tᵀA_t, A_tᵀA_{t+1}, A_tᵀs, sᵀs
    let mut at = vec![0f32; n * t * m];
    let (mut d0, mut d1, mut a_s, mut ss) =
        (vec![vec![0f32; t]; n], vec![vec![0f32; t]; n], vec![vec![0f32; t]; n], vec![vec![0f32; 1]; n]);
    for k in 0..n {
        let s = &taps.s[k];
        ss[k][0] = taps.ss(k) as f32;
        for j in 0..t {
            let col = |j: usize| (0..m).map(move |mm| a[(k, mm, j)] as f64);
            for (mm, v) in col(j).enumerate() {
                at[(k * t + j) * m + mm] = v as f32;
            }
            d0[k][j] = col(j).map(|v| v * v).sum::<f64>() as f32;
            d1[k][j] = col(j).zip(col((j + 1) % t)).map(|(x, y)| x * y).sum::<f64>() as f32;
            a_s[k][j] = col(j).zip(s).map(|(x, y)| x * y).sum::<f64>() as f32;
        }
    }
    let atw = g.weight("adjoint", &[n, t, m], &at);
    let aty = g.op("MatMul", &[&atw, &taps.blocks]); // [B, N, T, P]
    let (yy, sy) = (taps.yy.as_str(), taps.sy.as_str());
    let shape = g.op("Shape", &[&aty]);
    let shape1 = g.op("Shape", &[yy]);
    let tables: Vec<String> = [("gram_diagonal", &d0), ("gram_next", &d1), ("gram_ambient", &a_s)]
        .iter()
        .map(|(hint, v)| {
            let w = per_type(g, hint, v);
            g.op("Expand", &[&w, &shape])
        })
        .collect();
    let ss = per_type(g, "gram_ss", &ss);
    let ss = g.op("Expand", &[&ss, &shape1]);
    let parts = [aty.as_str(), &tables[0], &tables[1], &tables[2], yy, sy, &ss];
    let q = g.node("Concat", &parts, &[Attr::Int("axis", 2)]); // [B, N, 4T + 3, P]
    let q = from_blocks(g, fr, &q, 4 * t + 3, block); // [B, 4T + 3, H, W]
    let q = g.node("Concat", &[&q, litf, u], &[Attr::Int("axis", 1)]); // [B, 4T + 5, H, W]
                                                                       // the positions around each mode and where they read the templates: p = τ − ½ on the cycle
                                                                       // of bins, t₀ = ⌊p⌋, f = p − t₀, t₁ = t₀ + 1
    let steps: Vec<f32> = (0..REFINE_POINTS).map(|k| (k as f32 - (REFINE_POINTS - 1) as f32 / 2.0) * REFINE_STEP).collect();
    let steps = g.weight("refine_steps", &[1, REFINE_POINTS, 1, 1], &steps);
    let uk = g.op("Add", &[u, &steps]); // [B, K, H, W]
    let (half_os, per_bin, tf) =
        (g.scalar("half_oversample", 0.5 * os as f32), g.scalar("per_bin", 1.0 / os as f32), g.scalar("bins", t as f32));
    let tau = g.op("Add", &[&uk, &half_os]);
    let tau = g.op("Mul", &[&tau, &per_bin]);
    let half = g.scalar("half", 0.5);
    let p = g.op("Sub", &[&tau, &half]);
    let p = g.node("Mod", &[&p, &tf], &[Attr::Int("fmod", 1)]);
    let p = g.op("Add", &[&p, &tf]);
    let p = g.node("Mod", &[&p, &tf], &[Attr::Int("fmod", 1)]);
    let t0f = g.op("Floor", &[&p]);
    let f = g.op("Sub", &[&p, &t0f]);
    let to_int = |g: &mut Graph, x: &str| g.node("Cast", &[x], &[Attr::Int("to", onnx_protobuf::tensor_proto::DataType::INT64 as i64)]);
    let ti = g.ints("bins_i", &[t as i64]);
    let t0 = to_int(g, &t0f);
    let t0 = g.op("Mod", &[&t0, &ti]);
    let one_i = g.ints("one", &[1]);
    let t1 = g.op("Add", &[&t0, &one_i]);
    let t1 = g.op("Mod", &[&t1, &ti]);
    let unit = g.scalar("unit", 1.0);
    let f1 = g.op("Sub", &[&unit, &f]);
    let (ff, f1f) = (g.op("Mul", &[&f, &f]), g.op("Mul", &[&f1, &f1]));
    let two_ff1 = g.op("Mul", &[&f, &f1]);
    let two = g.scalar("two", 2.0);
    let two_ff1 = g.op("Mul", &[&two_ff1, &two]);
    // the window's cost at every position, summed over the like-range neighbours, ring by ring
    // of the windows that grow from the fit's up to the largest a mode's refinement takes
    let hw = (window / 2).max(tcsense_fits::depth::MODE_MAX_HALF) as i64;
    let pads = g.ints("pads", &[0, 0, hw, hw, 0, 0, hw, hw]);
    let qp = g.op("Pad", &[&q, &pads]);
    let axes = g.ints("axes23", &[2, 3]);
    let end = |d: i64| if hw - d > 0 { -(hw - d) } else { i64::MAX };
    let (cf, gap) = (
        g.scalar("candidates", c),
        g.scalar("edge_candidates", (tcsense_fits::range::RangeFitOptions::default().edge_bins * os as f64) as f32),
    );
    let tiny = g.scalar("tiny", 1e-30);
    let mut total: Option<String> = None;
    let mut sums: Vec<String> = Vec::new();
    for ring in 0..=hw {
        let offsets: Vec<(i64, i64)> = (-ring..=ring)
            .flat_map(|di| (-ring..=ring).map(move |dj| (di, dj)))
            .filter(|&(di, dj)| di.abs().max(dj.abs()) == ring)
            .collect();
        for (di, dj) in offsets {
            let (st, en) = (g.ints("starts", &[hw + di, hw + dj]), g.ints("ends", &[end(di), end(dj)]));
            let qs = g.op("Slice", &[&qp, &st, &en, &axes]);
            let ch = |g: &mut Graph, start: usize, len: usize| super::channels(g, &qs, start, len);
            let (aty_q, d0_q, d1_q, as_q) = (ch(g, 0, t), ch(g, t, t), ch(g, 2 * t, t), ch(g, 3 * t, t));
            let (yy_q, sy_q, ss_q, lit_q, u_q) =
                (ch(g, 4 * t, 1), ch(g, 4 * t + 1, 1), ch(g, 4 * t + 2, 1), ch(g, 4 * t + 3, 1), ch(g, 4 * t + 4, 1));
            let at_ = |g: &mut Graph, x: &str, i: &str| g.node("GatherElements", &[x, i], &[Attr::Int("axis", 1)]);
            let (a0, a1) = (at_(g, &aty_q, &t0), at_(g, &aty_q, &t1));
            let gy = g.op("Sub", &[&a1, &a0]);
            let gy = g.op("Mul", &[&gy, &f]);
            let gy = g.op("Add", &[&a0, &gy]);
            let (g00, g01, g11) = (at_(g, &d0_q, &t0), at_(g, &d1_q, &t0), at_(g, &d0_q, &t1));
            let (x, yv, z) = (g.op("Mul", &[&g00, &f1f]), g.op("Mul", &[&g01, &two_ff1]), g.op("Mul", &[&g11, &ff]));
            let gg = g.op("Add", &[&x, &yv]);
            let gg = g.op("Add", &[&gg, &z]);
            let (s0, s1) = (at_(g, &as_q, &t0), at_(g, &as_q, &t1));
            let gs = g.op("Sub", &[&s1, &s0]);
            let gs = g.op("Mul", &[&gs, &f]);
            let gs = g.op("Add", &[&s0, &gs]);
            // the two-column NNLS (as `pixel_costs`, the Gram entries of this position)
            let (ggss, gs2) = (g.op("Mul", &[&gg, &ss_q]), g.op("Mul", &[&gs, &gs]));
            let det = g.op("Sub", &[&ggss, &gs2]);
            let eps = g.scalar("posed", 1e-12);
            let bound = g.op("Mul", &[&ggss, &eps]);
            let posed = g.op("Greater", &[&det, &bound]);
            let inverse = |g: &mut Graph, x: &str| {
                let x = g.op("Max", &[x, &tiny]);
                g.op("Div", &[&unit, &x])
            };
            let (inv_det, inv_gg, inv_ss) = (inverse(g, &det), inverse(g, &gg), inverse(g, &ss_q));
            let v = nnls2(
                g,
                Gram { yy: &yy_q, gy: &gy, sy: &sy_q, gg: &gg, gs: &gs, ss: &ss_q },
                Inverses { det: &inv_det, posed: &posed, gg: &inv_gg, ss: &inv_ss },
            );
            // a neighbour of like range (within the edge gap, on the cycle), lit
            let d = g.op("Sub", &[&u_q, u]);
            let d = g.op("Abs", &[&d]);
            let other = g.op("Sub", &[&cf, &d]);
            let other = g.op("Abs", &[&other]);
            let d = g.op("Min", &[&d, &other]);
            let near = g.op("LessOrEqual", &[&d, &gap]);
            let near = g.node("Cast", &[&near], &[Attr::Int("to", onnx_protobuf::tensor_proto::DataType::FLOAT as i64)]);
            let keep = g.op("Mul", &[&near, &lit_q]);
            let v = g.op("Mul", &[&v, &keep]);
            total = Some(match total {
                None => v,
                Some(acc) => g.op("Add", &[&acc, &v]),
            });
        }
        if 2 * ring as usize + 1 >= window {
            sums.push(total.clone().expect("a window of one pixel at least")); // [B, K, H, W]
        }
    }
    // the smallest window that pins its least position, refined there; else the mode stands
    let mut out = u.to_string();
    for total in sums.iter().rev() {
        let (take, refined) = pinned(g, total, u, neg_nats, os, &cf);
        out = g.op("Where", &[&take, &refined, &out]);
    }
    out
}

/// Where the window's cost `total` `[B, K, H, W]` at the positions around the modes `u`
/// `[B, 1, H, W]` pins its least position, and that position refined by the parabola through
/// its neighbours (candidates, on the cycle of `c`): `(take [B, 1, H, W] bool, refined)`.
fn pinned(g: &mut Graph, total: &str, u: &str, neg_nats: &str, os: usize, cf: &str) -> (String, String) {
    let (two, half, tiny) = (g.scalar("two", 2.0), g.scalar("half", 0.5), g.scalar("tiny", 1e-30));
    // the least position, the parabola through it and its neighbours, its precision
    let k = g.node("ArgMin", &[total], &[Attr::Int("axis", 1), Attr::Int("keepdims", 1)]);
    let sides = g.ints("refine_sides", &[-1, 0, 1]);
    let side_shape = g.ints("side_shape", &[1, 3, 1, 1]);
    let sides = g.op("Reshape", &[&sides, &side_shape]);
    let idx = g.op("Add", &[&k, &sides]);
    let (first, last) = (g.ints("zero", &[0]), g.ints("last", &[REFINE_POINTS as i64 - 1]));
    let idx = g.op("Clip", &[&idx, &first, &last]);
    let c3 = g.node("GatherElements", &[total, &idx], &[Attr::Int("axis", 1)]); // [B, 3, H, W]
    let (lo, mid, hi) = (super::channels(g, &c3, 0, 1), super::channels(g, &c3, 1, 1), super::channels(g, &c3, 2, 1));
    let two_mid = g.op("Mul", &[&mid, &two]);
    let curv = g.op("Add", &[&lo, &hi]);
    let curv = g.op("Sub", &[&curv, &two_mid]);
    let num = g.op("Sub", &[&lo, &hi]);
    let num = g.op("Mul", &[&num, &half]);
    let den = g.op("Max", &[&curv, &tiny]);
    let offset = g.op("Div", &[&num, &den]);
    let neg_half = g.scalar("neg_half", -0.5);
    let offset = g.op("Clip", &[&offset, &neg_half, &half]);
    // inside the positions, curving upwards, and precise: curvature·os²·ν/step² ≥ 1/precision²
    let (zero_i, last_i) = (g.ints("zero", &[0]), g.ints("last", &[REFINE_POINTS as i64 - 1]));
    let (above, below) = (g.op("Greater", &[&k, &zero_i]), g.op("Less", &[&k, &last_i]));
    let interior = g.op("And", &[&above, &below]);
    let nats = g.op("Neg", &[neg_nats]);
    let kappa = g.op("Mul", &[&curv, &nats]);
    let scale = g.scalar("bins_per_step2", (os * os) as f32 / (REFINE_STEP * REFINE_STEP));
    let kappa = g.op("Mul", &[&kappa, &scale]);
    let need = g.scalar(
        "precision_curvature",
        (1.0 / (tcsense_fits::depth::MODE_PRECISION_BINS * tcsense_fits::depth::MODE_PRECISION_BINS)) as f32,
    );
    let precise = g.op("GreaterOrEqual", &[&kappa, &need]);
    let take = g.op("And", &[&interior, &precise]);
    let kf = g.node("Cast", &[&k], &[Attr::Int("to", onnx_protobuf::tensor_proto::DataType::FLOAT as i64)]);
    let centre = g.scalar("centre_point", (REFINE_POINTS - 1) as f32 / 2.0);
    let du = g.op("Sub", &[&kf, &centre]);
    let du = g.op("Add", &[&du, &offset]);
    let step = g.scalar("refine_step", REFINE_STEP);
    let du = g.op("Mul", &[&du, &step]);
    let refined = g.op("Add", &[u, &du]);
    let refined = g.node("Mod", &[&refined, cf], &[Attr::Int("fmod", 1)]);
    let refined = g.op("Add", &[&refined, cf]);
    let refined = g.node("Mod", &[&refined, cf], &[Attr::Int("fmod", 1)]);
    (take, refined)
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
    let y = unit_scale(&mut g, &y);
    // lit: the pixels with charge
    let axis1 = g.ints("axis1", &[1]);
    let intensity = g.node("ReduceSum", &[&y, &axis1], &[Attr::Int("keepdims", 1)]); // [B, 1, H, W]
    let nil = g.scalar("nil", 0.0);
    let lit = g.op("Greater", &[&intensity, &nil]);
    let litf = g.node("Cast", &[&lit], &[Attr::Int("to", onnx_protobuf::tensor_proto::DataType::FLOAT as i64)]);
    let taps = Taps::of(&mut g, &fr, &y, sensor);
    let cost = pixel_costs(&mut g, &fr, &taps, sensor, os);
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
    let u = refine_first(&mut g, &fr, &taps, sensor, os, window, (&u, &litf), &neg_nats);
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
        "tcsense U-Net on the range fit's evidence, one graph from the taps ({c} candidate ranges over {:.3} m, {} levels{}): measurements [B, {m}, H, W] -> depth (m) [B, 1, H, W] (the posterior's mode refined in the tap domain where a window pins it; NaN where unlit or below half confidence), confidence [B, 1, H, W]",
        net.range_m(),
        net.down().len(),
        if pool_like > window { format!(", the {window}×{window} window pooled by likeness over {pool_like}×{pool_like}") } else { String::new() },
    );
    super::model_bytes(g, &doc, meta)
}
