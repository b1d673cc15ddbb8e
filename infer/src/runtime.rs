//! Deployment inference: exported models through ONNX Runtime (`ort`, loaded at run time).
//!
//! The shared library is found through `ORT_DYLIB_PATH`, else in the project's `.venv`
//! (where `scripts/setup.sh` installs the PyPI wheel `onnxruntime==1.31.1`), looked for from
//! the working directory and from the executable's directory upwards. Without it, opening a
//! model fails with [`InferError::OrtMissing`], which says how to install it.

use ndarray::{Array3, Array4, ArrayView3, ArrayView4, ArrayViewD, Ix4};
use ort::session::builder::GraphOptimizationLevel;
use ort::session::Session;
use ort::value::TensorRef;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use tcsense_fits::depth::{CandidateGrid, RangeCosts, RangeTemplates, Seeds};
use tcsense_fits::range::{refine_ranges, RangeFitOptions};
use tcsense_models::decoder::{check_measurements, Control, Decoded, Decoder, Step};
use tcsense_models::net::{mask_depth, mask_lifetime};
use tcsense_sensor::MeasurementMatrix;

use crate::onnx::meta::{EvidenceNote, RangeEvidenceNote};
use crate::onnx::{OnnxMeta, EVIDENCE_INPUT, INPUT, LOG_LIKELIHOOD_INPUT, MATRIX_INPUT};
use crate::{InferError, Result};
use tcsense_fits::evidence::EvidenceBuffers;
use tcsense_fits::lifetime_taps::{Instrument, LifetimeCosts, LifetimeTemplates};
use tcsense_models::lifetime::{evidence_at_into, frame_templates};

/// The ONNX Runtime release the toolkit is built and tested against.
pub const ORT_VERSION: &str = "1.31.1";
/// The library's file name in the wheel.
pub const ORT_LIBRARY: &str = "libonnxruntime.so.1.31.1";

/// Where the ONNX Runtime shared library is: `ORT_DYLIB_PATH`, else a `.venv` of the working
/// directory or of one of the executable's ancestors.
pub fn find_library() -> Result<PathBuf> {
    if let Some(p) = std::env::var_os("ORT_DYLIB_PATH") {
        let p = PathBuf::from(p);
        return if p.is_file() { Ok(p) } else { Err(InferError::OrtMissing(format!("ORT_DYLIB_PATH={} is not a file", p.display()))) };
    }
    let mut roots: Vec<PathBuf> = std::env::current_dir().into_iter().collect();
    if let Ok(exe) = std::env::current_exe() {
        roots.extend(exe.ancestors().skip(1).map(Path::to_path_buf));
    }
    for root in roots {
        let lib = root.join(".venv").join("lib");
        let Ok(entries) = std::fs::read_dir(&lib) else { continue };
        let mut pythons: Vec<PathBuf> = entries.flatten().map(|e| e.path()).collect();
        pythons.sort();
        for py in pythons {
            let cand = py.join("site-packages").join("onnxruntime").join("capi").join(ORT_LIBRARY);
            if cand.is_file() {
                return Ok(cand);
            }
        }
    }
    Err(InferError::OrtMissing("neither ORT_DYLIB_PATH nor a .venv with onnxruntime was found".into()))
}

static ENVIRONMENT: OnceLock<std::result::Result<ort::environment::Environment, String>> = OnceLock::new();

/// The process's ONNX Runtime environment (the library is loaded once).
fn environment() -> Result<&'static ort::environment::Environment> {
    let env = ENVIRONMENT.get_or_init(|| {
        // the reason alone: OrtMissing's message adds the version and how to install it
        let lib = find_library().map_err(|e| match e {
            InferError::OrtMissing(reason) => reason,
            e => e.to_string(),
        })?;
        let builder = ort::init_from(&lib).map_err(|e| format!("cannot load {}: {e}", lib.display()))?;
        builder.with_name("tcsense").build().map_err(|e| format!("cannot start ONNX Runtime from {}: {e}", lib.display()))
    });
    env.as_ref().map_err(|e| InferError::OrtMissing(e.clone()))
}

/// The version string of the loaded ONNX Runtime library.
pub fn runtime_version() -> Result<String> {
    environment()?;
    Ok(ort::info().to_string())
}

/// An exported model opened in ONNX Runtime.
pub struct OnnxModel {
    path: PathBuf,
    session: Session,
    /// Its metadata (codes, sensor model, frame rule).
    pub meta: OnnxMeta,
    /// `A` of the codes in the metadata.
    pub sensor: MeasurementMatrix,
    /// `A` as the `sensor_matrix` input, `[N, M, T]` (models exported with it).
    matrix: Option<ndarray::Array3<f32>>,
    /// A lifetime decoder on the fit's evidence: the templates at a fixed instrument (a
    /// stream's), else the instrument is fitted to every frame.
    templates: Option<LifetimeTemplates>,
    /// A U-Net on the range fit's evidence: the fit's templates of the model's sensor.
    ranges: Option<RangeTemplates>,
    /// A decoder on a fit's evidence exported with a calibration: the correction of its raw
    /// tap images, applied before the evidence.
    correction: Option<FrameCorrection>,
}

/// A calibration's correction of raw tap images, `(y − d) / G`, for a decoder on a fit's
/// evidence (whose graph reads the evidence, not the taps).
#[derive(Debug, Clone)]
pub struct FrameCorrection {
    /// `d`, `[M, H, W]`.
    dark: ndarray::Array3<f32>,
    /// `G`, `[M, H, W]`.
    gain: ndarray::Array3<f32>,
}

impl FrameCorrection {
    /// The maps of `meta` (`None`: no correction), shaped `[M, H, W]` by its calibration's size.
    fn of(meta: &OnnxMeta, path: &Path) -> Result<Option<Self>> {
        let (Some(maps), Some(cal)) = (&meta.correction, &meta.calibration) else { return Ok(None) };
        let shape = (meta.taps, cal.size[0], cal.size[1]);
        let array = |v: &[f32]| {
            ndarray::Array3::from_shape_vec(shape, v.to_vec()).map_err(|e| InferError::File {
                path: path.to_path_buf(),
                msg: format!("metadata_props[\"calibration_maps\"]: {e}; expected M·H·W values of {shape:?}"),
            })
        };
        Ok(Some(FrameCorrection { dark: array(&maps.dark)?, gain: array(&maps.gain)? }))
    }

    /// Correct one frame `y` `[M, H, W]` (checked against the calibration's frame size) in place.
    pub fn apply(&self, mut y: ndarray::ArrayViewMut3<'_, f32>) {
        y -= &self.dark;
        y /= &self.gain;
    }
}

impl std::fmt::Debug for OnnxModel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("OnnxModel").field("path", &self.path).field("meta", &self.meta).finish()
    }
}

impl OnnxModel {
    /// Open `path` with `threads` intra-op threads (0: ONNX Runtime's default, one per core).
    pub fn open(path: &Path, threads: usize) -> Result<Self> {
        if !path.is_file() {
            return Err(InferError::File {
                path: path.to_path_buf(),
                msg: "no such file; expected an ONNX model written by `tcsense export onnx`".into(),
            });
        }
        let env = environment()?;
        let bad = |e: String| InferError::File { path: path.to_path_buf(), msg: format!("not a loadable ONNX model: {e}") };
        let mut builder = Session::builder(env).map_err(|e| bad(e.to_string()))?;
        builder = builder.with_optimization_level(GraphOptimizationLevel::All).map_err(|e| bad(e.to_string()))?;
        // ONNX Runtime's threads spin after a run by default, taking the cores from the work
        // between runs (the fits' evidence and refinement, the stream's reads and writes):
        // without it a lifetime network on the fit's evidence streams 15-18 frames/s instead of
        // 13-14 at 188x212x256; a graph-only model is no slower
        builder = builder.with_intra_op_spinning(false).map_err(|e| bad(e.to_string()))?;
        if threads > 0 {
            builder = builder.with_intra_threads(threads).map_err(|e| bad(e.to_string()))?;
        }
        let session = builder.commit_from_file(path).map_err(|e| bad(e.to_string()))?;
        let meta = {
            let md = session.metadata().map_err(|e| bad(e.to_string()))?;
            OnnxMeta::from_props(path, |k| md.custom(k))?
        };
        let sensor = meta.matrix()?;
        let inputs: Vec<&str> = session.inputs().iter().map(|i| i.name()).collect();
        let want: Vec<&str> = meta.graph_inputs();
        if inputs != want {
            return Err(InferError::File {
                path: path.to_path_buf(),
                msg: format!("graph inputs {inputs:?}; its metadata expects {want:?}"),
            });
        }
        let outputs: Vec<&str> = session.outputs().iter().map(|o| o.name()).collect();
        if outputs != meta.graph_outputs() {
            return Err(InferError::File {
                path: path.to_path_buf(),
                msg: format!("graph outputs {outputs:?}; its metadata expects {:?}", meta.graph_outputs()),
            });
        }
        let matrix = meta.matrix_input.then(|| sensor.a().to_owned());
        let ranges = meta.range_evidence.map(|e| RangeTemplates::new(&sensor, &e.fit_options(meta.returns)));
        let correction = FrameCorrection::of(&meta, path)?;
        Ok(OnnxModel { path: path.to_path_buf(), session, meta, sensor, matrix, templates: None, ranges, correction })
    }

    /// A lifetime decoder on the fit's evidence: fix the instrument (a recording's onset and
    /// IRF width, fitted once) instead of fitting it to every frame. No effect on other models.
    pub fn set_instrument(&mut self, instrument: Instrument) {
        if let Some(e) = &self.meta.evidence {
            self.templates = Some(LifetimeTemplates::new(&self.sensor, instrument, &e.fit_options()));
        }
    }

    /// Frames `y` `[M, H, W]` as the model's evidence reads them: corrected for the calibration
    /// of a decoder on a fit's evidence exported with one, else as they are.
    pub fn corrected<'a>(&self, y: ndarray::ArrayView3<'a, f32>) -> ndarray::CowArray<'a, f32, ndarray::Ix3> {
        match &self.correction {
            Some(c) => {
                let mut o = y.to_owned();
                c.apply(o.view_mut());
                o.into()
            }
            None => y.into(),
        }
    }

    /// The model file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Use `a` as the sensor matrix of a model exported with the matrix as an input (a
    /// recalibrated sensor); it must have the model's `[N, M, T]`.
    pub fn set_matrix(&mut self, a: &MeasurementMatrix) -> Result<()> {
        self.set_matrix_array(a.a())
    }

    /// [`Self::set_matrix`] from the array `[N, M, T]`.
    pub fn set_matrix_array(&mut self, a: ndarray::ArrayView3<'_, f32>) -> Result<()> {
        let Some(m) = &mut self.matrix else {
            return Err(InferError::File {
                path: self.path.clone(),
                msg: "this model has its sensor matrix baked in; export it with --matrix-input to give another".into(),
            });
        };
        if a.dim() != m.dim() {
            return Err(InferError::InvalidParam {
                field: "sensor matrix",
                got: format!("{:?}", a.dim()),
                expected: format!("[N, M, T] = {:?} as the model", m.dim()),
            });
        }
        if let Some(v) = a.iter().find(|v| !v.is_finite()) {
            return Err(InferError::InvalidParam { field: "sensor matrix", got: format!("a value {v}"), expected: "finite values".into() });
        }
        m.assign(&a);
        Ok(())
    }

    /// [`Self::run`] of a lifetime decoder on the fit's evidence: the evidence, the graph (the
    /// posterior's mode), the mode refined in the tap domain where it is the fit's own argmin
    /// ([`LifetimeTemplates::refine_modes`], as burn's decoder does), and the intensity.
    fn run_on_evidence(&mut self, y: &ArrayView4<'_, f32>, e: &EvidenceNote) -> Result<Vec<Array4<f32>>> {
        let of = match &self.templates {
            Some(t) => TemplatesOf::Fixed(t),
            None => TemplatesOf::Frame(&self.sensor),
        };
        let evidence = lifetime_evidence(y, e, of, EvidenceBuffers::default());
        let mut out = self.run_graph_on_evidence(&evidence)?;
        if let FitCosts::Lifetime(frames) = &evidence.costs {
            refine_lifetimes(y, frames, self.templates.as_ref(), &mut out);
        }
        Ok(out)
    }

    /// A decoder on a fit's evidence — a lifetime decoder at a fixed instrument
    /// ([`Self::set_instrument`]), a U-Net on the range fit's evidence — as its work on the CPU
    /// before and after the graph, to run beside it on threads of their own. `None` for other
    /// models, or a lifetime decoder before its instrument is fixed.
    pub fn evidence_stages(&self) -> Option<(EvidenceStage, RefineStage)> {
        let (work, refine) = match (self.meta.evidence.clone(), self.meta.range_evidence) {
            (Some(note), _) => {
                let templates = self.templates.clone()?;
                (StageWork::Lifetime { templates: templates.clone(), note }, RefineWork::Lifetime(templates))
            }
            (None, Some(e)) => {
                let opts = e.fit_options(self.meta.returns);
                let grid =
                    CandidateGrid { candidates: self.meta.bins * e.oversample, oversample: e.oversample, range_m: self.meta.range_m };
                (
                    StageWork::Range { templates: RangeTemplates::new(&self.sensor, &opts), pool: e.pool },
                    RefineWork::Range { templates: RangeTemplates::new(&self.sensor, &opts), grid, returns: self.meta.returns.max(1) },
                )
            }
            (None, None) => return None,
        };
        let stage = EvidenceStage { work, meta: self.meta.clone(), path: self.path.clone(), correction: self.correction.clone() };
        Some((stage, RefineStage { work: refine }))
    }

    /// The graph of a decoder on a fit's evidence alone: its outputs for
    /// [`RefineStage::finish`] (none for a frame without a lit pixel, which has no evidence).
    pub fn run_graph_on_evidence(&mut self, evidence: &FrameEvidence) -> Result<Vec<Array4<f32>>> {
        if matches!(evidence.costs, FitCosts::Range(None)) {
            return Ok(Vec::new());
        }
        let path = self.path.clone();
        let fail = |e: ort::Error| InferError::File { path: path.clone(), msg: format!("ONNX Runtime: {e}") };
        let f = TensorRef::from_array_view(evidence.features.view()).map_err(fail)?;
        let s = TensorRef::from_array_view(evidence.skip.view()).map_err(fail)?;
        let outputs = self.session.run(ort::inputs![EVIDENCE_INPUT => f, LOG_LIKELIHOOD_INPUT => s]).map_err(fail)?;
        named_outputs(&path, &outputs, self.meta.graph_outputs())
    }

    /// [`Self::run`] of a U-Net on the range fit's evidence, frame by frame (a frame's cost
    /// volume is `H·W·C` floats): the evidence, the graph (the posterior's mode and the first
    /// return's confidence), the mode refined in the tap domain with the fit's second return
    /// beside it ([`RangeTemplates::ranges`], as burn's decoder does); depth NaN where the
    /// confidence is below one half, the second return's confidence the first's where it has one.
    fn run_on_range_evidence(&mut self, y: &ArrayView4<'_, f32>, e: &RangeEvidenceNote) -> Result<Vec<Array4<f32>>> {
        let (b, _, h, w) = y.dim();
        let k = self.meta.returns.max(1);
        let grid = CandidateGrid { candidates: self.meta.bins * e.oversample, oversample: e.oversample, range_m: self.meta.range_m };
        let mut depth = Array4::from_elem((b, k, h, w), f32::NAN);
        let mut confidence = Array4::zeros((b, k, h, w));
        for i in 0..b {
            let yi = y.index_axis(ndarray::Axis(0), i);
            let Some(templates) = self.ranges.as_ref() else { unreachable!("templates built with the model") };
            let evidence = range_evidence(templates, &yi, e.pool, EvidenceBuffers::default());
            let out = self.run_graph_on_evidence(&evidence)?;
            let Some(templates) = self.ranges.as_mut() else { unreachable!("templates built with the model") };
            let [d, c] = refine_range_frame(templates, grid, (k, h, w), &evidence, &out);
            depth.index_axis_mut(ndarray::Axis(0), i).assign(&d);
            confidence.index_axis_mut(ndarray::Axis(0), i).assign(&c);
        }
        Ok(vec![depth, confidence])
    }

    /// Check measurements `[B, M, H, W]` against the metadata: taps, the frame rule, finite.
    pub fn check(&self, y: &ArrayView4<'_, f32>, what: &str) -> Result<()> {
        check_frames(&self.meta, &self.path, y, what)
    }

    /// Run the model on `y [B, M, H, W]` (checked first): its outputs in the order of
    /// [`OnnxMeta::outputs`], each `[B, C, H, W]`.
    pub fn run(&mut self, y: ArrayView4<'_, f32>) -> Result<Vec<Array4<f32>>> {
        self.check(&y, "input")?;
        let fail = |e: ort::Error| InferError::File { path: self.path.clone(), msg: format!("ONNX Runtime: {e}") };
        let mut y = y.as_standard_layout();
        if let Some(c) = &self.correction {
            let mut o = y.into_owned();
            o.outer_iter_mut().for_each(|f| c.apply(f));
            y = o.into();
        }
        if let Some(e) = self.meta.evidence.clone() {
            return self.run_on_evidence(&y.view(), &e);
        }
        if let Some(e) = self.meta.range_evidence {
            return self.run_on_range_evidence(&y.view(), &e);
        }
        let input = TensorRef::from_array_view(y.view()).map_err(fail)?;
        let names = self.meta.outputs();
        let outputs = match &self.matrix {
            Some(a) => {
                let a = TensorRef::from_array_view(a.view()).map_err(fail)?;
                self.session.run(ort::inputs![INPUT => input, MATRIX_INPUT => a])
            }
            None => self.session.run(ort::inputs![INPUT => input]),
        };
        let path = self.path.clone();
        let fail = |e: ort::Error| InferError::File { path: path.clone(), msg: format!("ONNX Runtime: {e}") };
        let outputs = outputs.map_err(fail)?;
        named_outputs(&path, &outputs, names)
    }
}

/// The session's outputs `names`, each `[B, C, H, W]`; errors name the model file `path`.
fn named_outputs(path: &Path, outputs: &ort::session::SessionOutputs<'_>, names: &[&str]) -> Result<Vec<Array4<f32>>> {
    let fail = |e: ort::Error| InferError::File { path: path.to_path_buf(), msg: format!("ONNX Runtime: {e}") };
    names
        .iter()
        .map(|n| {
            let v: ArrayViewD<'_, f32> = outputs[*n].try_extract_array::<f32>().map_err(fail)?;
            v.into_dimensionality::<Ix4>()
                .map(|v| v.to_owned())
                .map_err(|e| InferError::File { path: path.to_path_buf(), msg: format!("output {n}: {e}") })
        })
        .collect()
}

/// What the graph of a decoder on a fit's evidence reads for a batch (pixel-major) and what
/// its refinement reads after it.
pub struct FrameEvidence {
    /// `[B, H, W, F]`
    features: Array4<f32>,
    /// The log-likelihoods `[B, H, W, G]` (`[B, H, W, S·C]` of a range fit's windows).
    skip: Array4<f32>,
    costs: FitCosts,
}

impl FrameEvidence {
    /// The storage of the graph's inputs, for a later frame's evidence (the graph has run: the
    /// refinement reads the costs only).
    pub fn take_buffers(&mut self) -> EvidenceBuffers {
        let empty = || Array4::zeros((1, 0, 0, 0));
        EvidenceBuffers {
            skip: std::mem::replace(&mut self.skip, empty()).into_raw_vec_and_offset().0,
            features: std::mem::replace(&mut self.features, empty()).into_raw_vec_and_offset().0,
        }
    }
}

/// The costs the evidence came from, for the refinement in the tap domain.
enum FitCosts {
    /// Per frame its templates (where the instrument is not fixed) and costs.
    Lifetime(Vec<(Option<LifetimeTemplates>, LifetimeCosts)>),
    /// One frame's; `None`: no lit pixel, no evidence (the graph is not run).
    Range(Option<RangeCosts>),
}

/// Where a lifetime decoder's frames get their templates.
#[derive(Clone, Copy)]
enum TemplatesOf<'a> {
    /// Fixed ones (a stream's instrument, or one set with [`OnnxModel::set_instrument`]).
    Fixed(&'a LifetimeTemplates),
    /// Each frame's own, its instrument estimated through this sensor.
    Frame(&'a MeasurementMatrix),
}

/// [`FrameEvidence`] of every frame of `y` `[B, M, H, W]` for a lifetime decoder.
fn lifetime_evidence(y: &ArrayView4<'_, f32>, e: &EvidenceNote, of: TemplatesOf<'_>, buffers: EvidenceBuffers) -> FrameEvidence {
    let (b, _, h, w) = y.dim();
    let (f, l) = e.channels();
    let mut features = Vec::with_capacity(b * h * w * f);
    let mut skip = Vec::with_capacity(b * h * w * l);
    let mut frames = Vec::with_capacity(b);
    let opts = e.fit_options();
    // (a single frame's evidence is written into the buffers: a stream's earlier frame's)
    let mut buffers = (b == 1).then_some(buffers);
    for i in 0..b {
        let yi = y.index_axis(ndarray::Axis(0), i);
        let (own, fixed) = match of {
            TemplatesOf::Fixed(t) => (None, Some(t)),
            TemplatesOf::Frame(sensor) => (Some(frame_templates(&yi, sensor, &opts)), None),
        };
        let Some(templates) = own.as_ref().or(fixed) else { unreachable!("templates fixed or fitted") };
        let (ev, costs) = evidence_at_into(&yi, templates, e.pool, &e.windows, buffers.take().unwrap_or_default());
        // a stream's single frame is moved, not copied (tens of MB a frame)
        if b == 1 {
            features = ev.features.into_raw_vec_and_offset().0;
            skip = ev.skip.into_raw_vec_and_offset().0;
        } else {
            features.extend(ev.features.iter());
            skip.extend(ev.skip.iter());
        }
        frames.push((own, costs));
    }
    let shaped = |c: usize, v: Vec<f32>| Array4::from_shape_vec((b, h, w, c), v).expect("[B, H, W, C] of the frames' evidence");
    FrameEvidence { features: shaped(f, features), skip: shaped(l, skip), costs: FitCosts::Lifetime(frames) }
}

/// [`FrameEvidence`] of one frame `y` `[M, H, W]` for a U-Net on the range fit's evidence.
fn range_evidence(templates: &RangeTemplates, y: &ArrayView3<'_, f32>, pool: usize, buffers: EvidenceBuffers) -> FrameEvidence {
    match templates.costs(y) {
        Some(costs) => {
            let ev = templates.evidence_into(&costs, &y.sum_axis(ndarray::Axis(0)), pool, buffers);
            FrameEvidence {
                features: ev.features.insert_axis(ndarray::Axis(0)),
                skip: ev.skip.insert_axis(ndarray::Axis(0)),
                costs: FitCosts::Range(Some(costs)),
            }
        }
        None => FrameEvidence { features: Array4::zeros((1, 0, 0, 0)), skip: Array4::zeros((1, 0, 0, 0)), costs: FitCosts::Range(None) },
    }
}

/// The graph's posterior modes `out[0]` (`[B, 4, H, W]`, s) refined in the tap domain where
/// each is the fit's own argmin ([`LifetimeTemplates::refine_modes`], as burn's decoder does),
/// and the intensity `[B, 1, H, W]` pushed after the graph's outputs.
fn refine_lifetimes(
    y: &ArrayView4<'_, f32>,
    frames: &[(Option<LifetimeTemplates>, LifetimeCosts)],
    fixed: Option<&LifetimeTemplates>,
    out: &mut Vec<Array4<f32>>,
) {
    for (i, (own, costs)) in frames.iter().enumerate() {
        let Some(templates) = own.as_ref().or(fixed) else { unreachable!("templates fixed or fitted") };
        let (l0, step) = templates.log_grid();
        let lifetime = &mut out[0];
        let u: Vec<f32> = lifetime.slice(ndarray::s![i, 0, .., ..]).iter().map(|&t| ((t as f64).ln() - l0) as f32 / step as f32).collect();
        let tau = templates.refine_modes(&y.index_axis(ndarray::Axis(0), i), costs, &u);
        for c in 0..3 {
            lifetime.slice_mut(ndarray::s![i, c, .., ..]).assign(&tau);
        }
    }
    out.push(y.sum_axis(ndarray::Axis(1)).insert_axis(ndarray::Axis(1)));
}

/// One frame's depth and confidence `[K, H, W]` from the graph's outputs `out` (the
/// posterior's mode `[1, 1, H, W]` in metres, the first return's confidence): the mode refined
/// in the tap domain with the fit's second return beside it; depth NaN where the confidence is
/// below the detection threshold. NaN and 0 everywhere for a frame without evidence.
fn refine_range_frame(
    templates: &mut RangeTemplates,
    grid: CandidateGrid,
    (k, h, w): (usize, usize, usize),
    evidence: &FrameEvidence,
    out: &[Array4<f32>],
) -> [Array3<f32>; 2] {
    let FitCosts::Range(Some(costs)) = &evidence.costs else {
        return [Array3::from_elem((k, h, w), f32::NAN), Array3::zeros((k, h, w))];
    };
    let mut depth = Array3::from_elem((k, h, w), f32::NAN);
    let mut confidence = Array3::zeros((k, h, w));
    let u: Vec<f32> = out[0].iter().map(|&r| grid.candidate(r as f64) as f32).collect();
    let ranges = templates.ranges(costs, Seeds::Modes(&u));
    for p in 0..h * w {
        let (r, q) = (p / w, p % w);
        let p1 = out[1][(0, 0, r, q)];
        for j in 0..k.min(ranges.dim().0) {
            let v = ranges[(j, r, q)];
            let cj = if v.is_finite() { p1 } else { 0.0 };
            confidence[(j, r, q)] = cj;
            if cj >= tcsense_models::net::DETECTION_THRESHOLD {
                depth[(j, r, q)] = v;
            }
        }
    }
    [depth, confidence]
}

/// The work before the graph of a decoder on a fit's evidence, for a stream's frames
/// ([`OnnxModel::evidence_stages`]).
pub struct EvidenceStage {
    work: StageWork,
    meta: OnnxMeta,
    path: PathBuf,
    correction: Option<FrameCorrection>,
}

// (one of each per stream: the variants' sizes do not matter)
#[allow(clippy::large_enum_variant)]
enum StageWork {
    Lifetime { templates: LifetimeTemplates, note: EvidenceNote },
    Range { templates: RangeTemplates, pool: usize },
}

impl EvidenceStage {
    /// [`OnnxModel::check`] of `y` `[B, M, H, W]`.
    pub fn check(&self, y: &ArrayView4<'_, f32>, what: &str) -> Result<()> {
        check_frames(&self.meta, &self.path, y, what)
    }

    /// Correct a raw frame `y` `[M, H, W]` (checked first) for the model's calibration, in
    /// place; nothing without one. The evidence and the refinement read the corrected frame.
    pub fn correct(&self, y: &mut ndarray::Array3<f32>) {
        if let Some(c) = &self.correction {
            c.apply(y.view_mut());
        }
    }

    /// The evidence of one frame `y` `[M, H, W]` (checked, corrected first), written into an earlier
    /// frame's `buffers` ([`FrameEvidence::take_buffers`]; empty: allocated).
    pub fn evidence(&self, y: &ArrayView3<'_, f32>, buffers: EvidenceBuffers) -> FrameEvidence {
        match &self.work {
            StageWork::Lifetime { templates, note } => {
                lifetime_evidence(&y.view().insert_axis(ndarray::Axis(0)), note, TemplatesOf::Fixed(templates), buffers)
            }
            StageWork::Range { templates, pool } => range_evidence(templates, y, *pool, buffers),
        }
    }
}

/// The work after the graph of a decoder on a fit's evidence, for a stream's frames
/// ([`OnnxModel::evidence_stages`]).
pub struct RefineStage {
    work: RefineWork,
}

#[allow(clippy::large_enum_variant)]
enum RefineWork {
    Lifetime(LifetimeTemplates),
    Range { templates: RangeTemplates, grid: CandidateGrid, returns: usize },
}

impl RefineStage {
    /// The graph's outputs `out` of one frame `y` `[M, H, W]`, completed as [`OnnxModel::run`]
    /// gives them: the lifetimes refined in the tap domain and the intensity after them; the
    /// depth and confidence `[1, K, H, W]` of the ranges refined in the tap domain.
    pub fn finish(&mut self, y: &ArrayView3<'_, f32>, evidence: FrameEvidence, out: &mut Vec<Array4<f32>>) {
        match (&mut self.work, &evidence.costs) {
            (RefineWork::Lifetime(templates), FitCosts::Lifetime(frames)) => {
                refine_lifetimes(&y.view().insert_axis(ndarray::Axis(0)), frames, Some(templates), out)
            }
            (RefineWork::Range { templates, grid, returns }, FitCosts::Range(_)) => {
                let (_, h, w) = y.dim();
                let [d, c] = refine_range_frame(templates, *grid, (*returns, h, w), &evidence, out);
                *out = vec![d.insert_axis(ndarray::Axis(0)), c.insert_axis(ndarray::Axis(0))];
            }
            _ => unreachable!("the stages of one model"),
        }
    }
}

/// [`OnnxModel::check`] against `meta`, naming `path`.
fn check_frames(meta: &OnnxMeta, path: &Path, y: &ArrayView4<'_, f32>, what: &str) -> Result<()> {
    let (b, m, h, w) = y.dim();
    let (fh, fw) = meta.frame_multiple;
    if b == 0 || m != meta.taps || h == 0 || w == 0 || h % fh != 0 || w % fw != 0 {
        return Err(InferError::InvalidParam {
            field: "measurements",
            got: format!("{what}: [{b}, {m}, {h}, {w}]"),
            expected: format!(
                "[B, M, H, W] with M = {} taps and H, W non-zero multiples of {fh}x{fw} (the frame rule of {})",
                meta.taps,
                path.display()
            ),
        });
    }
    if let Some(c) = &meta.calibration {
        if [h, w] != c.size {
            return Err(InferError::InvalidParam {
                field: "measurements",
                got: format!("{what}: [{b}, {m}, {h}, {w}]"),
                expected: format!(
                    "raw {} tap images of {}x{}, the frame size of the calibration built into {}",
                    c.units,
                    c.size[0],
                    c.size[1],
                    path.display()
                ),
            });
        }
    }
    // (the rule every reader of tap images and cubes applies, with the first bad index)
    tcsense_sensor::npy::ensure_usable(y, what).map_err(|e| InferError::InvalidParam {
        field: "measurements",
        got: e.to_string(),
        expected: format!("finite tap values within ±{:e}", tcsense_sensor::npy::MAX_VALUE),
    })
}

/// An exported model behind the decoder contract (`eval --decoder onnx:model.onnx`).
pub struct OnnxDecoder {
    name: String,
    model: OnnxModel,
    /// A U-Net's ranges refined in the tap domain ([`tcsense_fits::range`]).
    range_fit: Option<RangeFitOptions>,
}

impl OnnxDecoder {
    pub fn new(model: OnnxModel) -> Self {
        OnnxDecoder { name: format!("onnx:{}", model.meta.decoder), model, range_fit: Some(RangeFitOptions::default()) }
    }

    /// A U-Net's ranges as the model outputs them, without the fit in the tap domain.
    pub fn without_range_fit(mut self) -> Self {
        self.range_fit = None;
        self
    }
}

impl Decoder for OnnxDecoder {
    fn name(&self) -> &str {
        &self.name
    }

    fn decode(&mut self, y: ArrayView4<'_, f32>, sensor: &tcsense_sensor::Sensor, ctl: &Control<'_>) -> tcsense_models::Result<Decoded> {
        let sensor = sensor.matrix();
        check_measurements(&y, sensor)?;
        let to_model = |e: InferError| tcsense_models::ModelError::InvalidParam {
            field: "onnx decoder",
            got: e.to_string(),
            expected: "a successful ONNX Runtime run".into(),
        };
        if self.model.meta.matrix_input {
            self.model.set_matrix(sensor).map_err(to_model)?;
        } else if *sensor != self.model.sensor {
            return Err(tcsense_models::ModelError::InvalidParam {
                field: "sensor",
                got: "a measurement matrix other than the model's".into(),
                expected: format!(
                    "the codes and sensor model baked into {} (or a model exported with --matrix-input)",
                    self.model.path().display()
                ),
            });
        }
        let b = y.dim().0;
        let mut frames: Vec<Vec<Array4<f32>>> = Vec::with_capacity(b);
        for i in 0..b {
            ctl.check()?;
            frames.push(self.model.run(y.slice(ndarray::s![i..i + 1, .., .., ..])).map_err(to_model)?);
            (ctl.progress)(Step { frame: i, frames: b, done: 1, total: 1 });
        }
        let cat = |k: usize| -> tcsense_models::Result<Array4<f32>> {
            let views: Vec<_> = frames.iter().map(|f| f[k].view()).collect();
            ndarray::concatenate(ndarray::Axis(0), &views).map_err(|e| tcsense_models::ModelError::InvalidParam {
                field: "batch",
                got: e.to_string(),
                expected: "frames of one shape".into(),
            })
        };
        if self.model.meta.decoder == "unet" {
            let (mut depth, confidence) = (cat(0)?, cat(1)?);
            mask_depth(&mut depth, &confidence);
            // (a U-Net on the range fit's evidence is refined in the tap domain already, by the
            // runtime or in its graph from the taps)
            if let (Some(opts), None, false) = (&self.range_fit, self.model.meta.range_evidence, self.model.meta.refined_in_graph) {
                refine_ranges(y, sensor, &mut depth, opts);
            }
            Ok(Decoded { depth: Some(depth), confidence: Some(confidence), ..Default::default() })
        } else if self.model.meta.decoder == "lifetime" {
            let (mut lifetime, confidence) = (cat(0)?, cat(1)?);
            mask_lifetime(&mut lifetime, &confidence);
            Ok(Decoded { lifetime: Some(lifetime), confidence: Some(confidence), intensity: Some(cat(2)?), ..Default::default() })
        } else {
            Ok(Decoded { cube: Some(cat(0)?), ..Default::default() })
        }
    }
}
