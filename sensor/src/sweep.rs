//! A laser-delay sweep (paper Fig. 16): tap images of a flat target lit by the laser at known
//! delays over one cycle, plus dark frames (no light) and optionally flat frames (constant
//! light). It is what [`crate::calibration`] measures a real sensor from.
//!
//! On disk a sweep is a directory with a manifest `sweep.json`:
//!
//! ```json
//! {
//!   "format": "tcsense-sweep", "version": 1,
//!   "delays_s": [0.0, 2.06e-10, ...],
//!   "frames": "sweep.npy",
//!   "dark": "dark.npy",
//!   "flat": "flat.npy",
//!   "full_scale": 20000.0,
//!   "units": "electrons"
//! }
//! ```
//!
//! `delays_s` are the laser delays (s) from the start of the code cycle, in `[0, cycle)`; a delay
//! in `[jΔt, (j+1)Δt)` belongs to bin `j`, one within [`crate::calibration::BIN_EDGE_TOLERANCE`]
//! of a bin below the bin's start to that bin, and the frames of one bin are averaged.
//! `frames` is a `.npy` of `[K, M, H, W]` (one frame per delay, usually an average of many),
//! or a list of `K` frames each listing its `M` tap images as 8/16-bit grayscale PNGs. `dark`
//! and `flat` are the same with any number of frames (`[F, M, H, W]` or `[M, H, W]`); they are
//! averaged. `full_scale` is the saturation level in the frames' units (ADC codes:
//! `2^bits − 1`); a frame at or above it is refused. A simulated sweep also records the sensor
//! that produced it (`sensor`: its non-idealities with their seed) and the codes' digest.

use ndarray::{s, Array3, Array4, Axis};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

use crate::codes::Codes;
use crate::error::{Result, SensorError};
use crate::matrix::MeasurementMatrix;
use crate::noise::{derive_seed, Exposure};
use crate::nonideal::{NonIdeal, RealSensor};
use crate::npy::{read_npy, write_bytes, write_npy};
use crate::params::NoiseParams;

/// The `format` of a sweep manifest.
pub const FORMAT: &str = "tcsense-sweep";
/// The version this build writes and reads.
pub const VERSION: u32 = 1;
/// The manifest's file name in a sweep directory.
pub const MANIFEST: &str = "sweep.json";
/// The most exposures averaged per delay in a simulated sweep.
pub const MAX_AVERAGE: usize = 4096;

/// Whether `name` is a file [`simulate_sweep`] writes (so that a rerun may replace them).
fn is_sweep_file(name: &str) -> bool {
    name == MANIFEST
        || ["sweep", "dark", "flat"]
            .iter()
            .any(|s| name == format!("{s}.npy") || (name.starts_with(&format!("{s}_")) && name.ends_with(".png")))
}

/// Frames on disk: one `.npy` stack, or per frame the `M` tap images as PNGs.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum FrameFiles {
    Npy(String),
    Png(Vec<Vec<String>>),
}

/// `sweep.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SweepManifest {
    pub format: String,
    pub version: u32,
    /// Laser delay of each frame (s), from the start of the code cycle.
    pub delays_s: Vec<f64>,
    pub frames: FrameFiles,
    pub dark: FrameFiles,
    #[serde(default)]
    pub flat: Option<FrameFiles>,
    /// Saturation level in the frames' units.
    pub full_scale: f64,
    /// Units of the values: `electrons`, `adc` or `input` (as measurements' sidecars name them).
    pub units: String,
    /// The codes' digest ([`Codes::digest`]), when known.
    #[serde(default)]
    pub codes_digest: Option<String>,
    /// A simulated sweep's sensor (non-idealities and seed).
    #[serde(default)]
    pub sensor: Option<NonIdeal>,
}

/// A sweep in memory.
#[derive(Debug, Clone)]
pub struct Sweep {
    /// Where it was read from (for error messages).
    pub dir: PathBuf,
    pub manifest: SweepManifest,
    /// `[K, M, H, W]`.
    pub frames: Array4<f32>,
    /// Mean dark frame `[M, H, W]`.
    pub dark: Array3<f32>,
    /// Dark frames averaged.
    pub dark_count: usize,
    /// RMS of the dark frames around their mean (the noise of one frame), with ≥ 2 frames.
    pub dark_noise: Option<f64>,
    /// Mean flat frame `[M, H, W]`, when given.
    pub flat: Option<Array3<f32>>,
    pub flat_count: usize,
}

fn file_err(path: &Path, msg: impl Into<String>) -> SensorError {
    SensorError::file(path, msg)
}

/// Read frames `[F, M, H, W]` (a `[M, H, W]` `.npy` is one frame).
fn read_frames(dir: &Path, files: &FrameFiles, field: &str) -> Result<Array4<f32>> {
    let manifest = dir.join(MANIFEST);
    match files {
        FrameFiles::Npy(name) => {
            let path = dir.join(name);
            let a = read_npy(&path)?;
            let shape = a.shape().to_vec();
            let a = match a.ndim() {
                3 => a.insert_axis(Axis(0)),
                4 => a,
                _ => return Err(file_err(&path, format!("{field} frames of shape {shape:?}, expected [F, M, H, W] or [M, H, W]"))),
            };
            let a = a.into_dimensionality().map_err(|e| file_err(&path, e.to_string()))?;
            crate::npy::ensure_finite(&a.view(), field).map_err(|e| e.in_file(&path))?;
            Ok(a)
        }
        FrameFiles::Png(frames) => {
            let Some(first) = frames.first() else {
                return Err(file_err(&manifest, format!("field {field}: no frames listed")));
            };
            let m = first.len();
            let mut out: Option<Array4<f32>> = None;
            for (f, taps) in frames.iter().enumerate() {
                if taps.len() != m || m == 0 {
                    return Err(file_err(
                        &manifest,
                        format!(
                            "field {field}: frame {f} lists {} tap images, frame 0 lists {m}; every frame lists one PNG per tap",
                            taps.len()
                        ),
                    ));
                }
                for (t, name) in taps.iter().enumerate() {
                    let path = dir.join(name);
                    let img = crate::show::read_gray_png(&path)?;
                    let (h, w) = img.dim();
                    let a = out.get_or_insert_with(|| Array4::zeros((frames.len(), m, h, w)));
                    if a.dim().2 != h || a.dim().3 != w {
                        return Err(file_err(
                            &path,
                            format!("image {h}x{w}, expected {}x{} like the first image of {field}", a.dim().2, a.dim().3),
                        ));
                    }
                    a.slice_mut(s![f, t, .., ..]).assign(&img);
                }
            }
            out.ok_or_else(|| file_err(&manifest, format!("field {field}: no frames")))
        }
    }
}

impl SweepManifest {
    /// Parse the text of `path` (a `sweep.json`) and check every field that needs no frame:
    /// format and version, full scale, units, the recorded sensor, the delays.
    pub fn parse(text: &str, path: &Path) -> Result<SweepManifest> {
        let manifest: SweepManifest = serde_json::from_str(text).map_err(|e| file_err(path, format!("not a sweep manifest: {e}")))?;
        if manifest.format != FORMAT || manifest.version != VERSION {
            return Err(file_err(
                path,
                format!("format {:?} version {}; expected {FORMAT:?} version {VERSION}", manifest.format, manifest.version),
            ));
        }
        if !(manifest.full_scale.is_finite() && manifest.full_scale > 0.0) {
            return Err(file_err(
                path,
                format!("field full_scale is {}, expected the positive saturation level of the frames", manifest.full_scale),
            ));
        }
        if crate::sensor::Units::parse(&manifest.units).is_err() {
            return Err(file_err(
                path,
                format!(
                    "field units is {:?}; expected \"electrons\", \"adc\" or \"input\" (the units measurements name in their sidecars)",
                    manifest.units
                ),
            ));
        }
        if let Some(sensor) = &manifest.sensor {
            sensor.validate().map_err(|e| file_err(path, format!("field sensor: {e}")))?;
        }
        if manifest.delays_s.is_empty() {
            return Err(file_err(path, "field delays_s is empty; expected one laser delay (s) per frame"));
        }
        if let Some((i, d)) = manifest.delays_s.iter().enumerate().find(|(_, d)| !d.is_finite()) {
            return Err(file_err(path, format!("field delays_s[{i}] is {d}, expected a finite delay in seconds")));
        }
        Ok(manifest)
    }
}

impl Sweep {
    /// Read a sweep directory; errors name the file and the field.
    pub fn load(dir: &Path) -> Result<Self> {
        let path = dir.join(MANIFEST);
        let text = std::fs::read_to_string(&path).map_err(|e| SensorError::io(&path, e))?;
        let manifest = SweepManifest::parse(&text, &path)?;
        let frames = read_frames(dir, &manifest.frames, "frames")?;
        if frames.dim().0 != manifest.delays_s.len() {
            return Err(file_err(
                &path,
                format!(
                    "field delays_s lists {} delays, but frames holds {} frames; one delay per frame",
                    manifest.delays_s.len(),
                    frames.dim().0
                ),
            ));
        }
        let (_, m, h, w) = frames.dim();
        let same = |a: &Array4<f32>, field: &str| -> Result<()> {
            let (_, am, ah, aw) = a.dim();
            if (am, ah, aw) != (m, h, w) {
                return Err(file_err(
                    &path,
                    format!("field {field}: frames of [M, H, W] = [{am}, {ah}, {aw}], the sweep's are [{m}, {h}, {w}]"),
                ));
            }
            Ok(())
        };
        let dark = read_frames(dir, &manifest.dark, "dark")?;
        same(&dark, "dark")?;
        let flat = manifest.flat.as_ref().map(|f| read_frames(dir, f, "flat")).transpose()?;
        if let Some(f) = &flat {
            same(f, "flat")?;
        }
        let mean = |a: &Array4<f32>| a.mean_axis(Axis(0)).expect("at least one frame");
        let dark_mean = mean(&dark);
        let dark_noise = (dark.dim().0 >= 2).then(|| {
            let ss: f64 = dark.outer_iter().map(|f| (&f - &dark_mean).iter().map(|&v| (v as f64).powi(2)).sum::<f64>()).sum();
            (ss / ((dark.len() - dark_mean.len()) as f64)).sqrt()
        });
        Ok(Sweep {
            dark_noise,
            dir: dir.to_path_buf(),
            dark_count: dark.dim().0,
            dark: dark_mean,
            flat_count: flat.as_ref().map_or(0, |f| f.dim().0),
            flat: flat.as_ref().map(mean),
            frames,
            manifest,
        })
    }
}

/// How to simulate a sweep.
#[derive(Debug, Clone, PartialEq)]
pub struct SweepSettings {
    /// Frame size `(H, W)`.
    pub size: (usize, usize),
    /// Frames averaged per delay, and dark and flat frames taken.
    pub average: usize,
    /// Noise (the sweep is recorded in electrons or ADC codes of this noise model).
    pub noise: NoiseParams,
    /// Noise on (else the mean frames).
    pub noisy: bool,
    /// Write ADC codes instead of electrons.
    pub adc: bool,
    /// Write the frames as 16-bit PNGs instead of `.npy`.
    pub png: bool,
    /// Peak of the sweep as a fraction of the full well.
    pub level: f64,
    pub seed: u64,
}

/// Simulate a sweep of the sensor `a` with the non-idealities `sensor` (its truth recorded in
/// the manifest) and write it to `dir`. The delays sit at the centres of the `T` bins: the model
/// knows the response only per bin (a real sweep may sample finer; calibration averages the
/// delays that fall in each bin). Returns the manifest.
pub fn simulate_sweep(
    a: &MeasurementMatrix,
    codes: &Codes,
    sensor: &NonIdeal,
    settings: &SweepSettings,
    dir: &Path,
) -> Result<SweepManifest> {
    let (h, w) = settings.size;
    if settings.average == 0 {
        return Err(crate::error::invalid("frames averaged", 0, "at least 1"));
    }
    if settings.average > MAX_AVERAGE {
        return Err(crate::error::invalid("frames averaged", settings.average, format!("at most {MAX_AVERAGE}")));
    }
    if !(settings.level > 0.0 && settings.level < 1.0) {
        return Err(crate::error::invalid("sweep level", settings.level, "a fraction of the full well in (0, 1)"));
    }
    let (bh, bw) = codes.block();
    if h == 0 || w == 0 || h % bh != 0 || w % bw != 0 {
        return Err(crate::error::invalid("size", format!("{h}x{w}"), format!("a frame of whole {bh}x{bw} blocks, at least one")));
    }
    // the working set before anything is allocated: the sweep, dark and flat stacks, one
    // delay's exposures, the scene and the realised sensor's per-pixel maps (f32)
    let (tf, mf, avg) = (a.bins() as f64, a.taps() as f64, settings.average as f64);
    let per_pixel = 4.0 * (tf * mf + 4.0 * avg * mf + 2.0 * tf + 8.0 * mf);
    crate::mem::check_fits(
        &format!("a {h}x{w} sweep of {} delays", a.bins()),
        per_pixel * h as f64 * w as f64,
        "use a smaller --size or --average",
    )?;
    let real: RealSensor = sensor.realise(a, h, w)?;
    let t = a.bins();
    let dt = a.bin_width_s();
    let noise = settings.noise.validate()?;
    // electrons per unit so that the brightest tap of the whole sweep (gains included) sits at `level`
    let gmax = real.gain.iter().fold(0f32, |m, &v| m.max(v)) as f64;
    let peak = real.matrix.a().iter().fold(0f32, |m, &v| m.max(v)) as f64 * gmax;
    let electrons_per_unit = settings.level * noise.full_well_e / peak.max(f64::MIN_POSITIVE);
    let exposure = Exposure::ElectronsPerUnit(electrons_per_unit);
    let lsb = if noise.adc_bits > 0 { noise.full_well_e / ((1u64 << noise.adc_bits) - 1) as f64 } else { 1.0 };
    let units = if settings.adc { "adc" } else { "electrons" };
    let scale = if settings.adc { 1.0 / lsb } else { 1.0 } as f32;
    // `average` exposures of a cube, each with its own noise stream; the sweep keeps their mean
    // per delay, the dark and flat frames one by one (their scatter is the noise of one frame)
    let singles = |x: &Array4<f32>, stream: u64| -> Result<Array4<f32>> {
        let mut out = Array4::<f32>::zeros((settings.average, a.taps(), h, w));
        for r in 0..settings.average {
            let e = real.measure(&x.view(), &noise, settings.noisy, exposure, derive_seed(settings.seed, stream * 100_003 + r as u64))?;
            let e = e
                .electrons
                .index_axis_move(Axis(0), 0)
                .into_dimensionality::<ndarray::Ix3>()
                .map_err(|e| crate::error::invalid("frame", "[M, H, W]", e.to_string()))?;
            out.slice_mut(s![r, .., .., ..]).assign(&e.mapv(|v| v * scale));
        }
        Ok(out)
    };
    let mut frames = Array4::<f32>::zeros((t, a.taps(), h, w));
    let mut delays = Vec::with_capacity(t);
    for j in 0..t {
        let mut x = Array4::<f32>::zeros((1, t, h, w));
        x.slice_mut(s![0, j, .., ..]).fill(1.0);
        frames.slice_mut(s![j, .., .., ..]).assign(&singles(&x, j as u64 + 1)?.mean_axis(Axis(0)).expect("at least one exposure"));
        delays.push((j as f64 + 0.5) * dt);
    }
    let dark = singles(&Array4::zeros((1, t, h, w)), 0)?;
    // flat: constant light, the brightest tap at half the sweep's level
    let row = real.matrix.a().sum_axis(Axis(2)).iter().fold(0f32, |m, &v| m.max(v)) as f64;
    let flat_level = 0.5 * settings.level * noise.full_well_e / (electrons_per_unit * gmax * row.max(f64::MIN_POSITIVE));
    let flat = singles(&Array4::from_elem((1, t, h, w), flat_level as f32), t as u64 + 1)?;
    let full_scale = if settings.adc { noise.full_well_e / lsb } else { noise.full_well_e };
    if settings.png && full_scale > 65535.0 {
        return Err(crate::error::invalid(
            "PNG sweep",
            format!("full scale {full_scale}"),
            "at most 65535 (write ADC codes of ≤ 16 bits, or .npy)",
        ));
    }
    // written whole: an earlier sweep's files (another size, PNGs instead of .npy) never remain
    crate::output::replace_dir(dir, &is_sweep_file, |dir| {
        write_sweep(dir, settings, codes, sensor, delays, [&frames, &dark, &flat], full_scale, units)
    })
}

/// The files of a simulated sweep in `dir`.
#[allow(clippy::too_many_arguments)]
fn write_sweep(
    dir: &Path,
    settings: &SweepSettings,
    codes: &Codes,
    sensor: &NonIdeal,
    delays: Vec<f64>,
    [frames, dark, flat]: [&Array4<f32>; 3],
    full_scale: f64,
    units: &str,
) -> Result<SweepManifest> {
    // a stack of frames [F, M, H, W]: one .npy, or one PNG per frame and tap
    let files = |name: &str, stack: &Array4<f32>| -> Result<FrameFiles> {
        if settings.png {
            let mut list = Vec::new();
            for (f, frame) in stack.outer_iter().enumerate() {
                let mut taps = Vec::new();
                for (m, img) in frame.outer_iter().enumerate() {
                    let file = format!("{name}_{f:03}_tap{m}.png");
                    crate::show::write_gray_png16(&dir.join(&file), &img)?;
                    taps.push(file);
                }
                list.push(taps);
            }
            Ok(FrameFiles::Png(list))
        } else {
            let file = format!("{name}.npy");
            write_npy(&dir.join(&file), &stack.view())?;
            Ok(FrameFiles::Npy(file))
        }
    };
    let manifest = SweepManifest {
        format: FORMAT.into(),
        version: VERSION,
        delays_s: delays,
        frames: files("sweep", frames)?,
        dark: files("dark", dark)?,
        flat: Some(files("flat", flat)?),
        full_scale,
        units: units.into(),
        codes_digest: Some(codes.digest()),
        sensor: Some(*sensor),
    };
    let text = serde_json::to_string_pretty(&manifest).map_err(|e| file_err(&dir.join(MANIFEST), e.to_string()))?;
    write_bytes(&dir.join(MANIFEST), (text + "\n").as_bytes())?;
    Ok(manifest)
}
