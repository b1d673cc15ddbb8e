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

use ndarray::{Array3, Array4, ArrayView3, Axis};
use std::fs::File;
use std::io::{BufWriter, Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::sync_channel;
use std::time::Instant;

use tcsense_sensor::npy::{f32_header, parse_header, read_npy, NpyHeader};

use crate::products::{depth_map, write_ply, PeakOptions};
use crate::runtime::OnnxModel;
use crate::{InferError, Result};
use tcsense_fits::depth::{DepthFitOptions, RangeTemplates};
use tcsense_fits::lifetime_taps::{estimate_instrument, LifetimeTemplates, TapFit, TapFitOptions};
use tcsense_fits::range::{refine_ranges, RangeFitOptions};
use tcsense_models::net::mask_depth;

fn file_err(path: &Path, msg: impl ToString) -> InferError {
    InferError::File { path: path.to_path_buf(), msg: msg.to_string() }
}

/// Where frames come from.
pub enum FrameSource {
    /// A `.npy` file, read frame by frame.
    Npy { path: PathBuf, file: File, header: NpyHeader, frames: usize, frame: [usize; 3], single: bool },
    /// A directory of frame files.
    Dir { files: Vec<PathBuf> },
}

impl FrameSource {
    /// Open a `.npy` frame or stack, or a directory of `.npy`/`.png` frames.
    pub fn open(path: &Path) -> Result<Self> {
        if path.is_dir() {
            let mut files: Vec<PathBuf> = std::fs::read_dir(path)
                .map_err(|e| file_err(path, e))?
                .flatten()
                .map(|e| e.path())
                .filter(|p| p.is_file() && matches!(p.extension().and_then(|e| e.to_str()), Some("npy" | "png")))
                .collect();
            files.sort();
            if files.is_empty() {
                return Err(file_err(path, "no frames: expected .npy [M, H, W] or 16-bit PNG [H, M·W] files in this directory"));
            }
            return Ok(FrameSource::Dir { files });
        }
        let mut file = File::open(path).map_err(|e| file_err(path, e))?;
        let mut head = vec![0u8; 4096];
        let n = read_up_to(&mut file, &mut head).map_err(|e| file_err(path, e))?;
        let header = parse_header(&head[..n]).map_err(|e| file_err(path, e))?;
        let (frames, frame, single) = match header.shape.as_slice() {
            &[m, h, w] => (1, [m, h, w], true),
            &[f, m, h, w] => (f, [m, h, w], false),
            s => return Err(file_err(path, format!("measurements of shape {s:?}; expected [M, H, W] or [F, M, H, W]"))),
        };
        if frames == 0 || frame.contains(&0) {
            return Err(file_err(
                path,
                format!(
                    "measurements of shape {:?} hold no tap image; expected [M, H, W] or [F, M, H, W] with every size ≥ 1",
                    header.shape
                ),
            ));
        }
        if header.fortran && frames > 1 {
            return Err(file_err(path, "a Fortran-order stack cannot be streamed; save it in C order (numpy.ascontiguousarray)"));
        }
        let need = header
            .shape
            .iter()
            .try_fold(header.size as u64, |acc, &d| acc.checked_mul(d as u64))
            .and_then(|b| b.checked_add(header.data_offset as u64));
        let Some(need) = need else {
            return Err(file_err(path, format!("measurements of shape {:?}: more bytes than a file can hold", header.shape)));
        };
        let have = file.metadata().map_err(|e| file_err(path, e))?.len();
        if have < need {
            return Err(file_err(
                path,
                format!("npy data truncated: shape {:?} of {} needs {need} bytes, the file has {have}", header.shape, header.descr),
            ));
        }
        Ok(FrameSource::Npy { path: path.to_path_buf(), file, header, frames, frame, single })
    }

    /// Frames in the source.
    pub fn len(&self) -> usize {
        match self {
            FrameSource::Npy { frames, .. } => *frames,
            FrameSource::Dir { files } => files.len(),
        }
    }

    /// Whether it holds no frame.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// A single `[M, H, W]` frame (outputs drop the frame axis).
    pub fn single(&self) -> bool {
        matches!(self, FrameSource::Npy { single: true, .. })
    }

    /// Frame `i`, `[M, H, W]`, and the file it came from; `taps` is the model's `M` (to split
    /// PNG tap strips).
    pub fn read(&mut self, i: usize, taps: usize) -> Result<(Array3<f32>, PathBuf)> {
        match self {
            FrameSource::Npy { path, file, header, frame, .. } => {
                let per = frame.iter().product::<usize>();
                if header.fortran {
                    let a = read_npy(path)?;
                    let a = a.into_dimensionality::<ndarray::Ix3>().map_err(|e| file_err(path, e))?;
                    return Ok((a, path.clone()));
                }
                let mut bytes = vec![0u8; per * header.size];
                file.seek(SeekFrom::Start((header.data_offset + i * per * header.size) as u64)).map_err(|e| file_err(path, e))?;
                file.read_exact(&mut bytes).map_err(|e| file_err(path, format!("frame {i}: {e}")))?;
                let mut v = vec![0f32; per];
                header.decode_into(&bytes, &mut v);
                let a = Array3::from_shape_vec((frame[0], frame[1], frame[2]), v).map_err(|e| file_err(path, e))?;
                Ok((a, path.clone()))
            }
            FrameSource::Dir { files } => {
                let p = files[i].clone();
                let a = if p.extension().and_then(|e| e.to_str()) == Some("png") {
                    read_png_taps(&p, taps)?
                } else {
                    let a = read_npy(&p)?;
                    let shape = a.shape().to_vec();
                    a.into_dimensionality::<ndarray::Ix3>()
                        .map_err(|_| file_err(&p, format!("a frame of shape {shape:?}; expected [M, H, W]")))?
                };
                Ok((a, p))
            }
        }
    }
}

fn read_up_to(f: &mut File, buf: &mut [u8]) -> std::io::Result<usize> {
    let mut n = 0;
    while n < buf.len() {
        match f.read(&mut buf[n..])? {
            0 => break,
            k => n += k,
        }
    }
    Ok(n)
}

/// A grayscale PNG of `taps` tap images side by side, `[H, M·W]` → `[M, H, W]`.
pub fn read_png_taps(path: &Path, taps: usize) -> Result<Array3<f32>> {
    let file = File::open(path).map_err(|e| file_err(path, e))?;
    let mut decoder = png::Decoder::new(std::io::BufReader::new(file));
    decoder.set_transformations(png::Transformations::IDENTITY);
    let mut reader = decoder.read_info().map_err(|e| file_err(path, format!("not a readable PNG: {e}")))?;
    let (w_all, h) = (reader.info().width as usize, reader.info().height as usize);
    let (color, depth) = (reader.info().color_type, reader.info().bit_depth);
    if color != png::ColorType::Grayscale || !matches!(depth, png::BitDepth::Sixteen | png::BitDepth::Eight) {
        return Err(file_err(path, format!("a {color:?} PNG of {depth:?} bits; expected 8- or 16-bit grayscale tap images")));
    }
    if taps == 0 || w_all % taps != 0 {
        return Err(file_err(path, format!("width {w_all} is not a multiple of the model's M = {taps} taps (tap images side by side)")));
    }
    let size = reader.output_buffer_size().ok_or_else(|| file_err(path, "PNG too large"))?;
    let mut buf = vec![0u8; size];
    let info = reader.next_frame(&mut buf).map_err(|e| file_err(path, format!("PNG data: {e}")))?;
    let w = w_all / taps;
    let line = info.line_size;
    let mut a = Array3::<f32>::zeros((taps, h, w));
    for r in 0..h {
        let row = &buf[r * line..(r + 1) * line];
        for col in 0..w_all {
            let v = match depth {
                png::BitDepth::Sixteen => u16::from_be_bytes([row[2 * col], row[2 * col + 1]]) as f32,
                _ => row[col] as f32,
            };
            a[(col / w, r, col % w)] = v;
        }
    }
    Ok(a)
}

/// An `f32` `.npy` stack written frame by frame into a temporary file, renamed on
/// [`NpyStackWriter::finish`]; dropped unfinished, the temporary file is removed.
pub struct NpyStackWriter {
    path: PathBuf,
    tmp: PathBuf,
    out: Option<BufWriter<File>>,
    expected: usize,
    written: usize,
}

impl NpyStackWriter {
    /// A writer of an array of `shape` (its values come in C order through `push`).
    pub fn create(path: &Path, shape: &[usize]) -> Result<Self> {
        let header = f32_header(shape).map_err(|e| file_err(path, e))?;
        let dir = path.parent().filter(|d| !d.as_os_str().is_empty()).map_or_else(|| PathBuf::from("."), Path::to_path_buf);
        let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| "out".into());
        let tmp = dir.join(format!(".{name}.{}.tmp", std::process::id()));
        let mut out = BufWriter::new(File::create(&tmp).map_err(|e| file_err(path, e))?);
        out.write_all(&header).map_err(|e| file_err(path, e))?;
        Ok(NpyStackWriter { path: path.to_path_buf(), tmp, out: Some(out), expected: shape.iter().product(), written: 0 })
    }

    /// Append values (C order).
    pub fn push<'a>(&mut self, values: impl IntoIterator<Item = &'a f32>) -> Result<()> {
        let Some(out) = self.out.as_mut() else { return Err(file_err(&self.path, "written after finish")) };
        let mut buf = Vec::new();
        for v in values {
            buf.extend_from_slice(&v.to_le_bytes());
        }
        self.written += buf.len() / 4;
        out.write_all(&buf).map_err(|e| file_err(&self.path, e))
    }

    /// Flush, check the count and rename into place.
    pub fn finish(mut self) -> Result<()> {
        let out = self.out.take().ok_or_else(|| file_err(&self.path, "finished twice"))?;
        let result = (|| {
            if self.written != self.expected {
                return Err(file_err(&self.path, format!("{} values written, {} expected", self.written, self.expected)));
            }
            let file = out.into_inner().map_err(|e| file_err(&self.path, e.into_error()))?;
            file.sync_all().map_err(|e| file_err(&self.path, e))?;
            std::fs::rename(&self.tmp, &self.path).map_err(|e| file_err(&self.path, e))
        })();
        if result.is_err() {
            let _ = std::fs::remove_file(&self.tmp);
        }
        result
    }
}

impl Drop for NpyStackWriter {
    fn drop(&mut self) {
        if self.out.is_some() {
            let _ = std::fs::remove_file(&self.tmp);
        }
    }
}

/// What an exported model gives, from its metadata's decoder name.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ModelKind {
    /// A transient cube (ADMM-Net).
    Cube,
    /// Depth of K returns with confidences (the U-Net).
    Depth,
    /// Lifetimes, confidence and intensity (the lifetime decoder).
    Lifetime,
}

impl ModelKind {
    /// The kind of a model whose metadata names `decoder`.
    pub fn of(decoder: &str) -> ModelKind {
        match decoder {
            "unet" => ModelKind::Depth,
            "lifetime" => ModelKind::Lifetime,
            _ => ModelKind::Cube,
        }
    }

    /// The products this kind of model can give, and those written when none are asked for.
    pub fn products(self) -> (&'static [&'static str], &'static str) {
        match self {
            ModelKind::Cube => (&["cube", "depth", "peaks", "ply", "lifetime", "intensity", "phasor"], "cube"),
            ModelKind::Depth => (&["depth", "ply"], "depth"),
            ModelKind::Lifetime => (&["lifetime", "intensity", "phasor"], "lifetime,intensity"),
        }
    }
}

/// What to write.
#[derive(Debug, Clone, PartialEq)]
pub struct Products {
    pub cube: bool,
    pub depth: bool,
    pub peaks: bool,
    pub ply: bool,
    /// The amplitude-weighted mean lifetime `[H, W]` (s): a cube's by the reconvolution fit.
    pub lifetime: bool,
    /// The photo-charge per pixel `[H, W]`.
    pub intensity: bool,
    /// The IRF-referenced phasor `(g, s)` at the cycle's first harmonic, `[2, H, W]`.
    pub phasor: bool,
    /// Returns per pixel from a cube (peak detection).
    pub returns: usize,
    /// Camera field of view for point clouds (degrees).
    pub fov_deg: f64,
    /// Lifetimes (and intensity, phasor) by the fit to the taps through the model's sensor
    /// ([`tcsense_fits::lifetime_taps::LifetimeTemplates`], the instrument estimated once on the first frame
    /// unless its `onset_s` is given) instead of the model's own; `None`: the model's.
    pub lifetime_fit: Option<TapFitOptions>,
    /// A depth model's ranges refined by the fit in the tap domain, as `reconstruct unet`
    /// applies it ([`tcsense_fits::range`]); `None`: as the network gives them.
    pub range_fit: Option<RangeFitOptions>,
    /// Depth (and the point cloud, the confidence) by the template fit of ranges to the taps
    /// through the model's sensor ([`tcsense_fits::depth`]) instead of the model's;
    /// `None`: the model's.
    pub depth_fit: Option<DepthFitOptions>,
}

impl Products {
    /// Parse a comma-separated list (`cube,depth,peaks,ply,lifetime,intensity,phasor`) for a
    /// model of `kind`.
    pub fn parse(list: &str, kind: ModelKind) -> Result<Self> {
        let mut p = Products {
            cube: false,
            depth: false,
            peaks: false,
            ply: false,
            lifetime: false,
            intensity: false,
            phasor: false,
            returns: 2,
            fov_deg: 40.0,
            lifetime_fit: None,
            range_fit: Some(RangeFitOptions::default()),
            depth_fit: None,
        };
        let (allowed, _) = kind.products();
        for item in list.split(',').map(str::trim).filter(|s| !s.is_empty()) {
            let (known, _) = ModelKind::Cube.products(); // a cube model gives every product
            if !known.contains(&item) {
                return Err(InferError::InvalidParam {
                    field: "--products",
                    got: item.into(),
                    expected: format!("a comma-separated list of {}", known.join(", ")),
                });
            }
            if !allowed.contains(&item) {
                let what = match kind {
                    ModelKind::Cube => "a cube",
                    ModelKind::Depth => "depth directly",
                    ModelKind::Lifetime => "lifetimes directly",
                };
                return Err(InferError::InvalidParam {
                    field: "--products",
                    got: list.into(),
                    expected: format!("{}: this model estimates {what}", allowed.join(", ")),
                });
            }
            match item {
                "cube" => p.cube = true,
                "depth" => p.depth = true,
                "peaks" => p.peaks = true,
                "ply" => p.ply = true,
                "lifetime" => p.lifetime = true,
                "intensity" => p.intensity = true,
                _ => p.phasor = true,
            }
        }
        if !(p.cube || p.depth || p.peaks || p.ply || p.lifetime || p.intensity || p.phasor) {
            return Err(InferError::InvalidParam { field: "--products", got: list.into(), expected: "at least one product".into() });
        }
        Ok(p)
    }

    /// Whether the model must run: a product asked for comes from it (not every product comes
    /// from the fit to the taps).
    pub fn need_model(&self) -> bool {
        self.cube
            || self.peaks
            || ((self.depth || self.ply) && self.depth_fit.is_none())
            || ((self.lifetime || self.intensity || self.phasor) && self.lifetime_fit.is_none())
    }
}

/// The phasor `(g, s)` at angular frequency `ω` of a pixel's decay from its lifetimes: the
/// components' semicircle points weighted by their intensity fractions `α_iτ_i / Σ α_jτ_j`.
pub fn phasor_of_components(tau1: f32, tau2: f32, alpha1: f32, omega: f64) -> (f32, f32) {
    if !(tau1.is_finite() && tau2.is_finite() && alpha1.is_finite()) {
        return (f32::NAN, f32::NAN);
    }
    let (t1, t2, a1) = (tau1 as f64, tau2 as f64, (alpha1 as f64).clamp(0.0, 1.0));
    let (i1, i2) = (a1 * t1, (1.0 - a1) * t2);
    let total = (i1 + i2).max(1e-300);
    let point = |t: f64| {
        let wt = omega * t;
        (1.0 / (1.0 + wt * wt), wt / (1.0 + wt * wt))
    };
    let (p1, p2) = (point(t1), point(t2));
    (((i1 * p1.0 + i2 * p2.0) / total) as f32, ((i1 * p1.1 + i2 * p2.1) / total) as f32)
}

/// What a streamed run did.
#[derive(Debug, Clone)]
pub struct StreamReport {
    pub frames: usize,
    pub seconds: f64,
    /// Seconds inside ONNX Runtime.
    pub infer_seconds: f64,
    pub written: Vec<PathBuf>,
}

struct Writers {
    cube: Option<NpyStackWriter>,
    depth: Option<NpyStackWriter>,
    second: Option<NpyStackWriter>,
    lifetime: Option<NpyStackWriter>,
    intensity: Option<NpyStackWriter>,
    phasor: Option<NpyStackWriter>,
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
    // the fits to the taps need corrected tap images, and a built-in correction is in the graph
    let uncalibrated = |field: &'static str| -> Result<()> {
        match model.meta.calibration {
            Some(_) => Err(InferError::InvalidParam {
                field,
                got: format!("{} (a calibration built into the graph)", model.path().display()),
                expected: "a model exported without --calibration: the fit to the taps needs corrected tap images, and the correction is inside the graph".into(),
            }),
            None => Ok(()),
        }
    };
    // the fit to the taps: the instrument from the first frame (or its given onset), once
    let templates = match &products.lifetime_fit {
        Some(opts) => {
            uncalibrated("--lifetime-fit")?;
            opts.validate().map_err(|msg| InferError::Settings { what: "--lifetime-fit", msg })?;
            let instrument = estimate_instrument(&first.view(), &model.sensor, opts);
            Some(LifetimeTemplates::new(&model.sensor, instrument, opts))
        }
        None => None,
    };
    let templates = templates.as_ref();
    let need_model = products.need_model();
    let range_fit = products
        .range_fit
        .as_ref()
        .filter(|_| kind == ModelKind::Depth && (products.depth || products.ply) && products.depth_fit.is_none());
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
    let mut infer_seconds = 0.0;
    let result: Result<()> = std::thread::scope(|scope| {
        let (ftx, frx) = sync_channel::<Result<(usize, Array3<f32>, PathBuf)>>(2);
        let (otx, orx) = sync_channel::<(usize, Vec<Array4<f32>>, Option<Array3<f32>>)>(2);
        // reader
        let reader = scope.spawn(move || {
            if ftx.send(Ok((0, first, first_path))).is_err() {
                return;
            }
            for i in 1..frames {
                if cancel.load(Ordering::Relaxed) {
                    return;
                }
                let r = source.read(i, taps).map(|(a, p)| (i, a, p));
                let stop = r.is_err();
                if ftx.send(r).is_err() || stop {
                    return;
                }
            }
        });
        // products + writer
        let writer = scope.spawn(move || -> Result<()> {
            let mut done = 0;
            for (i, mut outs, y) in orx {
                let fitted = templates.zip(y.as_ref()).map(|(tpl, y)| tpl.fit(&y.view()));
                let ranges = range_templates.as_mut().zip(y.as_ref()).map(|(tpl, y)| tpl.fit(&y.view()));
                if let (Some(opts), Some(y)) = (range_fit, y.as_ref()) {
                    // the network's ranges refined in the tap domain (masked first, as the
                    // decoder contract gives them to the fit)
                    let (depth, conf) = outs.split_at_mut(1);
                    mask_depth(&mut depth[0], &conf[0]);
                    refine_ranges(y.view().insert_axis(Axis(0)), sensor, &mut depth[0], opts);
                }
                write_frame(i, outs, fitted, ranges, &mut writers, products, kind, bin_s, t, &peak_opts, out)?;
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
            let (i, y, path) = match msg {
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
            let run = if need_model {
                model.run(y.view().insert_axis(Axis(0)))
            } else {
                model.check(&y.view().insert_axis(Axis(0)), &path.display().to_string()).map(|_| Vec::new())
            };
            let outs = match run {
                Ok(o) => o,
                Err(e) => {
                    status = Err(match e {
                        InferError::InvalidParam { field, got, expected } => {
                            file_err(&path, format!("{field}: got {got}, expected {expected}"))
                        }
                        e => e,
                    });
                    break;
                }
            };
            infer_seconds += ti.elapsed().as_secs_f64();
            if otx.send((i, outs, (templates.is_some() || range_fit.is_some() || depth_fit).then_some(y))).is_err() {
                break;
            }
        }
        drop(otx);
        let _ = reader.join();
        let written = writer.join().unwrap_or_else(|_| Err(file_err(out, "the writer thread panicked")));
        // an early stop drops the writers unfinished (their temporary files removed)
        status.and(written)
    });
    result?;
    Ok(StreamReport { frames, seconds: t0.elapsed().as_secs_f64(), infer_seconds, written })
}

/// Phasors `(g, s)` of every pixel as two planes `[2, H·W]`, flat.
fn planes(phasors: impl Iterator<Item = (f32, f32)>) -> Vec<f32> {
    let (g, s): (Vec<f32>, Vec<f32>) = phasors.unzip();
    g.into_iter().chain(s).collect()
}

/// The products of frame `i` from the model's outputs (`[1, C, H, W]` each).
#[allow(clippy::too_many_arguments)]
fn write_frame(
    i: usize,
    outs: Vec<Array4<f32>>,
    fitted: Option<TapFit>,
    ranges: Option<Array3<f32>>,
    wr: &mut Writers,
    p: &Products,
    kind: ModelKind,
    bin_s: f64,
    bins: usize,
    peak_opts: &PeakOptions,
    out: &Path,
) -> Result<()> {
    let omega = 2.0 * std::f64::consts::PI / (bins as f64 * bin_s);
    if let Some(fit) = &fitted {
        // lifetime, intensity and phasor (one exponential) by the fit to the taps
        if let Some(w) = wr.lifetime.as_mut() {
            w.push(fit.lifetime.iter())?;
        }
        if let Some(w) = wr.intensity.as_mut() {
            w.push(fit.intensity.iter())?;
        }
        if let Some(w) = wr.phasor.as_mut() {
            w.push(planes(fit.lifetime.iter().map(|&t| phasor_of_components(t, t, 1.0, omega))).iter())?;
        }
    }
    let by_model = fitted.is_none();
    if let Some(depth) = &ranges {
        // depth by the template fit: a confidence of 1 where a return was placed
        let confidence = depth.mapv(|d| if d.is_finite() { 1.0f32 } else { 0.0 });
        if let Some(w) = wr.depth.as_mut() {
            w.push(depth.iter())?;
        }
        if let Some(w) = wr.second.as_mut() {
            w.push(confidence.iter())?;
        }
        if p.ply {
            write_ply(&out.join("ply").join(format!("frame_{i:05}.ply")), &depth.view(), &confidence.view(), p.fov_deg)?;
        }
    }
    let depth_by_model = ranges.is_none();
    // the model's outputs: none when every product asked for comes from a fit to the taps
    let Some(first) = outs.first() else { return Ok(()) };
    match kind {
        ModelKind::Cube => {
            let cube: ArrayView3<'_, f32> = first.index_axis(Axis(0), 0);
            if let Some(w) = wr.cube.as_mut() {
                w.push(cube.iter())?;
            }
            if depth_by_model && (p.depth || p.peaks || p.ply) {
                let (depth, amp) = depth_map(&cube, bin_s, peak_opts);
                if let Some(w) = wr.depth.as_mut() {
                    w.push(depth.iter())?;
                }
                if let Some(w) = wr.second.as_mut() {
                    w.push(amp.iter())?;
                }
                if p.ply {
                    write_ply(&out.join("ply").join(format!("frame_{i:05}.ply")), &depth.view(), &amp.view(), p.fov_deg)?;
                }
            }
            if by_model && (p.lifetime || p.phasor) {
                // the reconvolution fit (IRF fitted to the frame)
                let fit = tcsense_fits::lifetime_cube::fit_cube(&cube, bin_s, &tcsense_fits::lifetime_cube::FitOptions::default());
                if let Some(w) = wr.lifetime.as_mut() {
                    w.push(fit.lifetimes.index_axis(Axis(0), 0).iter())?;
                }
                if let Some(w) = wr.phasor.as_mut() {
                    w.push(fit.phasor.iter())?;
                }
            }
            if let Some(w) = wr.intensity.as_mut().filter(|_| by_model) {
                w.push(cube.sum_axis(Axis(0)).iter())?;
            }
        }
        ModelKind::Depth if depth_by_model => {
            let mut depth = outs[0].clone();
            mask_depth(&mut depth, &outs[1]);
            if let Some(w) = wr.depth.as_mut() {
                w.push(depth.iter())?;
            }
            if let Some(w) = wr.second.as_mut() {
                w.push(outs[1].iter())?;
            }
            if p.ply {
                write_ply(
                    &out.join("ply").join(format!("frame_{i:05}.ply")),
                    &depth.index_axis(Axis(0), 0),
                    &outs[1].index_axis(Axis(0), 0),
                    p.fov_deg,
                )?;
            }
        }
        ModelKind::Lifetime if by_model => {
            // lifetime [1, 4, H, W] (τ_m, τ₁, τ₂ in s, α₁), confidence and intensity [1, 1, H, W]
            let mut lifetime = outs[0].clone();
            tcsense_models::net::mask_lifetime(&mut lifetime, &outs[1]);
            let l = lifetime.index_axis(Axis(0), 0);
            if let Some(w) = wr.lifetime.as_mut() {
                w.push(l.index_axis(Axis(0), 0).iter())?;
            }
            if let Some(w) = wr.intensity.as_mut() {
                w.push(outs[2].iter())?;
            }
            if let Some(w) = wr.phasor.as_mut() {
                let (_, h, wd) = l.dim();
                w.push(
                    planes(
                        (0..h * wd)
                            .map(|q| phasor_of_components(l[(1, q / wd, q % wd)], l[(2, q / wd, q % wd)], l[(3, q / wd, q % wd)], omega)),
                    )
                    .iter(),
                )?;
            }
        }
        ModelKind::Lifetime | ModelKind::Depth => {}
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

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
