//! ONNX export of the learned decoders (DESIGN §5, "the ONNX graph").
//!
//! ```text
//! input   measurements   [B, M, H, W]  float32, raw tap images (any scale)
//!         sensor_matrix  [N, M, T]     float32, only with `ExportOptions::matrix_input`
//! output  cube           [B, T, H, W]  ADMM-Net
//!         depth          [B, K, H, W]  Aᵀ + U-Net, metres
//!         confidence     [B, K, H, W]  Aᵀ + U-Net, in [0, 1]
//! ```
//!
//! `B`, `H` and `W` are dynamic; `H` and `W` must be multiples of the frame multiple in the
//! metadata (the block, and for the U-Net its stride `2^(levels−1)`). Every layer emits its
//! own nodes ([`graph::Graph`]); the sensor's per-pixel operators become plain convolutions
//! ([`sensor`]); weights are initializers (never graph inputs). The codes, sensor model,
//! units and frame rule travel in `metadata_props` ([`OnnxMeta`]), which `tcsense infer`
//! checks against the measurements. Opset 17, IR version 9: any ONNX runtime of the last
//! years reads it.

pub mod graph;
pub mod meta;
pub mod range_graph;
pub mod sensor;

use burn::nn::conv::Conv2d;
use protobuf::Message;
use std::path::Path;

use tcsense_models::admm::{Stage, DELAY_DILATIONS};
use tcsense_models::runs::{LoadedRun, TrainedNet};
use tcsense_models::{AdmmNet, LifetimeNet, Prior, Unet};

use crate::{InferError, Result};
use graph::{Attr, Dim, Graph};
pub use meta::OnnxMeta;
use sensor::SensorGraph;
use tcsense_sensor::calibration::Calibration;

/// Name of the measurements input.
pub const INPUT: &str = "measurements";
/// Name of the optional sensor-matrix input.
pub const MATRIX_INPUT: &str = "sensor_matrix";
/// Inputs of a lifetime decoder on the fit's evidence
/// ([`tcsense_models::LifetimeInput::Costs`]): the pooled per-pixel posteriors, log intensity
/// and lit mask, and the fit's window log-likelihood over the lifetime grid
/// ([`tcsense_fits::lifetime_taps::evidence`]), computed by the runtime from the taps.
pub const EVIDENCE_INPUT: &str = "evidence";
pub const LOG_LIKELIHOOD_INPUT: &str = "log_likelihood";
/// Outputs of a U-Net on the range fit's evidence ([`tcsense_models::UnetInput::Costs`]): the
/// range (m) of its posterior's mode and the first return's confidence, which the runtime
/// turns into the product (the mode refined in the tap domain, the fit's second return).
pub const MODE_RANGE_OUTPUT: &str = "mode_range";
pub const FIRST_CONFIDENCE_OUTPUT: &str = "first_confidence";

/// Export options.
#[derive(Debug, Clone, Copy, Default)]
pub struct ExportOptions<'a> {
    /// Take the sensor matrix `[N, M, T]` as a second input instead of baking it in.
    pub matrix_input: bool,
    /// A sensor calibration to build in: the graph takes raw tap images of the calibration's
    /// frame size, subtracts its dark offsets and divides by its gains (`(y − d) / G`), and
    /// decodes with its matrix; the metadata records it.
    pub calibration: Option<&'a Calibration>,
    /// A U-Net on the range fit's evidence as one graph from the tap images
    /// ([`range_graph`]): the evidence computed in the graph, not by the runtime.
    pub from_taps: bool,
}

/// The ONNX model of a trained run, serialised.
pub fn export(run: &LoadedRun, opts: ExportOptions<'_>) -> Result<Vec<u8>> {
    let meta = OnnxMeta::of_run(run, opts);
    if opts.from_taps {
        return from_taps(run, &meta, opts);
    }
    if let TrainedNet::Lifetime(net) = &run.net {
        if net.input_kind() == tcsense_models::LifetimeInput::Costs {
            return lifetime_on_evidence(net, &meta, opts);
        }
    }
    if let TrainedNet::Unet(net) = &run.net {
        if net.input_kind() == tcsense_models::UnetInput::Costs {
            return unet_on_evidence(net, &meta, opts);
        }
    }
    let (n, m, t) = run.sensor.matrix().a().dim();
    let mut g = Graph::new(run.spec.model.name());
    let y = match opts.calibration {
        None => g.input(INPUT, &[Dim::Named("batch"), Dim::Fixed(m), Dim::Named("height"), Dim::Named("width")]),
        Some(cal) => {
            // raw tap images of the calibrated frame size, corrected in the graph: (y − d) / G
            let [h, w] = cal.meta.size;
            if cal.meta.taps != m || cal.matrix.a().dim() != (n, m, t) {
                return Err(InferError::InvalidParam {
                    field: "calibration",
                    got: format!("A {:?}", cal.matrix.a().dim()),
                    expected: format!("the run's sensor [N, M, T] = [{n}, {m}, {t}]"),
                });
            }
            let raw = g.input(INPUT, &[Dim::Named("batch"), Dim::Fixed(m), Dim::Fixed(h), Dim::Fixed(w)]);
            let dark = g.weight(
                "calibration_dark",
                &[1, m, h, w],
                cal.dark.as_slice().ok_or_else(|| InferError::InvalidParam {
                    field: "calibration",
                    got: "a strided dark map".into(),
                    expected: "a contiguous map".into(),
                })?,
            );
            let gain = g.weight(
                "calibration_gain",
                &[1, m, h, w],
                cal.gain.as_slice().ok_or_else(|| InferError::InvalidParam {
                    field: "calibration",
                    got: "a strided gain map".into(),
                    expected: "a contiguous map".into(),
                })?,
            );
            let d = g.op("Sub", &[&raw, &dark]);
            g.op("Div", &[&d, &gain])
        }
    };
    let a_model = opts.calibration.map_or(run.sensor.matrix(), |c| &c.matrix);
    let sensor = if opts.matrix_input {
        let a = g.input(MATRIX_INPUT, &[Dim::Fixed(n), Dim::Fixed(m), Dim::Fixed(t)]);
        SensorGraph::from_input(&mut g, &a, n, m, t, run.sensor.matrix().block())
    } else {
        SensorGraph::baked(a_model)
    };
    let frame = [Dim::Named("batch"), Dim::Fixed(0), Dim::Named("height"), Dim::Named("width")];
    let with_c = |c: usize| {
        let mut d = frame;
        d[1] = Dim::Fixed(c);
        d
    };
    let doc = match &run.net {
        TrainedNet::AdmmNet(net) => {
            let cube = admm_net(&mut g, net, &sensor, &y)?;
            g.output(&cube, "cube", &with_c(t));
            format!("tcsense ADMM-Net ({} stages): measurements [B, M, H, W] -> cube [B, T, H, W]", net.stages().len())
        }
        TrainedNet::Lifetime(net) => {
            let (lifetime, conf, intensity) = lifetime(&mut g, net, &sensor, &y)?;
            g.output(&lifetime, "lifetime", &with_c(4));
            g.output(&conf, "confidence", &with_c(1));
            g.output(&intensity, "intensity", &with_c(1));
            format!("tcsense lifetime decoder ({} harmonics, {} levels): measurements [B, M, H, W] -> lifetime (s) [B, 4, H, W], confidence, intensity [B, 1, H, W]", net.harmonics(), net.down().len())
        }
        TrainedNet::Unet(net) => {
            let (depth, conf) = unet(&mut g, net, &sensor, &y)?;
            let k = net.returns();
            g.output(&depth, "depth", &with_c(k));
            g.output(&conf, "confidence", &with_c(k));
            format!("tcsense A^T + U-Net ({} levels): measurements [B, M, H, W] -> depth (m), confidence [B, K, H, W]", net.levels())
        }
    };
    model_bytes(g, &doc, &meta)
}

/// [`range_graph::unet_from_taps`] of a run, for a U-Net on the range fit's evidence only,
/// without a matrix input or a calibration (the graph bakes the sensor's templates in).
fn from_taps(run: &LoadedRun, meta: &OnnxMeta, opts: ExportOptions<'_>) -> Result<Vec<u8>> {
    let refuse = |got: &str| InferError::InvalidParam {
        field: "export",
        got: got.into(),
        expected:
            "--from-taps for a U-Net on the range fit's evidence (zoo:unet-lidar-evidence-*), without --matrix-input or --calibration"
                .into(),
    };
    match &run.net {
        TrainedNet::Unet(net) if net.input_kind() == tcsense_models::UnetInput::Costs => {
            if opts.matrix_input {
                return Err(refuse("--from-taps with --matrix-input"));
            }
            if opts.calibration.is_some() {
                return Err(refuse("--from-taps with --calibration"));
            }
            range_graph::unet_from_taps(net, run.sensor.matrix(), meta, net.fit_options().fit.window)
        }
        _ => Err(refuse(&format!("--from-taps for a model that does not read the range fit's evidence ({})", run.spec.model.name()))),
    }
}

/// The model of graph `g`, documented by `doc`, with `meta` in its `metadata_props`, serialised.
fn model_bytes(g: Graph, doc: &str, meta: &OnnxMeta) -> Result<Vec<u8>> {
    g.into_model(doc, &meta.to_props()).write_to_bytes().map_err(|e| InferError::InvalidParam {
        field: "ONNX model",
        got: e.to_string(),
        expected: "a serialisable model".into(),
    })
}

/// Export `run` to `path` (written to a temporary file, then renamed).
pub fn export_to(run: &LoadedRun, opts: ExportOptions<'_>, path: &Path) -> Result<usize> {
    let bytes = export(run, opts)?;
    tcsense_sensor::npy::write_bytes(path, &bytes)?;
    Ok(bytes.len())
}

fn values(t: burn::tensor::TensorData) -> Result<Vec<f32>> {
    t.try_into_vec::<f32>().map_err(|e| InferError::InvalidParam {
        field: "weights",
        got: format!("{e:?}"),
        expected: "f32 weights".into(),
    })
}

/// An ONNX `Conv` of `x` with weights `[dims]` and `layer`'s bias (if any).
fn conv_node(g: &mut Graph, layer: &Conv2d, x: &str, dims: &[usize], w: &[f32], attrs: &[Attr<'_>]) -> Result<String> {
    let wn = g.weight("conv_w", dims, w);
    match &layer.bias {
        Some(b) => {
            let bv = values(b.val().into_data())?;
            let bn = g.weight("conv_b", &[bv.len()], &bv);
            Ok(g.node("Conv", &[x, &wn, &bn], attrs))
        }
        None => Ok(g.node("Conv", &[x, &wn], attrs)),
    }
}

/// A burn `Conv2d` (3×3 "same" or 1×1) as an ONNX `Conv`.
fn conv(g: &mut Graph, layer: &Conv2d, x: &str) -> Result<String> {
    let dims = layer.weight.dims();
    let w = values(layer.weight.val().into_data())?;
    let pad = (dims[2] / 2) as i64;
    conv_node(
        g,
        layer,
        x,
        &dims,
        &w,
        &[Attr::Ints("kernel_shape", &[dims[2] as i64, dims[3] as i64]), Attr::Ints("pads", &[pad, pad, pad, pad])],
    )
}

/// One layer of the delay prior ([`Prior::Delay`]) on `x [B, C_in, T, H, W]` → `[B, C_out, T, H, W]`:
/// the cube padded circularly in `t` by `d` bins on each side (`Slice` + `Concat`), then a
/// 3×3×3 `Conv` dilated `d` in `t`. Its weight `[C_out, C_in, 3, 3, 3]` is the burn layer's
/// `[C_out, 3·C_in, 3, 3]`, input channel `j·C_in + c` being channel `c` at bin `t + (j − 1)·d`.
fn delay_conv(g: &mut Graph, layer: &Conv2d, x: &str, d: usize) -> Result<String> {
    let [co, ci3, kh, kw] = layer.weight.dims();
    let ci = ci3 / 3;
    let w2 = values(layer.weight.val().into_data())?;
    let mut w3 = vec![0f32; w2.len()];
    let k = kh * kw;
    for o in 0..co {
        for j in 0..3 {
            for c in 0..ci {
                let src = ((o * ci3) + j * ci + c) * k;
                let dst = ((o * ci + c) * 3 + j) * k;
                w3[dst..dst + k].copy_from_slice(&w2[src..src + k]);
            }
        }
    }
    let d = d as i64;
    let axis = g.ints("axis_t", &[2]);
    let (last_start, last_end) = (g.ints("wrap_start", &[-d]), g.ints("wrap_end", &[i64::MAX]));
    let (first_start, first_end) = (g.ints("wrap_start", &[0]), g.ints("wrap_end", &[d]));
    let tail = g.op("Slice", &[x, &last_start, &last_end, &axis]);
    let head = g.op("Slice", &[x, &first_start, &first_end, &axis]);
    let padded = g.node("Concat", &[&tail, x, &head], &[Attr::Int("axis", 2)]);
    let attrs = [
        Attr::Ints("kernel_shape", &[3, kh as i64, kw as i64]),
        Attr::Ints("dilations", &[d, 1, 1]),
        Attr::Ints("pads", &[0, 1, 1, 0, 1, 1]),
    ];
    conv_node(g, layer, &padded, &[co, ci, 3, kh, kw], &w3, &attrs)
}

/// The prior's residual `P(x)` of an ADMM-Net stage on `x [B, T, H, W]` → `[B, T, H, W]`.
fn prior(g: &mut Graph, st: &Stage, kind: Prior, x: &str) -> Result<String> {
    let [c1, c2, c3] = st.convs();
    match kind {
        Prior::Bins => {
            let h = conv(g, c1, x)?;
            let h = relu(g, &h);
            let h = conv(g, c2, &h)?;
            let h = relu(g, &h);
            conv(g, c3, &h)
        }
        Prior::Delay => {
            let [d1, d2, d3] = DELAY_DILATIONS;
            let axis = g.ints("axis_c", &[1]);
            let h = g.op("Unsqueeze", &[x, &axis]); // [B, 1, T, H, W]
            let h = delay_conv(g, c1, &h, d1)?;
            let h = relu(g, &h);
            let h = delay_conv(g, c2, &h, d2)?;
            let h = relu(g, &h);
            let p = delay_conv(g, c3, &h, d3)?;
            Ok(g.op("Squeeze", &[&p, &axis]))
        }
    }
}

fn relu(g: &mut Graph, x: &str) -> String {
    g.node("Relu", &[x], &[])
}

/// ADMM-Net ([`tcsense_models::admm`]) on `y [B, M, H, W]` → cube `[B, T, H, W]`.
fn admm_net(g: &mut Graph, net: &AdmmNet, sensor: &SensorGraph, y: &str) -> Result<String> {
    // per-frame scale: the mean absolute tap value
    let scale = if net.normalize() {
        let abs = g.node("Abs", &[y], &[]);
        let mean = g.node("ReduceMean", &[&abs], &[Attr::Ints("axes", &[1, 2, 3]), Attr::Int("keepdims", 1)]);
        let tiny = g.scalar("tiny", 1e-12);
        Some(g.node("Add", &[&mean, &tiny], &[]))
    } else {
        None
    };
    let y = match &scale {
        Some(s) => g.node("Div", &[y, s], &[]),
        None => y.to_string(),
    };
    let yb = sensor.measurement_blocks(g, &y);
    let mut z = sensor.pinv(g, &yb);
    let rhos: Vec<f64> = net.stages().iter().map(|s| s.rho() as f64).collect();
    let dc = sensor.dc_weights(g, &rhos);
    let mut u: Option<String> = None;
    for (k, st) in net.stages().iter().enumerate() {
        // x = (AᵀA + ρI)⁻¹(Aᵀy + ρ(z − u))
        let d = match &u {
            Some(u) => g.op("Sub", &[&z, u]),
            None => z.clone(),
        };
        let x = sensor.x_update(g, &d, &yb, &dc, k);
        let xu = match &u {
            Some(u) => g.op("Add", &[&x, u]),
            None => x.clone(),
        };
        let p = prior(g, st, net.prior(), &xu)?;
        z = g.op("Add", &[&xu, &p]);
        // u + η(x − z)
        let eta = g.scalar("eta", st.eta());
        let xz = g.op("Sub", &[&x, &z]);
        let step = g.op("Mul", &[&xz, &eta]);
        u = Some(match &u {
            Some(u) => g.op("Add", &[u, &step]),
            None => step,
        });
    }
    Ok(match &scale {
        Some(s) => g.node("Mul", &[&z, s], &[]),
        None => z,
    })
}

/// Aᵀ + U-Net ([`tcsense_models::unet`]) on `y [B, M, H, W]` → (depth (m), confidence), each
/// `[B, K, H, W]`; `H`, `W` multiples of the stride.
/// The encoder–decoder of a U-Net ([`tcsense_models::unet`]) on frames that are multiples of
/// its stride.
///
/// # Shapes
/// - `x`: `[B, C, H, W]` → `[B, w₀, H, W]`
fn unet_trunk(g: &mut Graph, down: &[tcsense_models::unet::Block], up: &[tcsense_models::unet::Block], x: &str) -> Result<String> {
    let levels = down.len();
    let block = |g: &mut Graph, b: &tcsense_models::unet::Block, x: &str| {
        let [c1, c2] = b.convs();
        let h = conv(g, c1, x)?;
        let h = relu(g, &h);
        let h = conv(g, c2, &h)?;
        Ok::<String, InferError>(relu(g, &h))
    };
    let mut z = x.to_string();
    let mut skips = Vec::with_capacity(levels);
    for (l, b) in down.iter().enumerate() {
        z = block(g, b, &z)?;
        if l + 1 < levels {
            skips.push(z.clone());
            z = g.node("MaxPool", &[&z], &[Attr::Ints("kernel_shape", &[2, 2]), Attr::Ints("strides", &[2, 2])]);
        }
    }
    let scales = g.weight("up_scales", &[4], &[1.0, 1.0, 2.0, 2.0]);
    for (b, skip) in up.iter().zip(skips).rev() {
        let up = g.node(
            "Resize",
            &[&z, "", &scales],
            &[Attr::Str("mode", "nearest"), Attr::Str("coordinate_transformation_mode", "asymmetric"), Attr::Str("nearest_mode", "floor")],
        );
        let cat = g.node("Concat", &[&up, &skip], &[Attr::Int("axis", 1)]);
        z = block(g, b, &cat)?;
    }
    Ok(z)
}

/// Channels `[start, start + len)` of `x` (axis 1).
fn channels(g: &mut Graph, x: &str, start: usize, len: usize) -> String {
    let (s, e, ax) = (g.ints("starts", &[start as i64]), g.ints("ends", &[(start + len) as i64]), g.ints("axes", &[1]));
    g.op("Slice", &[x, &s, &e, &ax])
}

/// The lifetime decoder ([`tcsense_models::lifetime`]): harmonics of `Aᵀy` folded into one
/// matrix per subpixel, turned to the frame's delay reference, normalised, the U-Net, and the
/// heads; lifetimes in seconds.
///
/// # Shapes
/// - `y`: `[B, M, H, W]` → (`lifetime [B, 4, H, W]`, `confidence [B, 1, H, W]`, `intensity [B, 1, H, W]`)
fn lifetime(g: &mut Graph, net: &LifetimeNet, sensor: &SensorGraph, y: &str) -> Result<(String, String, String)> {
    let (k, t) = (net.harmonics(), net.bins());
    let spec = sensor.adjoint_then(g, y, &tcsense_models::lifetime::dft_basis(k, t), 2 * k + 1); // [B, 2K+1, H, W]
                                                                                                 // the delay reference e^{iφ} from the frame's summed first harmonic
    let axes23 = g.ints("axes23", &[2, 3]);
    let total = g.node("ReduceSum", &[&spec, &axes23], &[Attr::Int("keepdims", 1)]); // [B, 2K+1, 1, 1]
    let (re1, im1) = (channels(g, &total, 1, 1), channels(g, &total, k + 1, 1));
    let (re2, im2) = (g.op("Mul", &[&re1, &re1]), g.op("Mul", &[&im1, &im1]));
    let r = g.op("Add", &[&re2, &im2]);
    let r = g.op("Sqrt", &[&r]);
    let floor = g.scalar("ref_floor", 1e-20);
    let r = g.op("Add", &[&r, &floor]);
    let (c1, s1) = (g.op("Div", &[&re1, &r]), g.op("Div", &[&im1, &r]));
    let (mut cs, mut ss) = (vec![c1.clone()], vec![s1.clone()]);
    for j in 1..k {
        let (c, s) = (cs[j - 1].clone(), ss[j - 1].clone());
        let (a, b) = (g.op("Mul", &[&c, &c1]), g.op("Mul", &[&s, &s1]));
        let (e, f) = (g.op("Mul", &[&s, &c1]), g.op("Mul", &[&c, &s1]));
        cs.push(g.op("Sub", &[&a, &b]));
        ss.push(g.op("Add", &[&e, &f]));
    }
    let cs_refs: Vec<&str> = cs.iter().map(String::as_str).collect();
    let ss_refs: Vec<&str> = ss.iter().map(String::as_str).collect();
    let c = g.node("Concat", &cs_refs, &[Attr::Int("axis", 1)]); // [B, K, 1, 1]
    let s = g.node("Concat", &ss_refs, &[Attr::Int("axis", 1)]);
    let (dc, re, im) = (channels(g, &spec, 0, 1), channels(g, &spec, 1, k), channels(g, &spec, k + 1, k));
    let (a, b) = (g.op("Mul", &[&re, &c]), g.op("Mul", &[&im, &s]));
    let re_r = g.op("Add", &[&a, &b]);
    let (a, b) = (g.op("Mul", &[&im, &c]), g.op("Mul", &[&re, &s]));
    let im_r = g.op("Sub", &[&a, &b]);
    let z = g.node("Concat", &[&dc, &re_r, &im_r], &[Attr::Int("axis", 1)]);
    // per-pixel normalisation and the relative brightness
    let norm = g.node("ReduceL2", &[&z], &[Attr::Ints("axes", &[1]), Attr::Int("keepdims", 1)]);
    let mean = g.node("ReduceMean", &[&norm], &[Attr::Ints("axes", &[2, 3]), Attr::Int("keepdims", 1)]);
    let tiny = g.scalar("tiny", 1e-30);
    let mt = g.op("Add", &[&mean, &tiny]);
    let rel = g.op("Div", &[&norm, &mt]);
    let nf = g.scalar("norm_floor", tcsense_models::unet::NORM_FLOOR as f32);
    let mf = g.op("Mul", &[&mean, &nf]);
    let den = g.op("Add", &[&norm, &mf]);
    let den = g.op("Add", &[&den, &tiny]);
    let zn = g.op("Div", &[&z, &den]);
    let x = g.node("Concat", &[&zn, &rel], &[Attr::Int("axis", 1)]);
    let trunk = unet_trunk(g, net.down(), net.up(), &x)?;
    let o = conv(g, net.head(), &trunk)?; // [B, 5, H, W]
    let split5 = g.ints("split5", &[1, 1, 1, 1, 1]);
    let parts = g.node_multi("Split", &[&o, &split5], &[Attr::Int("axis", 1)], 5);
    let [lo, hi] = net.tau_range_ns();
    let (lo_n, span_n) = (g.scalar("log_tau_lo", (lo * 1e-9).ln() as f32), g.scalar("log_tau_span", (hi / lo).ln() as f32));
    let tau = |g: &mut Graph, o: &str| {
        let sg = g.op("Sigmoid", &[o]);
        let a = g.op("Mul", &[&sg, &span_n]);
        let a = g.op("Add", &[&a, &lo_n]);
        g.op("Exp", &[&a])
    };
    let tm = tau(g, &parts[0]);
    let (ta, tb) = (tau(g, &parts[1]), tau(g, &parts[2]));
    let (t1, t2) = (g.op("Min", &[&ta, &tb]), g.op("Max", &[&ta, &tb]));
    let alpha = g.op("Sigmoid", &[&parts[3]]);
    let conf = g.op("Sigmoid", &[&parts[4]]);
    let lifetime = g.node("Concat", &[&tm, &t1, &t2, &alpha], &[Attr::Int("axis", 1)]);
    let axis1 = g.ints("axis1", &[1]);
    let intensity = g.node("ReduceSum", &[y, &axis1], &[Attr::Int("keepdims", 1)]);
    Ok((lifetime, conf, intensity))
}

/// The mode of a posterior over `points` grid points (axis 1 of the pixels' `logits`
/// `[N, G]`), refined by the parabola through its log at the neighbouring points (within half
/// a step; none where a neighbour is not below it), as a float grid coordinate `[N, 1]`. On a
/// `cyclic` grid the neighbours wrap around; otherwise they are clamped to the grid, so at
/// either end a neighbour is the point itself.
fn posterior_mode(g: &mut Graph, logits: &str, points: usize, cyclic: bool) -> String {
    // (few operators on the per-pixel columns: each is a wake-up of ONNX Runtime's threads)
    let best = g.node("ArgMax", &[logits], &[Attr::Int("axis", 1), Attr::Int("keepdims", 1)]); // int64 [N, 1]
    let sides = if cyclic {
        let (steps, n) = (g.ints("side_steps", &[points as i64 - 1, 1]), g.ints("points", &[points as i64]));
        let sides = g.op("Add", &[&best, &steps]);
        g.node("Mod", &[&sides, &n], &[])
    } else {
        let (steps, zero, last) = (g.ints("side_steps", &[-1, 1]), g.ints("zero", &[0]), g.ints("last", &[points as i64 - 1]));
        let sides = g.op("Add", &[&best, &steps]);
        g.op("Clip", &[&sides, &zero, &last])
    }; // [N, 2]: the neighbours below and above
    let sides = g.node("GatherElements", &[logits, &sides], &[Attr::Int("axis", 1)]);
    // the mode's log is the maximum: the neighbours' logs below it, d = (l₋ − l₀, l₊ − l₀)
    let l0 = g.node("ReduceMax", &[logits], &[Attr::Ints("axes", &[1]), Attr::Int("keepdims", 1)]);
    let d = g.op("Sub", &[&sides, &l0]); // [N, 2]
                                         // (½(d₋ − d₊), d₋ + d₊): the parabola's numerator and curvature
    let mix = g.weight("parabola", &[2, 2], &[0.5, 1.0, -0.5, 1.0]);
    let nc = g.op("MatMul", &[&d, &mix]);
    let halves = g.ints("split_sides", &[1, 1]);
    let parts = g.node_multi("Split", &[&nc, &halves], &[Attr::Int("axis", 1)], 2);
    let eps = g.scalar("neg_eps", -1e-12);
    let den = g.op("Min", &[&parts[1], &eps]);
    let delta = g.op("Div", &[&parts[0], &den]);
    let (neg_half, half) = (g.scalar("neg_half", -0.5), g.scalar("half", 0.5));
    let delta = g.op("Clip", &[&delta, &neg_half, &half]);
    // an interior maximum: both neighbours below it
    let top = g.node("ReduceMax", &[&d], &[Attr::Ints("axes", &[1]), Attr::Int("keepdims", 1)]);
    let nil = g.scalar("nil", 0.0);
    let interior = g.op("Less", &[&top, &nil]);
    let delta = g.op("Where", &[&interior, &delta, &nil]);
    let u = g.node("Cast", &[&best], &[Attr::Int("to", 1)]); // FLOAT
    g.op("Add", &[&u, &delta])
}

/// The pixels of the pixel-major evidence as rows: `[B, H, W, C]` → `[B·H·W, C]` (a view in
/// ONNX Runtime: no copy), and the shape `[B, 1, H, W]` of a frame's map of them.
fn pixel_rows(g: &mut Graph, x: &str, c: usize) -> (String, String) {
    let rows = g.ints("rows_shape", &[-1, c as i64]);
    let r = g.op("Reshape", &[x, &rows]);
    let shape = g.op("Shape", &[x]);
    let (s0, s1, s3) = (g.ints("s0", &[0]), g.ints("s1", &[1]), g.ints("s3", &[3]));
    let b = g.node("Slice", &[&shape, &s0, &s1], &[]);
    let hw = g.node("Slice", &[&shape, &s1, &s3], &[]);
    let frame = g.node("Concat", &[&b, &s1, &hw], &[Attr::Int("axis", 0)]); // [B, 1, H, W]
    (r, frame)
}

/// Output channels `start..start + len` of a 1×1 convolution (a head) applied to the pixels:
/// `x [B, C_in, H, W]` as rows `[B·H·W, C_in]` times the weight's rows `[C_in, len]` plus their
/// bias, one `Gemm` → `[B·H·W, len]`. A head of a log-prior per grid point then meets the
/// pixel-major evidence without either being transposed (the widest tensors of the graph: the
/// U-Net's trunk has a few channels, the evidence tens to hundreds), and each part of the head
/// comes out on its own (no split of a wide tensor).
fn head_rows(g: &mut Graph, layer: &Conv2d, x_rows: &str, start: usize, len: usize) -> Result<String> {
    let (ci, w, bias) = head_part(layer, start, len)?;
    let w = g.weight("head_w_rows", &[ci, len], &w);
    let bias = g.weight("head_b_rows", &[len], &bias);
    Ok(g.op("Gemm", &[x_rows, &w, &bias]))
}

/// [`head_rows`] added onto `base` `[N, len]` in the same `Gemm`: the trunk's rows with a
/// column of ones times the weight's rows with the bias under them, plus `base` — the
/// log-prior onto the log-likelihood without a pass of its own over the widest tensor.
fn head_rows_onto(g: &mut Graph, layer: &Conv2d, x_rows: &str, start: usize, len: usize, base: &str) -> Result<String> {
    let (ci, mut wb, bias) = head_part(layer, start, len)?;
    wb.extend(bias); // [C_in + 1, len]: the weight's rows, then the bias
    let wb = g.weight("head_wb_rows", &[ci + 1, len], &wb);
    let ones = ones_column(g, x_rows);
    let x1 = g.node("Concat", &[x_rows, &ones], &[Attr::Int("axis", 1)]); // [N, C_in + 1]
    Ok(g.op("Gemm", &[&x1, &wb, base]))
}

/// Output channels `start..start + len` of a 1×1 convolution as `(C_in, weight [C_in, len],
/// bias [len])` (zeros without a bias).
fn head_part(layer: &Conv2d, start: usize, len: usize) -> Result<(usize, Vec<f32>, Vec<f32>)> {
    let [co, ci, kh, kw] = layer.weight.dims();
    if (kh, kw) != (1, 1) || start + len > co {
        return Err(InferError::InvalidParam {
            field: "head",
            got: format!("a {kh}×{kw} convolution to {co} channels"),
            expected: format!("a 1×1 convolution to at least {} channels", start + len),
        });
    }
    let w = values(layer.weight.val().into_data())?; // [C_out, C_in]
    let rows: Vec<f32> = (0..ci * len).map(|q| w[(start + q % len) * ci + q / len]).collect();
    let bias = match &layer.bias {
        Some(b) => values(b.val().into_data())?[start..start + len].to_vec(),
        None => vec![0.0; len],
    };
    Ok((ci, rows, bias))
}

/// A column of ones `[N, 1]` beside the rows `[N, C]`.
fn ones_column(g: &mut Graph, rows: &str) -> String {
    let shape = g.op("Shape", &[rows]);
    let (s0, s1) = (g.ints("s0", &[0]), g.ints("s1", &[1]));
    let n = g.node("Slice", &[&shape, &s0, &s1], &[]);
    let column = g.node("Concat", &[&n, &s1], &[Attr::Int("axis", 0)]); // [N, 1]
    let one = g.weight("one_f", &[1, 1], &[1.0]);
    g.op("Expand", &[&one, &column])
}

/// The U-Net trunk's output `[B, C, H, W]` as pixel rows `[B·H·W, C]`.
fn trunk_rows(g: &mut Graph, trunk: &str, c: usize) -> String {
    let t = g.node("Transpose", &[trunk], &[Attr::Ints("perm", &[0, 2, 3, 1])]);
    let rows = g.ints("rows_shape", &[-1, c as i64]);
    g.op("Reshape", &[&t, &rows])
}

/// The export options of a decoder on a fit's evidence (`what`): its runtime computes the
/// evidence from the taps, so the sensor matrix is never a graph input, and a calibration is
/// the runtime's too (its matrix the metadata's, its dark and gain maps in
/// [`OnnxMeta::correction`]).
fn evidence_options(meta: &OnnxMeta, opts: ExportOptions<'_>, what: &str) -> Result<()> {
    if opts.matrix_input {
        return Err(InferError::InvalidParam {
            field: "export",
            got: "--matrix-input".into(),
            expected: format!(
                "no matrix input for {what} (its runtime computes the evidence from the taps with the model's sensor; build a calibration in with --calibration)"
            ),
        });
    }
    if let Some(cal) = opts.calibration {
        let want = (meta.block.0 * meta.block.1, meta.taps, meta.bins);
        if cal.meta.taps != meta.taps || cal.matrix.a().dim() != want {
            return Err(InferError::InvalidParam {
                field: "calibration",
                got: format!("A {:?}", cal.matrix.a().dim()),
                expected: format!("the run's sensor [N, M, T] = {want:?}"),
            });
        }
    }
    Ok(())
}

/// The U-Net on the range fit's evidence ([`tcsense_models::UnetInput::Costs`]) as a whole
/// model: the evidence in, the fit's log-likelihood at the learned temperature plus the
/// learned log-prior, the posterior's cyclic mode refined by a parabola, its range in metres,
/// and the first return's confidence. The evidence (the templates' costs) and the refinement
/// in the tap domain with the second return ([`tcsense_fits::depth::RangeTemplates::ranges`])
/// are the runtime's.
///
/// # Shapes
/// - `evidence [B, H, W, F]`, `log_likelihood [B, H, W, C]` (pixel-major) → `mode_range [B, 1, H, W]` (m), `first_confidence [B, 1, H, W]`
fn unet_on_evidence(net: &Unet, meta: &OnnxMeta, opts: ExportOptions<'_>) -> Result<Vec<u8>> {
    evidence_options(meta, opts, "a U-Net on the range fit's evidence")?;
    let (c, pool) = net.grid();
    let f = tcsense_fits::depth::range_feature_channels(c, pool);
    let mut g = Graph::new(tcsense_models::runs::network_names::UNET);
    let frame = [Dim::Named("batch"), Dim::Fixed(1), Dim::Named("height"), Dim::Named("width")];
    let pixels = |c: usize| [Dim::Named("batch"), Dim::Named("height"), Dim::Named("width"), Dim::Fixed(c)];
    let features = g.input(EVIDENCE_INPUT, &pixels(f));
    let skip = g.input(LOG_LIKELIHOOD_INPUT, &pixels(tcsense_fits::depth::SCALES * c));
    // the trunk channel-major, the posterior on the pixels as rows (as the evidence comes)
    let (skip, frame_shape) = pixel_rows(&mut g, &skip, tcsense_fits::depth::SCALES * c); // [N, S·C]
    let features = g.node("Transpose", &[&features], &[Attr::Ints("perm", &[0, 3, 1, 2])]);
    let trunk = unet_trunk(&mut g, net.down(), net.up(), &features)?;
    let trunk = trunk_rows(&mut g, &trunk, net.head().weight.dims()[1]); // [N, C_0]
    let bound = g.scalar("prior_bound", tcsense_models::depth_evidence::PRIOR_BOUND as f32);
    let prior = head_rows(&mut g, net.head(), &trunk, 0, c)?; // [N, C]
    let prior = g.op("Div", &[&prior, &bound]);
    let prior = g.op("Tanh", &[&prior]);
    let prior = g.op("Mul", &[&prior, &bound]);
    let logit = head_rows(&mut g, net.head(), &trunk, c, 1)?;
    let logit = g.op("Reshape", &[&logit, &frame_shape]);
    // the fit's window's log-likelihood plus the wider windows' at the learned weights
    let wide = tcsense_fits::depth::SCALES - 1;
    let o_s = head_rows(&mut g, net.head(), &trunk, c + 1, wide)?;
    let likelihood = windowed_likelihood(&mut g, &o_s, &skip, c, wide);
    let logits = g.op("Add", &[&likelihood, &prior]);
    let u = posterior_mode(&mut g, &logits, c, true);
    let u = g.op("Reshape", &[&u, &frame_shape]);
    // the range of candidate u: (u + ½·os)/C · r_max, within the cycle
    let (half_os, per) = (
        g.scalar("half_oversample", 0.5 * net.grid_oversample() as f32),
        g.scalar("metres_per_candidate", (net.range_m() / c as f64) as f32),
    );
    let r = g.op("Add", &[&u, &half_os]);
    let r = g.op("Mul", &[&r, &per]);
    let period = g.scalar("range_m", net.range_m() as f32);
    let r = g.node("Mod", &[&r, &period], &[Attr::Int("fmod", 1)]);
    let conf = g.op("Sigmoid", &[&logit]);
    g.output(&r, MODE_RANGE_OUTPUT, &frame);
    g.output(&conf, FIRST_CONFIDENCE_OUTPUT, &frame);
    let doc = format!(
        "tcsense U-Net on the range fit's evidence ({c} candidate ranges over {:.3} m, {} levels): evidence [B, H, W, {f}], log_likelihood [B, H, W, {}] (the windows' log-likelihoods, window-major) -> mode_range (m) [B, 1, H, W], first_confidence [B, 1, H, W]; the runtime computes the evidence from the taps and refines the first return with the fit's second beside it",
        net.range_m(),
        net.down().len(),
        tcsense_fits::depth::SCALES * c
    );
    model_bytes(g, &doc, meta)
}

/// The fit's window's log-likelihood plus the `wide` wider windows' at the weights the head
/// sets pixel by pixel, `L_0 + Σ_s e^{clip(6·o_s − 6)}·L_s` (as burn's posteriors of the networks
/// on a fit's evidence): `o_s` are the head's channels after its `points` log-prior channels
/// and its confidence logit. On the pixels as rows.
///
/// # Shapes
/// - `o_s`: `[N, S]`, `skip`: `[N, (1 + S)·G]` (window-major) → `[N, G]`
fn windowed_likelihood(g: &mut Graph, o_s: &str, skip: &str, points: usize, wide: usize) -> String {
    let (gain, offset) = (
        g.scalar("window_gain", tcsense_models::depth_evidence::WIDER_GAIN as f32),
        g.scalar("window_offset", tcsense_models::depth_evidence::WIDER_OFFSET as f32),
    );
    let o_s = g.op("Mul", &[o_s, &gain]);
    let o_s = g.op("Add", &[&o_s, &offset]);
    let [lo, hi] = tcsense_models::depth_evidence::TEMPERATURE_RANGE;
    let (lo, hi) = (g.scalar("log_weight_lo", lo as f32), g.scalar("log_weight_hi", hi as f32));
    let o_s = g.op("Clip", &[&o_s, &lo, &hi]);
    let weights = g.op("Exp", &[&o_s]);
    // every window at its weight, the fit's at 1, one small product a pixel: [N, 1, 1 + S]
    // times [N, 1 + S, G] (the log-likelihoods read in place, never sliced)
    let ones = ones_column(g, &weights);
    let weights = g.node("Concat", &[&ones, &weights], &[Attr::Int("axis", 1)]); // [N, 1 + S]
    let (wshape, vshape, out) = (
        g.ints("weights_shape", &[-1, 1, 1 + wide as i64]),
        g.ints("volume_shape", &[-1, 1 + wide as i64, points as i64]),
        g.ints("likelihood_shape", &[-1, points as i64]),
    );
    let weights = g.op("Reshape", &[&weights, &wshape]);
    let volume = g.op("Reshape", &[skip, &vshape]);
    let summed = g.op("MatMul", &[&weights, &volume]); // [N, 1, G]
    g.op("Reshape", &[&summed, &out]) // [N, G]
}

/// The lifetime decoder on the fit's evidence ([`tcsense_models::LifetimeInput::Costs`]) as a
/// whole model: the evidence in, the U-Net's log-prior added to the fit's log-likelihood, the
/// posterior's mode refined by a parabola (ArgMax, GatherElements), the lifetime in seconds.
/// The evidence itself (the instrument, the templates' costs) is computed by the runtime.
///
/// # Shapes
/// - `evidence [B, H, W, F]`, `log_likelihood [B, H, W, G]` (pixel-major) → `lifetime [B, 4, H, W]`, `confidence [B, 1, H, W]`
fn lifetime_on_evidence(net: &LifetimeNet, meta: &OnnxMeta, opts: ExportOptions<'_>) -> Result<Vec<u8>> {
    evidence_options(meta, opts, "a lifetime decoder on the fit's evidence")?;
    let (points, pool) = net.grid_points();
    let wide = net.windows().len();
    let f = tcsense_fits::lifetime_taps::evidence::feature_channels_with(points, pool, wide);
    let mut g = Graph::new(tcsense_models::runs::network_names::LIFETIME);
    let frame = |c: usize| [Dim::Named("batch"), Dim::Fixed(c), Dim::Named("height"), Dim::Named("width")];
    let pixels = |c: usize| [Dim::Named("batch"), Dim::Named("height"), Dim::Named("width"), Dim::Fixed(c)];
    // the evidence comes pixel-major, as the runtime computes it
    let features = g.input(EVIDENCE_INPUT, &pixels(f));
    let skip = g.input(LOG_LIKELIHOOD_INPUT, &pixels((1 + wide) * points));
    // the trunk channel-major, the posterior on the pixels as rows (as the evidence comes)
    let (skip, frame_shape) = pixel_rows(&mut g, &skip, (1 + wide) * points); // [N, (1 + S)·G]
    let features = g.node("Transpose", &[&features], &[Attr::Ints("perm", &[0, 3, 1, 2])]);
    let trunk = unet_trunk(&mut g, net.down(), net.up(), &features)?;
    let trunk = trunk_rows(&mut g, &trunk, net.head().weight.dims()[1]); // [N, C_0]
    let logit = head_rows(&mut g, net.head(), &trunk, points, 1)?;
    let logit = g.op("Reshape", &[&logit, &frame_shape]);
    let likelihood = if wide == 0 {
        skip
    } else {
        // as burn's LifetimeNet::posterior
        let o_s = head_rows(&mut g, net.head(), &trunk, points + 1, wide)?;
        windowed_likelihood(&mut g, &o_s, &skip, points, wide)
    };
    let likelihood = if net.tempered() {
        // as burn's LifetimeNet::posterior: e^{clip(gain·o_t)} · L, one weight a pixel row
        let o_t = head_rows(&mut g, net.head(), &trunk, points + 1 + wide, 1)?; // [N, 1]
        let gain = g.scalar("temper_gain", tcsense_models::lifetime::TEMPER_GAIN as f32);
        let [lo, hi] = tcsense_models::lifetime::TEMPER_RANGE;
        let (lo, hi) = (g.scalar("temper_lo", lo as f32), g.scalar("temper_hi", hi as f32));
        let o_t = g.op("Mul", &[&o_t, &gain]);
        let o_t = g.op("Clip", &[&o_t, &lo, &hi]);
        let weight = g.op("Exp", &[&o_t]);
        g.op("Mul", &[&likelihood, &weight])
    } else {
        likelihood
    };
    let logits = head_rows_onto(&mut g, net.head(), &trunk, 0, points, &likelihood)?; // [N, G]
    let u = posterior_mode(&mut g, &logits, points, false);
    let u = g.op("Reshape", &[&u, &frame_shape]);
    let nil = g.scalar("nil", 0.0);
    let (l0_ns, step) = net.log_grid_ns();
    let (lt0, st) = (g.scalar("log_tau_0_s", (l0_ns + 1e-9f64.ln()) as f32), g.scalar("log_tau_step", step as f32));
    let a = g.op("Mul", &[&u, &st]);
    let a = g.op("Add", &[&a, &lt0]);
    let tau = g.op("Exp", &[&a]);
    let ones = g.op("Mul", &[&tau, &nil]);
    let unit = g.scalar("unit", 1.0);
    let ones = g.op("Add", &[&ones, &unit]);
    let lifetime = g.node("Concat", &[&tau, &tau, &tau, &ones], &[Attr::Int("axis", 1)]);
    let conf = g.op("Sigmoid", &[&logit]);
    g.output(&lifetime, "lifetime", &frame(4));
    g.output(&conf, "confidence", &frame(1));
    let doc = format!(
        "tcsense lifetime decoder on the fit's evidence ({points} lifetimes {}-{} ns, {} levels{}{}): evidence [B, H, W, {f}], log_likelihood [B, H, W, {}]{} -> lifetime (s) [B, 4, H, W], confidence [B, 1, H, W]; the runtime computes the evidence from the taps",
        net.tau_range_ns()[0],
        net.tau_range_ns()[1],
        net.down().len(),
        if wide == 0 { String::new() } else { format!(", wider windows {:?}", net.windows()) },
        if net.tempered() { ", its log-likelihood at a learned temperature" } else { "" },
        (1 + wide) * points,
        if wide == 0 { "" } else { " (the windows' log-likelihoods, window-major)" }
    );
    model_bytes(g, &doc, meta)
}

fn unet(g: &mut Graph, net: &Unet, sensor: &SensorGraph, y: &str) -> Result<(String, String)> {
    let x0 = match net.input_kind() {
        tcsense_models::UnetInput::Matched => sensor.matched(g, y),
        tcsense_models::UnetInput::Backprojection => sensor.adjoint(g, y),
        tcsense_models::UnetInput::Costs => {
            return Err(InferError::InvalidParam {
                field: "model.input",
                got: "Costs (the U-Net on the range fit's evidence)".into(),
                expected: "a U-Net on Aᵀy or the matched filters: the range fit's evidence has no ONNX graph yet; decode with `tcsense reconstruct --run`".into(),
            })
        }
    };
    // per-pixel normalisation: x₀ / (‖x₀‖₂ + f·mean‖x₀‖₂ + 10⁻³⁰), f = Unet::norm_floor()
    let norm = g.node("ReduceL2", &[&x0], &[Attr::Ints("axes", &[1]), Attr::Int("keepdims", 1)]);
    let mean = g.node("ReduceMean", &[&norm], &[Attr::Ints("axes", &[2, 3]), Attr::Int("keepdims", 1)]);
    let floor = g.scalar("norm_floor", net.norm_floor() as f32);
    let mf = g.node("Mul", &[&mean, &floor], &[]);
    let den = g.node("Add", &[&norm, &mf], &[]);
    let tiny = g.scalar("tiny", 1e-30);
    let den = g.node("Add", &[&den, &tiny], &[]);
    let mut z = g.node("Div", &[&x0, &den], &[]);
    z = unet_trunk(g, net.down(), net.up(), &z)?;
    let out = conv(g, net.head(), &z)?; // [B, 2K, H, W] or [B, K·T + K, H, W]
    let k = net.returns() as i64;
    if net.head_kind() == tcsense_models::UnetHead::ScoreVolume {
        // soft-argmax of the scores [B, K, T, H, W] over the bin centres within
        // SOFT_ARGMAX_HALF_WIDTH bins of the most probable one (as Unet::local_soft_argmax)
        let centres = net.bin_centres_m();
        let t = centres.len() as i64;
        let split = g.ints("split", &[k * t, k]);
        let parts = g.node_multi("Split", &[&out, &split], &[Attr::Int("axis", 1)], 2);
        let shape5 = g.ints("score_shape", &[0, k, t, -1]);
        let flat = g.op("Reshape", &[&parts[0], &shape5]); // [B, K, T, H·W]
        let p = g.node("Softmax", &[&flat], &[Attr::Int("axis", 2)]);
        let peak = g.node("ArgMax", &[&p], &[Attr::Int("axis", 2), Attr::Int("keepdims", 1)]); // [B, K, 1, H·W]
        let peak = g.node("Cast", &[&peak], &[Attr::Int("to", onnx_protobuf::tensor_proto::DataType::FLOAT as i64)]);
        let index: Vec<f32> = (0..centres.len()).map(|j| j as f32).collect();
        let bins = g.weight("bin_index", &[1, 1, centres.len(), 1], &index);
        let offset = g.op("Sub", &[&bins, &peak]);
        let offset = g.node("Abs", &[&offset], &[]);
        let half = g.scalar("soft_argmax_half_width", tcsense_models::unet::SOFT_ARGMAX_HALF_WIDTH as f32);
        let near = g.node("LessOrEqual", &[&offset, &half], &[]);
        let near = g.node("Cast", &[&near], &[Attr::Int("to", onnx_protobuf::tensor_proto::DataType::FLOAT as i64)]);
        let p = g.op("Mul", &[&p, &near]);
        let c = g.weight("bin_centres_m", &[1, 1, centres.len(), 1], &centres);
        let pc = g.op("Mul", &[&p, &c]);
        let axis2 = g.ints("axis2", &[2]);
        let num = g.node("ReduceSum", &[&pc, &axis2], &[Attr::Int("keepdims", 0)]); // [B, K, H·W]
        let mass = g.node("ReduceSum", &[&p, &axis2], &[Attr::Int("keepdims", 0)]);
        let d = g.node("Div", &[&num, &mass], &[]);
        let yshape = g.op("Shape", &[y]);
        let (from, to) = (g.ints("from2", &[2]), g.ints("to4", &[4]));
        let hw = g.node("Slice", &[&yshape, &from, &to], &[]);
        let bk = g.ints("bk", &[0, k]);
        let out_shape = g.node("Concat", &[&bk, &hw], &[Attr::Int("axis", 0)]);
        let depth = g.op("Reshape", &[&d, &out_shape]); // [B, K, H, W]
        let conf = g.node("Sigmoid", &[&parts[1]], &[]);
        return Ok((depth, conf));
    }
    let split = g.ints("split", &[k, k]);
    let parts = g.node_multi("Split", &[&out, &split], &[Attr::Int("axis", 1)], 2);
    let sd = g.node("Sigmoid", &[&parts[0]], &[]);
    let range = g.scalar("range_m", net.range_m() as f32);
    let depth = g.node("Mul", &[&sd, &range], &[]);
    let conf = g.node("Sigmoid", &[&parts[1]], &[]);
    Ok((depth, conf))
}
