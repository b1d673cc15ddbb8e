//! Calibration of a real sensor from a delay sweep ([`crate::sweep`]): the dark offset and
//! gain maps per pixel and tap, and the measured matrix `A [N, M, T]` with the response shape,
//! tap gains, crosstalk, diffusion tail and drift the nominal model leaves out.
//!
//! Model of a sweep frame at delay `τ_k` in bin `j` (pixel `p` of subpixel type `n`):
//! `S_k[m, p] = κ · G[m, p] · A[n, m, j] + d[m, p]` (+ noise), with `κ` the laser's brightness.
//!
//! 1. `d` = the mean dark frame.
//! 2. `R[m, j, p]` = mean over the delays in bin `j` of `S_k − d`; every bin needs a delay.
//! 3. `G[m, p]` = the pixel's response (the mean flat frame minus `d` when given, else
//!    `Σ_j R[m, j, p]`) over the mean response of its `(n, m)` class: mean 1 per class, so the
//!    tap gains stay in `A`. Classes with (almost) no response keep `G = 1`.
//! 4. `A[n, m, j]` = mean over the pixels of type `n` of `R[m, j, p] / G[m, p]`, scaled so that
//!    `Σ A` equals the nominal `Σ A` (the laser's brightness `κ` is unknown; this keeps the
//!    calibrated model on the nominal one's scale, where the decoders were trained).
//!
//! Applying it: raw tap images `y` become `(y − d) / G` and are decoded with the calibrated `A`
//! ([`Calibration::correct`]). The result is a directory (`calibration.json`, `A.npy`,
//! `gain.npy`, `dark.npy`, `residual.npy`), written to a temporary directory first and
//! renamed into place, so an error never leaves half of one.

use crate::waveform::subpixel;
use ndarray::{s, Array2, Array3, Array4, ArrayView4, Axis};
use serde::{Deserialize, Serialize};
use std::path::Path;

use crate::codes::Codes;
use crate::error::{Result, SensorError};
use crate::matrix::MeasurementMatrix;
use crate::npy::{read_npy, write_bytes, write_npy};
use crate::params::Sampling;
use crate::sidecar::Sidecar;
use crate::sweep::Sweep;

/// The `format` of `calibration.json`.
pub const FORMAT: &str = "tcsense-calibration";
/// The version this build writes and reads.
pub const VERSION: u32 = 1;
/// The description's file name.
pub const DESCRIPTION: &str = "calibration.json";

/// A class whose response is below this share of the strongest class's keeps unit gain.
const WEAK_CLASS: f64 = 1e-3;
/// Frames at or above this share of the full scale count as saturated.
const SATURATED: f64 = 0.999;

/// A sweep delay within this share of a bin below the bin's start is assigned to that bin
/// (floating-point rounding of delays set on the bins' edges must not decide the bin).
pub const BIN_EDGE_TOLERANCE: f64 = 1e-6;

/// `calibration.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CalibrationMeta {
    pub format: String,
    pub version: u32,
    /// Taps `M`.
    pub taps: usize,
    /// Code block `[bh, bw]`.
    pub block: [usize; 2],
    /// Masks `L` per cycle.
    pub length: usize,
    pub clock_hz: f64,
    pub sampling: Sampling,
    /// Bins `T`.
    pub bins: usize,
    pub bin_width_s: f64,
    /// Frame size `[H, W]` of the gain and dark maps.
    pub size: [usize; 2],
    /// [`Codes::digest`] of the codes the sweep was taken with.
    pub codes_digest: String,
    /// Digest of the nominal `A` (codes, IRF, sampling) it was calibrated against.
    pub nominal_digest: String,
    /// Digest of the calibrated `A`.
    pub matrix_digest: String,
    /// Units of the raw tap images (those of the sweep).
    pub units: String,
    /// Saturation level of the raw tap images.
    pub full_scale: f64,
    /// Delays, dark frames and flat frames used.
    pub delays: usize,
    pub dark_frames: usize,
    pub flat_frames: usize,
    /// Tap gains relative to the nominal model, `Σ_{n,j} A[n, m, j] / Σ A_nominal[n, m, j]`
    /// normalised to mean 1 (crosstalk and tail move charge between taps too).
    pub tap_gains: Vec<f64>,
    /// RMS of the fit's residual relative to the sweep's peak response.
    pub residual_rms: f64,
    /// RMS of the dark frames around their mean, relative to the sweep's peak (the noise of a
    /// single frame; `null` with one dark frame).
    pub dark_noise_rms: Option<f64>,
    /// The sweep directory it was made from.
    pub sweep: String,
    /// Files, relative to the directory.
    pub files: CalibrationFiles,
}

/// The arrays of a calibration directory.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CalibrationFiles {
    /// `A [N, M, T]`.
    pub matrix: String,
    /// `G [M, H, W]`.
    pub gain: String,
    /// `d [M, H, W]`, raw units.
    pub dark: String,
    /// RMS residual per pixel `[H, W]`, relative to the sweep's peak.
    pub residual: String,
}

/// A calibration in memory.
#[derive(Debug, Clone)]
pub struct Calibration {
    pub meta: CalibrationMeta,
    /// The calibrated `A`.
    pub matrix: MeasurementMatrix,
    /// `G [M, H, W]`.
    pub gain: Array3<f32>,
    /// `d [M, H, W]`.
    pub dark: Array3<f32>,
    /// `[H, W]`.
    pub residual: Array2<f32>,
    /// The mean response per pixel, `R [T, M, H, W]` (for the report; not saved).
    pub response: Option<Array4<f32>>,
}

fn err(path: &Path, msg: impl Into<String>) -> SensorError {
    SensorError::file(path, msg)
}

/// The checks on tap images stored in `y` (`.npy`) before they are decoded, as `tcsense
/// reconstruct` and the Python module make them: their sidecar, when there is one, must name
/// the codes, sampling and matrix of `nominal`; with a calibration, their units must be its
/// sweep's (its dark offsets are subtracted in those units).
pub fn check_measurements_file(y: &Path, nominal: &MeasurementMatrix, codes: &Codes, calibration: Option<&Calibration>) -> Result<()> {
    let Some(meta) = Sidecar::read_for(y)? else { return Ok(()) };
    let path = Sidecar::path_for(y);
    meta.check(&path, nominal, Some(codes))?;
    match calibration {
        Some(cal) if meta.units != cal.meta.units => Err(SensorError::File {
            msg: format!("the measurements are in {:?} (field units), the calibration's dark offsets in {:?}; simulate or record them in the units of the sweep", meta.units, cal.meta.units),
            path,
        }),
        _ => Ok(()),
    }
}

/// Calibrate the sensor of `nominal` (from `codes` under `sampling`) from `sweep`.
pub fn calibrate(sweep: &Sweep, nominal: &MeasurementMatrix, codes: &Codes, sampling: Sampling) -> Result<Calibration> {
    let manifest_path = sweep.dir.join(crate::sweep::MANIFEST);
    let (k, m, h, w) = sweep.frames.dim();
    let (n, t) = (nominal.subpixels(), nominal.bins());
    let (bh, bw) = nominal.block();
    if m != nominal.taps() {
        return Err(err(&manifest_path, format!("frames have {m} tap images, the sensor (codes) has M = {}", nominal.taps())));
    }
    if h == 0 || w == 0 || h % bh != 0 || w % bw != 0 {
        return Err(err(&manifest_path, format!("frames are {h}x{w}, expected a non-zero multiple of the {bh}x{bw} code block")));
    }
    if let Some(d) = &sweep.manifest.codes_digest {
        if *d != codes.digest() {
            return Err(err(
                &manifest_path,
                format!("field codes_digest {d}: the sweep was taken with other codes than these ({})", codes.digest()),
            ));
        }
    }
    // saturation: a clipped frame says nothing about the response
    let limit = (SATURATED * sweep.manifest.full_scale) as f32;
    for (i, frame) in sweep.frames.outer_iter().enumerate() {
        let over = frame.iter().filter(|&&v| v >= limit).count();
        if over > 0 {
            return Err(err(&manifest_path, format!("frame {i} (delay {:.4} ns) is saturated: {over} values at or above full_scale {}; lower the laser power or the exposure", sweep.manifest.delays_s[i] * 1e9, sweep.manifest.full_scale)));
        }
    }
    if let Some(f) = &sweep.flat {
        let over = f.iter().filter(|&&v| v >= limit).count();
        if over > 0 {
            return Err(err(
                &manifest_path,
                format!("field flat: the mean flat frame is saturated in {over} values (full_scale {})", sweep.manifest.full_scale),
            ));
        }
    }
    // delays → bins, covering the whole cycle
    let dt = nominal.bin_width_s();
    let cycle = dt * t as f64;
    let mut count = vec![0usize; t];
    let mut bin_of = Vec::with_capacity(k);
    for (i, &d) in sweep.manifest.delays_s.iter().enumerate() {
        if !(0.0..cycle).contains(&d) {
            return Err(err(
                &manifest_path,
                format!("field delays_s[{i}] = {:.4} ns lies outside the code cycle [0, {:.4}) ns", d * 1e9, cycle * 1e9),
            ));
        }
        // a delay a rounding error below a bin's start belongs to that bin: settings on bin
        // edges (j·Δt computed in floating point) must not land in the bin before
        let j = ((d / dt + BIN_EDGE_TOLERANCE).floor() as usize).min(t - 1);
        count[j] += 1;
        bin_of.push(j);
    }
    let missing: Vec<usize> = (0..t).filter(|&j| count[j] == 0).collect();
    if !missing.is_empty() {
        let show: Vec<String> =
            missing.iter().take(8).map(|j| format!("{:.3}–{:.3} ns", *j as f64 * dt * 1e9, (*j + 1) as f64 * dt * 1e9)).collect();
        return Err(err(
            &manifest_path,
            format!("field delays_s does not cover the cycle: {} of the {t} bins ({:.1} ps each) have no delay, e.g. {}; sweep the delay over the whole {:.3} ns cycle", missing.len(), dt * 1e12, show.join(", "), cycle * 1e9),
        ));
    }
    // R [T, M, H, W]: mean response per bin, dark subtracted
    let mut r = Array4::<f32>::zeros((t, m, h, w));
    for (i, frame) in sweep.frames.outer_iter().enumerate() {
        let j = bin_of[i];
        let mut dst = r.slice_mut(s![j, .., .., ..]);
        dst.zip_mut_with(&frame, |acc, &v| *acc += v / count[j] as f32);
    }
    for mut slice in r.outer_iter_mut() {
        slice -= &sweep.dark;
    }
    // the pixel's response to constant light
    let response: Array3<f32> = match &sweep.flat {
        Some(f) => f - &sweep.dark,
        None => r.sum_axis(Axis(0)),
    };
    let ty = |i: usize, j: usize| subpixel(i, j, (bh, bw));
    let mut class_mean = Array2::<f64>::zeros((n, m));
    let mut class_count = vec![0usize; n];
    for i in 0..h {
        for j in 0..w {
            class_count[ty(i, j)] += 1;
            for c in 0..m {
                class_mean[(ty(i, j), c)] += response[(c, i, j)] as f64;
            }
        }
    }
    for (q, row) in class_mean.outer_iter_mut().enumerate() {
        let cnt = class_count[q].max(1) as f64;
        row.into_iter().for_each(|v| *v /= cnt);
    }
    let strongest = class_mean.iter().fold(0f64, |a, &b| a.max(b.abs()));
    if strongest <= 0.0 {
        return Err(err(&manifest_path, "the sweep shows no response above the dark frames; was the laser on?"));
    }
    let mut gain = Array3::<f32>::ones((m, h, w));
    for c in 0..m {
        for i in 0..h {
            for j in 0..w {
                let cm = class_mean[(ty(i, j), c)];
                if cm > WEAK_CLASS * strongest {
                    gain[(c, i, j)] = (response[(c, i, j)] as f64 / cm) as f32;
                }
            }
        }
    }
    if let Some(((c, i, j), g)) = gain.indexed_iter().find(|(_, g)| !(g.is_finite() && **g > 0.0)) {
        return Err(err(
            &manifest_path,
            format!(
                "pixel ({i}, {j}) tap {c} has gain {g}: no response to the light (a dead pixel, or dark frames brighter than the light)"
            ),
        ));
    }
    // A [N, M, T]: the class mean of R / G
    let mut a = Array3::<f64>::zeros((n, m, t));
    for jt in 0..t {
        for c in 0..m {
            for i in 0..h {
                for j in 0..w {
                    a[(ty(i, j), c, jt)] += (r[(jt, c, i, j)] / gain[(c, i, j)]) as f64 / class_count[ty(i, j)] as f64;
                }
            }
        }
    }
    let kappa = a.sum() / nominal.a().iter().map(|&v| v as f64).sum::<f64>();
    if !(kappa.is_finite() && kappa > 0.0) {
        return Err(err(&manifest_path, "the sweep's total response is not positive; check the dark frames"));
    }
    a.mapv_inplace(|v| v / kappa);
    // residual of the model κ·G·A against R, per pixel, relative to the peak response
    let peak = r.iter().fold(0f32, |p, &v| p.max(v.abs())) as f64;
    let mut residual = Array2::<f32>::zeros((h, w));
    for i in 0..h {
        for j in 0..w {
            let mut ss = 0.0;
            for jt in 0..t {
                for c in 0..m {
                    let model = kappa * gain[(c, i, j)] as f64 * a[(ty(i, j), c, jt)];
                    ss += (r[(jt, c, i, j)] as f64 - model).powi(2);
                }
            }
            residual[(i, j)] = ((ss / (t * m) as f64).sqrt() / peak) as f32;
        }
    }
    let residual_rms = (residual.iter().map(|&v| (v as f64).powi(2)).sum::<f64>() / (h * w) as f64).sqrt();
    let matrix = nominal.with_values(a.mapv(|v| v as f32))?;
    let tap_gains = {
        let nom = nominal.a();
        let raw: Vec<f64> = (0..m)
            .map(|c| {
                let got: f64 = matrix.a().slice(s![.., c, ..]).iter().map(|&v| v as f64).sum();
                let want: f64 = nom.slice(s![.., c, ..]).iter().map(|&v| v as f64).sum();
                if want > 0.0 {
                    got / want
                } else {
                    f64::NAN
                }
            })
            .collect();
        let mean = raw.iter().filter(|v| v.is_finite()).sum::<f64>() / raw.iter().filter(|v| v.is_finite()).count().max(1) as f64;
        raw.iter().map(|v| v / mean).collect()
    };
    let dark_noise_rms = sweep.dark_noise.map(|n| n / peak);
    let meta = CalibrationMeta {
        format: FORMAT.into(),
        version: VERSION,
        taps: m,
        block: [bh, bw],
        length: codes.length(),
        clock_hz: codes.clock_hz,
        sampling,
        bins: t,
        bin_width_s: dt,
        size: [h, w],
        codes_digest: codes.digest(),
        nominal_digest: nominal.digest(),
        matrix_digest: matrix.digest(),
        units: sweep.manifest.units.clone(),
        full_scale: sweep.manifest.full_scale,
        delays: k,
        dark_frames: sweep.dark_count,
        flat_frames: sweep.flat_count,
        tap_gains,
        residual_rms,
        dark_noise_rms,
        sweep: sweep.dir.display().to_string(),
        files: CalibrationFiles {
            matrix: "A.npy".into(),
            gain: "gain.npy".into(),
            dark: "dark.npy".into(),
            residual: "residual.npy".into(),
        },
    };
    Ok(Calibration { meta, matrix, gain, dark: sweep.dark.clone(), residual, response: Some(r) })
}

impl Calibration {
    /// Write the calibration directory `dir` (replacing one that is there, whole). Everything
    /// is written into a temporary directory next to it first and renamed into place; a
    /// directory holding files a calibration does not write (its arrays, description, report
    /// page and figures) is refused, never replaced.
    pub fn save(&self, dir: &Path) -> Result<()> {
        let ours = |n: &str| n == DESCRIPTION || n == "report.html" || n.ends_with(".npy") || n.ends_with(".png");
        crate::output::replace_dir(dir, &ours, |tmp| -> Result<()> {
            self.matrix.save(&tmp.join(&self.meta.files.matrix))?;
            write_npy(&tmp.join(&self.meta.files.gain), &self.gain.view())?;
            write_npy(&tmp.join(&self.meta.files.dark), &self.dark.view())?;
            write_npy(&tmp.join(&self.meta.files.residual), &self.residual.view())?;
            let text = serde_json::to_string_pretty(&self.meta).map_err(|e| err(&tmp.join(DESCRIPTION), e.to_string()))?;
            write_bytes(&tmp.join(DESCRIPTION), (text + "\n").as_bytes())
        })
    }

    /// Read a calibration directory for the sensor `nominal` (of `codes`): the codes must be
    /// those of the sweep and the geometry that of the sensor. Errors name the file and field.
    pub fn load(dir: &Path, nominal: &MeasurementMatrix, codes: &Codes) -> Result<Self> {
        let path = dir.join(DESCRIPTION);
        let text = std::fs::read_to_string(&path).map_err(|e| SensorError::io(&path, e))?;
        let meta: CalibrationMeta = serde_json::from_str(&text).map_err(|e| err(&path, format!("not a calibration description: {e}")))?;
        if meta.format != FORMAT || meta.version != VERSION {
            return Err(err(&path, format!("format {:?} version {}; expected {FORMAT:?} version {VERSION}", meta.format, meta.version)));
        }
        if meta.codes_digest != codes.digest() {
            return Err(err(
                &path,
                format!(
                    "field codes_digest {}: the sensor was calibrated with other codes than {} ({})",
                    meta.codes_digest,
                    "these",
                    codes.digest()
                ),
            ));
        }
        let (bh, bw) = nominal.block();
        if meta.taps != nominal.taps() || meta.block != [bh, bw] || meta.bins != nominal.bins() {
            return Err(err(
                &path,
                format!(
                    "fields taps/block/bins are {}/{:?}/{}, the sensor's {}/{:?}/{} (check --oversample/--heterodyne)",
                    meta.taps,
                    meta.block,
                    meta.bins,
                    nominal.taps(),
                    [bh, bw],
                    nominal.bins()
                ),
            ));
        }
        let a = read_npy(&dir.join(&meta.files.matrix))?;
        let shape = a.shape().to_vec();
        let a = a.into_dimensionality().map_err(|_| err(&dir.join(&meta.files.matrix), format!("shape {shape:?}, expected [N, M, T]")))?;
        let matrix = nominal.with_values(a).map_err(|e| e.in_file(&dir.join(&meta.files.matrix)))?;
        let map = |name: &str, want: &[usize]| -> Result<ndarray::ArrayD<f32>> {
            let p = dir.join(name);
            let v = read_npy(&p)?;
            if v.shape() != want {
                return Err(err(&p, format!("shape {:?}, expected {want:?}", v.shape())));
            }
            Ok(v)
        };
        let [h, w] = meta.size;
        let gain: Array3<f32> = map(&meta.files.gain, &[meta.taps, h, w])?.into_dimensionality().map_err(|e| err(dir, e.to_string()))?;
        if let Some(((c, i, j), g)) = gain.indexed_iter().find(|(_, g)| !(g.is_finite() && **g > 0.0)) {
            return Err(err(&dir.join(&meta.files.gain), format!("gain of pixel ({i}, {j}) tap {c} is {g}, expected a positive number")));
        }
        let dark = map(&meta.files.dark, &[meta.taps, h, w])?.into_dimensionality().map_err(|e| err(dir, e.to_string()))?;
        let residual = map(&meta.files.residual, &[h, w])?.into_dimensionality().map_err(|e| err(dir, e.to_string()))?;
        Ok(Calibration { meta, matrix, gain, dark, residual, response: None })
    }

    /// Raw tap images → corrected ones, `(y − d) / G`.
    ///
    /// # Shapes
    /// - `y`: `[B, M, H, W]` with `(H, W)` the calibration's size → `[B, M, H, W]`
    pub fn correct(&self, y: &ArrayView4<'_, f32>) -> Result<Array4<f32>> {
        let (_, m, h, w) = y.dim();
        let [ch, cw] = self.meta.size;
        if m != self.meta.taps || (h, w) != (ch, cw) {
            return Err(SensorError::Shape {
                what: "tap images to correct".into(),
                got: y.shape().to_vec(),
                expected: format!(
                    "[B, {}, {ch}, {cw}]: the calibration's taps and frame size (gain and dark maps are per pixel)",
                    self.meta.taps
                ),
            });
        }
        let mut out = y.to_owned();
        for mut frame in out.outer_iter_mut() {
            frame -= &self.dark;
            frame /= &self.gain;
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::codes::{CodeShape, Constraints};
    use crate::generate::random_codes;
    use crate::nonideal::NonIdeal;
    use crate::params::{Irf, NoiseParams, SensorParams};
    use crate::sweep::{simulate_sweep, SweepSettings};

    fn sensor() -> (Codes, MeasurementMatrix) {
        let shape = CodeShape { bh: 2, bw: 2, taps: 4, length: 16, drain: false };
        let codes = random_codes(shape, 607e6, Constraints { tap: true, ..Default::default() }, 3).unwrap();
        let spec = SensorParams { irf: Irf::Physical { laser_fwhm_s: 0.8e-9, tap_tau_s: 0.3e-9 }, ..SensorParams::from_codes(&codes) }
            .validate()
            .unwrap();
        let a = MeasurementMatrix::synthesize(&codes, &spec).unwrap();
        (codes, a)
    }

    #[test]
    fn a_simulated_sweep_calibrates_back_to_its_sensor() {
        let (codes, a) = sensor();
        let truth = NonIdeal {
            tap_gain: 0.05,
            prnu: 0.02,
            dark: 0.01,
            dark_fpn: 0.002,
            crosstalk: 0.02,
            tail: 0.25,
            tail_tau_s: 0.4e-9,
            shift_s: 0.05e-9,
            gate_skew_s: 0.1e-9,
            seed: 11,
            ..NonIdeal::default()
        };
        let dir = tempfile::tempdir().unwrap();
        let settings = SweepSettings {
            size: (8, 8),
            average: 256,
            noise: NoiseParams::default(),
            noisy: true,
            adc: false,
            png: false,
            level: 0.7,
            seed: 2,
        };
        simulate_sweep(&a, &codes, &truth, &settings, dir.path()).unwrap();
        let sweep = Sweep::load(dir.path()).unwrap();
        let cal = calibrate(&sweep, &a, &codes, Sampling::Oversample(1)).unwrap();
        let real = truth.realise(&a, 8, 8).unwrap();
        // per-pixel gains: the true PRNU normalised per (subpixel type, tap) class, within 1 %
        let (mut worst, mut ss) = (0f64, 0f64);
        for c in 0..4 {
            for q in 0..4 {
                let px: Vec<(usize, usize)> =
                    (0..8).flat_map(|i| (0..8).map(move |j| (i, j))).filter(|(i, j)| (i % 2) * 2 + j % 2 == q).collect();
                let mean = px.iter().map(|&(i, j)| real.gain[(c, i, j)] as f64).sum::<f64>() / px.len() as f64;
                for &(i, j) in &px {
                    let e = (cal.gain[(c, i, j)] as f64 - real.gain[(c, i, j)] as f64 / mean).abs();
                    worst = worst.max(e);
                    ss += e * e;
                }
            }
        }
        let rms = (ss / 256.0).sqrt();
        assert!(worst < 0.01 && rms < 0.004, "gain map off by {worst} at worst, {rms} RMS");
        // dark offsets to a fraction of the dark level
        let dark_e = real.dark_electrons(&NoiseParams::default());
        let derr = (&cal.dark - &dark_e).mapv(f32::abs).iter().fold(0f32, |p, &v| p.max(v));
        assert!(derr < 0.05 * 200.0, "dark off by {derr} e⁻");
        // A: the true A' up to the brightness κ (fixed by the nominal scale), within the sweep's noise
        let scale = real.matrix.a().sum() / cal.matrix.a().sum();
        let peak = real.matrix.a().iter().fold(0f32, |p, &v| p.max(v));
        let aerr = (&cal.matrix.a().mapv(|v| v * scale) - &real.matrix.a()).mapv(f32::abs).iter().fold(0f32, |p, &v| p.max(v)) / peak;
        assert!(aerr < 0.01, "A off by {aerr} of its peak");
        // and much further from the nominal A (the calibration found something)
        let nerr = (&a.a().mapv(|v| v * real.matrix.a().sum() / a.a().sum()) - &real.matrix.a())
            .mapv(f32::abs)
            .iter()
            .fold(0f32, |p, &v| p.max(v))
            / peak;
        assert!(nerr > 5.0 * aerr, "nominal {nerr} vs calibrated {aerr}");
        // tap gains (crosstalk mixes 2 %: within 1 % of the true gains)
        let g = truth.tap_gains(4);
        let gm = g.iter().sum::<f64>() / 4.0;
        for (c, (&got, want)) in cal.meta.tap_gains.iter().zip(&g).enumerate() {
            assert!((got - want / gm).abs() < 0.01, "tap {c}: {got} vs {}", want / gm);
        }
        assert!(cal.meta.residual_rms < 0.01, "residual {}", cal.meta.residual_rms);
        // round trip through the directory
        let out = dir.path().join("cal");
        cal.save(&out).unwrap();
        let back = Calibration::load(&out, &a, &codes).unwrap();
        assert_eq!((back.matrix, back.gain, back.dark), (cal.matrix.clone(), cal.gain.clone(), cal.dark.clone()));
    }

    /// Delays on the bins' edges, one ulp low (as `j·Δt` in floating point can come out), and
    /// two delays per bin: each bin gets its own (the old `floor` put bin j's delay in bin j − 1
    /// and refused the sweep: "bins have no delay"), and the two frames of a bin are averaged.
    #[test]
    fn delays_a_rounding_error_below_a_bin_edge_belong_to_that_bin() {
        let (codes, a) = sensor();
        let dir = tempfile::tempdir().unwrap();
        let settings = SweepSettings {
            size: (4, 4),
            average: 1,
            noise: NoiseParams::default(),
            noisy: false,
            adc: false,
            png: false,
            level: 0.7,
            seed: 0,
        };
        simulate_sweep(&a, &codes, &NonIdeal::default(), &settings, dir.path()).unwrap();
        let centred = Sweep::load(dir.path()).unwrap();
        let want = calibrate(&centred, &a, &codes, Sampling::Oversample(1)).unwrap();
        let dt = a.bin_width_s();
        let mut edges = centred.clone();
        edges.manifest.delays_s = (0..a.bins()).map(|j| if j == 0 { 0.0 } else { f64::from_bits((j as f64 * dt).to_bits() - 1) }).collect();
        let got = calibrate(&edges, &a, &codes, Sampling::Oversample(1)).unwrap();
        assert_eq!(got.matrix, want.matrix, "each frame in its own bin");
        // two frames per bin (the same frame twice): averaged, the same calibration
        let mut twice = centred.clone();
        twice.manifest.delays_s = centred.manifest.delays_s.iter().flat_map(|&d| [d, d]).collect();
        twice.frames = ndarray::concatenate(Axis(0), &[centred.frames.view(), centred.frames.view()]).unwrap();
        let order: Vec<usize> = (0..a.bins()).flat_map(|j| [j, j + a.bins()]).collect();
        twice.frames = twice.frames.select(Axis(0), &order);
        let got = calibrate(&twice, &a, &codes, Sampling::Oversample(1)).unwrap();
        let diff = (&got.matrix.a() - &want.matrix.a()).mapv(f32::abs).iter().fold(0f32, |m, &v| m.max(v));
        assert!(diff < 1e-6, "{diff}");
    }

    #[test]
    fn correction_undoes_gain_and_dark() {
        let (codes, a) = sensor();
        let truth = NonIdeal { tap_gain: 0.05, prnu: 0.02, dark: 0.01, dark_fpn: 0.002, seed: 5, ..NonIdeal::default() };
        let dir = tempfile::tempdir().unwrap();
        let settings = SweepSettings {
            size: (4, 4),
            average: 1,
            noise: NoiseParams::default(),
            noisy: false,
            adc: false,
            png: true,
            level: 0.7,
            seed: 0,
        };
        simulate_sweep(&a, &codes, &truth, &settings, dir.path()).unwrap();
        let cal = calibrate(&Sweep::load(dir.path()).unwrap(), &a, &codes, Sampling::Oversample(1)).unwrap();
        // a scene through the real sensor, corrected, equals the calibrated A applied to it
        let real = truth.realise(&a, 4, 4).unwrap();
        let x = Array4::from_shape_fn((1, a.bins(), 4, 4), |(_, j, i, k)| ((j * 3 + i + k) % 5) as f32 / 5.0);
        let e = real.measure(&x.view(), &NoiseParams::default(), false, crate::noise::Exposure::ElectronsPerUnit(1000.0), 0).unwrap();
        let y: Array4<f32> = e.electrons.into_dimensionality().unwrap();
        let corrected = cal.correct(&y.view()).unwrap();
        let pred = cal.matrix.plan(4, 4).unwrap().forward_batch(&x.view()).unwrap();
        let ratio = corrected.sum() / pred.sum();
        let rel = (&corrected - &pred.mapv(|v| v * ratio)).mapv(|v| v * v).sum().sqrt() / corrected.mapv(|v| v * v).sum().sqrt();
        assert!(rel < 2e-3, "corrected frames differ from the calibrated model by {rel}");
        assert!(cal.correct(&Array4::zeros((1, 4, 2, 2)).view()).is_err());
    }
}
