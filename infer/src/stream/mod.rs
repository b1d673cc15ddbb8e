//! Streaming deployment inference: frames from a file or a directory, through an exported
//! model, to products on disk, with bounded memory whatever the stack length.
//!
//! ```text
//! reader thread ──(2 frames)──▶ inference (ONNX Runtime) ──(2 results)──▶ products + writer thread
//! ```
//!
//! Inputs: one frame `.npy [M, H, W]`, a stack `.npy [F, M, H, W]` (read frame by frame from
//! disk, any real dtype, C order), or a directory of frames: `.npy [M, H, W]` files and 16-bit
//! (or 8-bit) grayscale PNGs holding the `M` tap images side by side (`[H, M·W]`, tap `m` in
//! columns `m·W … (m+1)·W − 1`, as a sensor dumps them), taken in file-name order.
//!
//! Outputs in `OUT/` (stacks `[F, …]`, or without `F` for a single `[M, H, W]` frame), each
//! streamed into a temporary file and renamed at the end, so an error or Ctrl-C leaves none:
//! `cube.npy [F, T, H, W]`, `depth.npy [F, K, H, W]` (m, NaN where no return),
//! `confidence.npy` (depth models) or `peaks.npy` (peak amplitudes, cube models),
//! `lifetime.npy [F, H, W]` (s; the amplitude-weighted mean — a cube's by the reconvolution
//! fit, the lifetime decoder's own), `intensity.npy [F, H, W]`, `phasor.npy [F, 2, H, W]`
//! (IRF-referenced `g, s`) and `ply/frame_NNNNN.ply`.
//!
//! What `reconstruct` applies after a network, the stream applies too: a depth model's ranges
//! refined in the tap domain ([`Products::range_fit`], on by default). The fits to the taps
//! replace a product where asked for, through the model's codes and sensor (its metadata):
//! lifetimes by [`tcsense_fits::lifetime_taps::LifetimeTemplates`] ([`Products::lifetime_fit`], the onset and
//! IRF width estimated once on the first frame) and depth by
//! [`tcsense_fits::depth::RangeTemplates`] ([`Products::depth_fit`]); the network is
//! then not run unless another product needs it.
//!
//! The parts: [`read`] (the frame sources), [`policy`] (what a model gives and what to write),
//! [`write`] (stacks written frame by frame, the products of a frame), and here the threads
//! that connect them.

mod policy;
mod read;
mod write;

pub use policy::{phasor_of_components, ModelKind, Products};
pub use read::{read_png_taps, FrameSource};
pub use write::NpyStackWriter;
use write::{write_frame, Writers};

use ndarray::{Array3, Array4, ArrayView3, Axis};
use std::fs::File;
use std::io::{BufWriter, Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::sync_channel;
use std::time::Instant;

use tcsense_sensor::npy::{f32_header, parse_header, read_npy, NpyHeader};

use crate::products::{depth_map, write_ply, PeakOptions};
use crate::runtime::{FrameEvidence, OnnxModel};
use crate::{InferError, Result};
use tcsense_fits::depth::{DepthFitOptions, RangeTemplates};
use tcsense_fits::evidence::EvidenceBuffers;
use tcsense_fits::lifetime_taps::{estimate_instrument, instrument_frames, Instrument, LifetimeTemplates, TapFit, TapFitOptions};
use tcsense_fits::range::{refine_ranges, RangeFitOptions};
use tcsense_models::net::mask_depth;

fn file_err(path: &Path, msg: impl ToString) -> InferError {
    InferError::File { path: path.to_path_buf(), msg: msg.to_string() }
}

/// A refusal of a frame's values as an error naming the frame's file.
fn in_file(path: &Path, e: InferError) -> InferError {
    match e {
        InferError::InvalidParam { field, got, expected } => file_err(path, format!("{field}: got {got}, expected {expected}")),
        e => e,
    }
}

/// What a streamed run did.
#[derive(Debug, Clone)]
pub struct StreamReport {
    pub frames: usize,
    pub seconds: f64,
    /// Seconds inside ONNX Runtime.
    pub infer_seconds: f64,
    pub written: Vec<PathBuf>,
    /// A lifetime stream's instrument (fitted or with its given onset) and the frames it was
    /// searched on (summed).
    pub instrument: Option<(Instrument, usize)>,
}

/// Stream every frame of `source` through `model` into `out`, calling `on_frame(done, total)`
/// after each; stops with [`InferError::Cancelled`] when `cancel` is set (writing nothing).
///
/// `out` is written whole: the products go into a temporary sibling that replaces `out` once
/// every frame is done, so an earlier run's products (a longer run's point clouds, a product
/// not asked for now) never remain beside the new ones, and a refusal, an error or an
/// interruption leaves `out` as it was. A directory holding other files is refused.
pub fn run_stream(
    model: &mut OnnxModel,
    source: FrameSource,
    out: &Path,
    products: &Products,
    cancel: &AtomicBool,
    on_frame: &(dyn Fn(usize, usize) + Sync),
) -> Result<StreamReport> {
    tcsense_sensor::output::replace_dir(out, &is_stream_output, |tmp| {
        let mut report = stream_into(model, source, tmp, products, cancel, on_frame)?;
        // the paths the products will have once the temporary directory is renamed
        for p in &mut report.written {
            if let Ok(rel) = p.strip_prefix(tmp) {
                *p = out.join(rel);
            }
        }
        Ok(report)
    })
}

/// The frame a stream's instrument is searched on, and how many frames it sums: the first
/// (`first`, `[M, H, W]`), or, when its pixels are too dim on their own, its sum with those
/// of the next frames up to the
/// [`instrument_frames`]-th that show the same scene ([`same_scene`]: a recording, not a stack
/// of other scenes, whose lifetimes would mix), each as `correct` gives it. A frame of another
/// shape is refused with its file named.
fn instrument_reference(
    source: &mut FrameSource,
    first: &Array3<f32>,
    taps: usize,
    sensor: &tcsense_sensor::MeasurementMatrix,
    opts: &TapFitOptions,
    correct: impl Fn(ndarray::ArrayView3<'_, f32>) -> Array3<f32>,
) -> Result<(Array3<f32>, usize)> {
    // (each frame compared as corrected: a calibration's gain map is no part of the scene)
    let reference = correct(first.view());
    let frames = instrument_frames(&reference.view(), sensor, opts).min(source.len());
    if frames <= 1 {
        return Ok((reference, 1));
    }
    let mut sum = reference.clone();
    let mut summed = 1;
    for i in 1..frames {
        let (y, path) = source.read(i, taps)?;
        if y.dim() != first.dim() {
            return Err(file_err(&path, format!("frame of shape {:?}; the first frame was {:?}", y.shape(), first.shape())));
        }
        let y = correct(y.view());
        if same_scene(&reference.view(), &y.view()) {
            sum += &y;
            summed += 1;
        }
    }
    Ok((sum, summed))
}

/// Side of the blocks whose intensities [`same_scene`] compares (their shot noise averaged).
const SCENE_BLOCK: usize = 8;

/// Least correlation of two frames' block intensities for [`same_scene`]: two frames of one
/// scene correlate by `S/(S + N)` (the blocks' scene variance `S`, their noise's `N`), so ½
/// takes the frames whose scene stands above their noise; frames of unrelated scenes correlate
/// by about `±1/√blocks` (±0.13 for 64×64 pixels).
const SAME_SCENE: f64 = 0.5;

/// Whether frame `y` shows the scene of frame `a` (both `[M, H, W]`): the correlation of their
/// intensities (the taps' sum) over blocks of [`SCENE_BLOCK`] pixels is at least [`SAME_SCENE`].
/// A frame without contrast (or of one block) is not taken for the same scene.
fn same_scene(a: &ArrayView3<'_, f32>, y: &ArrayView3<'_, f32>) -> bool {
    let (_, h, w) = a.dim();
    let (bh, bw) = (h.div_ceil(SCENE_BLOCK), w.div_ceil(SCENE_BLOCK));
    let blocks = |f: &ArrayView3<'_, f32>| -> Vec<f64> {
        let mut b = vec![0f64; bh * bw];
        for tap in f.outer_iter() {
            for ((i, j), &v) in tap.indexed_iter() {
                b[(i / SCENE_BLOCK) * bw + j / SCENE_BLOCK] += v as f64;
            }
        }
        b
    };
    let (p, q) = (blocks(a), blocks(y));
    let n = p.len() as f64;
    let (mp, mq) = (p.iter().sum::<f64>() / n, q.iter().sum::<f64>() / n);
    let (mut c, mut vp, mut vq) = (0.0, 0.0, 0.0);
    for (x, z) in p.iter().zip(&q) {
        c += (x - mp) * (z - mq);
        vp += (x - mp) * (x - mp);
        vq += (z - mq) * (z - mq);
    }
    vp > 0.0 && vq > 0.0 && c / (vp * vq).sqrt() >= SAME_SCENE
}

/// Whether `name` is a file or folder [`run_stream`] writes into its output directory.
pub fn is_stream_output(name: &str) -> bool {
    matches!(name, "cube.npy" | "depth.npy" | "peaks.npy" | "confidence.npy" | "lifetime.npy" | "intensity.npy" | "phasor.npy" | "ply")
}

/// [`run_stream`] into the directory `out` (fresh and empty).
fn stream_into(
    model: &mut OnnxModel,
    mut source: FrameSource,
    out: &Path,
    products: &Products,
    cancel: &AtomicBool,
    on_frame: &(dyn Fn(usize, usize) + Sync),
) -> Result<StreamReport> {
    let frames = source.len();
    let taps = model.meta.taps;
    let (first, first_path) = source.read(0, taps)?;
    let (m, h, w) = first.dim();
    model.check(&first.view().insert_axis(Axis(0)), &first_path.display().to_string())?;
    let kind = ModelKind::of(&model.meta.decoder);
    // a frame's pixels with a tap at the clip level (as read), [H, W]; None: none
    let clip = products.clip_level;
    let clipped =
        move |a: &Array3<f32>| clip.map(|level| tcsense_sensor::measure::at_clip_level(&a.view(), level)).filter(|u| u.iter().any(|&v| v));
    let cube_model = kind == ModelKind::Cube;
    let (t, k) = (
        model.meta.bins,
        match &products.depth_fit {
            Some(f) => f.returns,
            None if cube_model => products.returns,
            None => model.meta.returns,
        },
    );
    let lead: Vec<usize> = if source.single() { vec![] } else { vec![frames] };
    let shape = |rest: &[usize]| -> Vec<usize> { lead.iter().chain(rest).copied().collect() };
    let mut writers = Writers {
        cube: if products.cube { Some(NpyStackWriter::create(&out.join("cube.npy"), &shape(&[t, h, w]))?) } else { None },
        depth: if products.depth { Some(NpyStackWriter::create(&out.join("depth.npy"), &shape(&[k, h, w]))?) } else { None },
        second: match (cube_model, products.peaks || (!cube_model && products.depth)) {
            (true, true) => Some(NpyStackWriter::create(&out.join("peaks.npy"), &shape(&[k, h, w]))?),
            (false, true) => Some(NpyStackWriter::create(&out.join("confidence.npy"), &shape(&[k, h, w]))?),
            _ => None,
        },
        lifetime: if products.lifetime { Some(NpyStackWriter::create(&out.join("lifetime.npy"), &shape(&[h, w]))?) } else { None },
        intensity: if products.intensity { Some(NpyStackWriter::create(&out.join("intensity.npy"), &shape(&[h, w]))?) } else { None },
        phasor: if products.phasor { Some(NpyStackWriter::create(&out.join("phasor.npy"), &shape(&[2, h, w]))?) } else { None },
    };
    if products.ply {
        std::fs::create_dir_all(out.join("ply")).map_err(|e| file_err(out, e))?;
    }
    // what this stream writes (not whatever an earlier run left in `out`)
    let mut written: Vec<PathBuf> =
        [&writers.cube, &writers.depth, &writers.second, &writers.lifetime, &writers.intensity, &writers.phasor]
            .into_iter()
            .flatten()
            .map(|w| w.path.clone())
            .collect();
    if products.ply {
        written.push(out.join("ply"));
    }
    let bin_s = model.meta.bin_s;
    let peak_opts = PeakOptions { max_peaks: k, ..Default::default() };
    let t0 = Instant::now();
    let mut found = None;
    // a lifetime network on the fit's evidence: its instrument from the first frame (or the
    // first few, summed, when it is dim), once
    if let Some(e) = model.meta.evidence.clone().filter(|_| products.need_model()) {
        let opts = TapFitOptions { onset_s: products.onset_s, ..e.fit_options() };
        opts.validate().map_err(|msg| InferError::Settings { what: "--onset-ns", msg })?;
        let (reference, summed) =
            instrument_reference(&mut source, &first, taps, &model.sensor, &opts, |y| model.corrected(y).into_owned())?;
        let instrument = estimate_instrument(&reference.view(), &model.sensor, &opts);
        model.set_instrument(instrument);
        found = Some((instrument, summed));
    }
    // the fits to the taps need corrected tap images, and a built-in correction is in the graph
    let uncalibrated = |field: &'static str| -> Result<()> {
        match model.meta.calibration {
            Some(_) => Err(InferError::InvalidParam {
                field,
                got: format!("{} (a calibration built into the graph)", model.path().display()),
                expected: "a model exported without --calibration: the fit to the taps needs corrected tap images, and a calibrated model corrects them inside itself".into(),
            }),
            None => Ok(()),
        }
    };
    // the fit to the taps: the instrument from the first frame (or the first few, summed, when
    // it is dim; or its given onset), once
    let templates = match &products.lifetime_fit {
        Some(opts) => {
            uncalibrated("--lifetime-fit")?;
            opts.validate().map_err(|msg| InferError::Settings { what: "--lifetime-fit", msg })?;
            let (reference, summed) = instrument_reference(&mut source, &first, taps, &model.sensor, opts, |y| y.to_owned())?;
            let instrument = estimate_instrument(&reference.view(), &model.sensor, opts);
            found = Some((instrument, summed));
            Some(LifetimeTemplates::new(&model.sensor, instrument, opts))
        }
        None => None,
    };
    let templates = templates.as_ref();
    let need_model = products.need_model();
    let range_fit = products
        .range_fit
        .as_ref()
        .filter(|_| kind == ModelKind::Depth && (products.depth || products.ply) && products.depth_fit.is_none())
        // (a U-Net on the range fit's evidence is refined in the tap domain already, by the
        // runtime or in its graph from the taps)
        .filter(|_| model.meta.range_evidence.is_none() && !model.meta.refined_in_graph);
    let mut range_templates = match &products.depth_fit {
        Some(opts) => {
            if kind == ModelKind::Lifetime {
                return Err(InferError::InvalidParam {
                    field: "--depth-fit",
                    got: model.meta.decoder.clone(),
                    expected: "a depth or cube model (the fit gives depth)".into(),
                });
            }
            uncalibrated("--depth-fit")?;
            if products.peaks {
                return Err(InferError::InvalidParam {
                    field: "--products",
                    got: "peaks with --depth-fit".into(),
                    expected: "depth, ply (the fit gives ranges, not the cube's peaks)".into(),
                });
            }
            opts.validate().map_err(|msg| InferError::Settings { what: "--depth-fit", msg })?;
            Some(RangeTemplates::new(&model.sensor, opts))
        }
        None => None,
    };
    let depth_fit = range_templates.is_some();
    let sensor = &model.sensor.clone();
    // a decoder on a fit's evidence runs as a pipeline: the next frame's evidence and the last
    // frame's refinement on the CPU while ONNX Runtime decodes the frame between
    let (stage, refine) = match need_model.then(|| model.evidence_stages()).flatten() {
        Some((s, r)) => (Some(s), Some(r)),
        None => (None, None),
    };
    let stage = stage.as_ref();
    let mut infer_seconds = 0.0;
    // (a frame, its file, its evidence and its pixels with a tap at the clip level, [H, W])
    type Frame = (usize, Array3<f32>, PathBuf, Option<FrameEvidence>, Option<ndarray::Array2<bool>>);
    let result: Result<()> = std::thread::scope(|scope| {
        let (ftx, frx) = sync_channel::<Result<Frame>>(2);
        let (otx, orx) =
            sync_channel::<(usize, Vec<Array4<f32>>, Option<Array3<f32>>, Option<FrameEvidence>, Option<ndarray::Array2<bool>>)>(2);
        // reader (into the evidence stage when there is one)
        let (rtx, rrx) = sync_channel::<Result<Frame>>(2);
        // the graph's inputs back to the evidence stage once the graph has run: the next
        // frames' evidence is written into them (no fresh memory a frame)
        let (btx, brx) = sync_channel::<EvidenceBuffers>(4);
        let to_next = if stage.is_some() { rtx } else { ftx.clone() };
        let reader = scope.spawn(move || {
            let unread0 = clipped(&first);
            if to_next.send(Ok((0, first, first_path, None, unread0))).is_err() {
                return;
            }
            for i in 1..frames {
                if cancel.load(Ordering::Relaxed) {
                    return;
                }
                let r = source.read(i, taps).map(|(a, p)| {
                    let unread = clipped(&a);
                    (i, a, p, None, unread)
                });
                let stop = r.is_err();
                if to_next.send(r).is_err() || stop {
                    return;
                }
            }
        });
        // the evidence stage: each frame checked, then its evidence
        let evidence = stage.map(|stage| {
            scope.spawn(move || {
                for msg in rrx {
                    if cancel.load(Ordering::Relaxed) {
                        return;
                    }
                    let r = msg.and_then(|(i, mut y, path, _, unread)| {
                        if y.dim() != (m, h, w) {
                            return Err(file_err(&path, format!("frame of shape {:?}; the first frame was [{m}, {h}, {w}]", y.shape())));
                        }
                        let y4 = y.view().insert_axis(Axis(0));
                        stage.check(&y4, &path.display().to_string()).map_err(|e| in_file(&path, e))?;
                        stage.correct(&mut y);
                        let ev = stage.evidence(&y.view(), brx.try_recv().unwrap_or_default());
                        Ok((i, y, path, Some(ev), unread))
                    });
                    let stop = r.is_err();
                    if ftx.send(r).is_err() || stop {
                        return;
                    }
                }
            })
        });
        // products + writer
        let mut refine = refine;
        let writer = scope.spawn(move || -> Result<()> {
            let mut done = 0;
            for (i, mut outs, y, ev, unread) in orx {
                if let (Some(refine), Some(ev), Some(y)) = (refine.as_mut(), ev, y.as_ref()) {
                    refine.finish(&y.view(), ev, &mut outs);
                }
                let mut fitted = templates.zip(y.as_ref()).map(|(tpl, y)| tpl.fit(&y.view()));
                let mut ranges = range_templates.as_mut().zip(y.as_ref()).map(|(tpl, y)| tpl.fit(&y.view()));

                if let (Some(opts), Some(y)) = (range_fit, y.as_ref()) {
                    // the network's ranges refined in the tap domain (masked first, as the
                    // decoder contract gives them to the fit)
                    let (depth, conf) = outs.split_at_mut(1);
                    mask_depth(&mut depth[0], &conf[0]);
                    refine_ranges(y.view().insert_axis(Axis(0)), sensor, &mut depth[0], opts);
                }
                // no range and no lifetime where a tap is clipped (the products as decoded, then
                // masked, as reconstruct masks them): the network's confidence 0 there, its and
                // the fits' ranges and lifetimes NaN
                if let Some(u) = &unread {
                    write::without_pixels(u, kind, &mut outs, fitted.as_mut(), ranges.as_mut());
                }
                write_frame(i, outs, fitted, ranges, &mut writers, products, kind, bin_s, t, &peak_opts, out, unread.as_ref())?;
                done += 1;
                on_frame(i + 1, frames);
            }
            // only a complete stream is renamed into place; otherwise the writers are dropped
            // and their temporary files removed
            if done == frames {
                for wr in
                    [writers.cube, writers.depth, writers.second, writers.lifetime, writers.intensity, writers.phasor].into_iter().flatten()
                {
                    wr.finish()?;
                }
            }
            Ok(())
        });
        let mut status = Ok(());
        for msg in frx {
            if cancel.load(Ordering::Relaxed) {
                status = Err(InferError::Cancelled);
                break;
            }
            let (i, y, path, mut ev, unread) = match msg {
                Ok(v) => v,
                Err(e) => {
                    status = Err(e);
                    break;
                }
            };
            if y.dim() != (m, h, w) {
                status = Err(file_err(&path, format!("frame of shape {:?}; the first frame was [{m}, {h}, {w}]", y.shape())));
                break;
            }
            let ti = Instant::now();
            let run = match &ev {
                Some(ev) => model.run_graph_on_evidence(ev),
                None if need_model => model.run(y.view().insert_axis(Axis(0))),
                None => model.check(&y.view().insert_axis(Axis(0)), &path.display().to_string()).map(|_| Vec::new()),
            };
            let outs = match run {
                Ok(o) => o,
                Err(e) => {
                    status = Err(in_file(&path, e));
                    break;
                }
            };
            infer_seconds += ti.elapsed().as_secs_f64();
            if let Some(ev) = ev.as_mut() {
                let _ = btx.try_send(ev.take_buffers());
            }
            let keep = templates.is_some() || range_fit.is_some() || depth_fit || ev.is_some();
            if otx.send((i, outs, keep.then_some(y), ev, unread)).is_err() {
                break;
            }
        }
        drop(otx);
        let _ = reader.join();
        if let Some(e) = evidence {
            let _ = e.join();
        }
        let written = writer.join().unwrap_or_else(|_| Err(file_err(out, "the writer thread panicked")));
        // an interruption the reader or the evidence stage saw first ends the frames early
        // without an error of their own: it is still an interruption (nothing is written)
        if status.is_ok() && cancel.load(Ordering::Relaxed) {
            status = Err(InferError::Cancelled);
        }
        // an early stop drops the writers unfinished (their temporary files removed)
        status.and(written)
    });
    result?;
    Ok(StreamReport { frames, seconds: t0.elapsed().as_secs_f64(), infer_seconds, written, instrument: found })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two noisy frames of one scene are the same scene; frames of two scenes, or a frame
    /// without contrast, are not.
    #[test]
    fn same_scene_tells_a_recording_from_a_stack_of_scenes() {
        // (a xorshift: uniform draws in [0, 1))
        struct Draws(u64);
        impl Draws {
            fn next(&mut self) -> f32 {
                self.0 ^= self.0 << 13;
                self.0 ^= self.0 >> 7;
                self.0 ^= self.0 << 17;
                (self.0 >> 40) as f32 / (1u64 << 24) as f32
            }
        }
        let (h, w) = (64, 64);
        // scenes of bright and dark 8×8 cells, and the Poisson-like noise of ~20 photons a pixel
        let scene = |seed: u64| -> Vec<f32> {
            let mut r = Draws(0x9E37_79B9_7F4A_7C15 ^ seed);
            let cells: Vec<f32> = (0..64).map(|_| if r.next() < 0.5 { 40.0 } else { 4.0 }).collect();
            (0..h * w).map(|p| cells[(p / w / 8) * 8 + (p % w) / 8]).collect()
        };
        let frame = |mean: &[f32], seed: u64| -> Array3<f32> {
            let mut r = Draws(0x2545_F491_4F6C_DD1D ^ seed);
            Array3::from_shape_fn((4, h, w), |(_, i, j)| {
                let m = mean[i * w + j] / 4.0;
                (m + m.sqrt() * (r.next() * 2.0 - 1.0) * 3f32.sqrt()).max(0.0)
            })
        };
        let (a, b) = (scene(1), scene(2));
        let (a1, a2, b1) = (frame(&a, 10), frame(&a, 11), frame(&b, 12));
        assert!(same_scene(&a1.view(), &a2.view()), "one scene, two noise draws");
        assert!(!same_scene(&a1.view(), &b1.view()), "two scenes");
        let flat = Array3::from_elem((4, h, w), 5.0f32);
        assert!(!same_scene(&flat.view(), &flat.view()), "no contrast");
    }

    /// One exponential lies on the universal semicircle at `g = 1/(1+ω²τ²)`; a mixture
    /// weighted by intensity fractions `α_iτ_i` sits on the chord between its components.
    #[test]
    fn phasor_of_components_is_on_the_semicircle_and_its_chords() {
        let omega = 2.0 * std::f64::consts::PI / 52.7e-9;
        let (g, s) = phasor_of_components(3e-9, 3e-9, 1.0, omega);
        let wt = omega * 3e-9;
        assert!((g as f64 - 1.0 / (1.0 + wt * wt)).abs() < 1e-6 && (s as f64 - wt / (1.0 + wt * wt)).abs() < 1e-6);
        let (p1, p2) = (phasor_of_components(1e-9, 1e-9, 1.0, omega), phasor_of_components(5e-9, 5e-9, 1.0, omega));
        let (gm, sm) = phasor_of_components(1e-9, 5e-9, 0.5, omega);
        // intensity fraction of τ₁: 0.5·1 / (0.5·1 + 0.5·5) = 1/6
        let f = 1.0 / 6.0;
        assert!((gm - (f * p1.0 + (1.0 - f) * p2.0)).abs() < 1e-6 && (sm - (f * p1.1 + (1.0 - f) * p2.1)).abs() < 1e-6);
        assert!(phasor_of_components(f32::NAN, 1e-9, 0.5, omega).0.is_nan());
    }
}
