//! Decoding tap images with any decoder on a [`Sensor`]: the one path `tcsense reconstruct`
//! and the Python module share.
//!
//! A calibrated sensor's raw tap images are corrected first, `(y − d) / G`, then decoded with
//! its measured `A`; a learned decoder decodes only the codes it was trained with. Files are
//! checked against their sidecar (codes, sampling, matrix, units) before anything is decoded,
//! and nothing is written when decoding fails or is interrupted.

use ndarray::{Array4, ArrayD, ArrayView4, Axis, Ix3, Ix4};
use std::path::{Path, PathBuf};
use tcsense_models::decoder::{Control, Decoded, Decoder};
use tcsense_models::ModelError;
use tcsense_sensor::npy::{read_npy, write_npy};
use tcsense_sensor::output::Outputs;
use tcsense_sensor::{Codes, Sensor};

use crate::{InferError, Result};

/// Refuse a learned decoder's codes on a sensor with other codes.
pub fn check_codes(label: &str, trained: Option<&Codes>, sensor: &Sensor) -> Result<()> {
    match trained {
        Some(c) if c.digest() != sensor.codes().digest() => Err(InferError::InvalidParam {
            field: "sensor",
            got: format!("codes {}", sensor.codes().digest()),
            expected: format!("{label}'s own: it was trained with codes {}, and a learned decoder decodes its own codes only (fine-tune it to new codes with `tcsense train --init-from`)", c.digest()),
        }),
        _ => Ok(()),
    }
}

/// Decode a batch of raw tap images on `sensor`: corrected by its calibration when it has one,
/// then decoded with its matrix.
///
/// # Shapes
/// - `y`: `[B, M, H, W]` → the decoder's [`Decoded`] (cube `[B, T, H, W]`, depth and
///   confidence `[B, K, H, W]`, lifetimes `[B, 4, H, W]`)
pub fn decode_batch(decoder: &mut dyn Decoder, sensor: &Sensor, y: ArrayView4<'_, f32>, ctl: &Control<'_>) -> Result<Decoded> {
    let out = match sensor.calibration() {
        Some(_) => decoder.decode(sensor.correct(y)?.view(), sensor, ctl),
        None => decoder.decode(y, sensor, ctl),
    };
    out.map_err(|e| match e {
        ModelError::Cancelled => InferError::Cancelled,
        e => e.into(),
    })
}

/// Tap images read from `path` (`.npy`, `[M, H, W]` or `[B, M, H, W]`) as a batch, checked
/// against `sensor` (their sidecar's codes, sampling and matrix; the calibration's units; `M`
/// taps), and whether the file had a batch axis.
///
/// # Shapes
/// - file `[M, H, W]` → `(false, [1, M, H, W])`; `[B, M, H, W]` → `(true, [B, M, H, W])`
pub fn read_measurements(path: &Path, sensor: &Sensor) -> Result<(bool, Array4<f32>)> {
    let y = read_npy(path)?;
    sensor.check_measurements(path)?;
    let file = |msg: String| InferError::File { path: path.to_path_buf(), msg };
    if !(y.ndim() == 3 || y.ndim() == 4) {
        return Err(file(format!("measurements have shape {:?}, expected [M, H, W] or [B, M, H, W]", y.shape())));
    }
    let m = y.shape()[y.ndim() - 3];
    if m != sensor.taps() {
        return Err(file(format!("{m} tap images, but the sensor (codes) has M = {} taps", sensor.taps())));
    }
    Ok(match y.ndim() {
        3 => (false, y.into_dimensionality::<Ix3>().map_err(|e| file(e.to_string()))?.insert_axis(Axis(0))),
        _ => (true, y.into_dimensionality::<Ix4>().map_err(|e| file(e.to_string()))?),
    })
}

/// What [`decode_file`] wrote.
#[derive(Debug)]
pub struct DecodedFile {
    /// The decoder's output (with the batch axis).
    pub decoded: Decoded,
    /// Whether the measurements file had a batch axis (the outputs have one then).
    pub batched: bool,
    /// Frames decoded.
    pub frames: usize,
    /// Wall time per frame (s).
    pub seconds_per_frame: f64,
    /// The files written, the main output first.
    pub written: Vec<PathBuf>,
    /// Pixels (over all frames) with a tap at the clip level: no range or lifetime there.
    pub clipped: usize,
}

/// The files beside a decoder's main output `output`: `OUTPUT.confidence.npy` (depth and
/// lifetimes), `OUTPUT.intensity.npy` (lifetimes) and `OUTPUT.depth.npy` (the ranges of a
/// decoder of cubes that gives them too, `NAME+fit`).
pub fn companions(output: &Path) -> [PathBuf; 3] {
    [output.with_extension("confidence.npy"), output.with_extension("intensity.npy"), output.with_extension("depth.npy")]
}

/// Decode the tap images in `measurements` with `decoder` on `sensor` and write what it gives
/// (same batching as the input) to `output`: the cube (with its ranges at `OUTPUT.depth.npy`
/// and their confidence where the decoder gives them, `NAME+fit`); or the depth `[K, H, W]` with the
/// confidence at `OUTPUT.confidence.npy`; or the lifetimes `[4, H, W]` with the confidence and
/// the intensity (`OUTPUT.intensity.npy`) — staged in `outputs` (planned with `output` and its
/// [`companions`]), which the caller commits once every other output of the command is
/// written too. Nothing is written when decoding fails. With a `clip_level` (what a tap
/// clipped at the full well reads: [`tcsense_sensor::sidecar::Sidecar::clip_level`]), the
/// pixels with a tap at it get no range and no lifetime (their confidence 0).
pub fn decode_file(
    decoder: &mut dyn Decoder,
    sensor: &Sensor,
    measurements: &Path,
    output: &Path,
    ctl: &Control<'_>,
    outputs: &mut Outputs,
    clip_level: Option<f32>,
) -> Result<DecodedFile> {
    let (batched, y) = read_measurements(measurements, sensor)?;
    let frames = y.dim().0;
    let t0 = std::time::Instant::now();
    let mut decoded = decode_batch(decoder, sensor, y.view(), ctl).map_err(|e| match e {
        InferError::Cancelled => InferError::Cancelled,
        e => InferError::File { path: measurements.to_path_buf(), msg: e.to_string() },
    })?;
    let seconds_per_frame = t0.elapsed().as_secs_f64() / frames.max(1) as f64;
    // no range and no lifetime where a tap reads the clip level: nothing there can be read
    let clipped = match clip_level {
        Some(level) => {
            let unread = tcsense_sensor::measure::at_clip_level(&y.view(), level); // [B, H, W]
            decoded.without_pixels(&unread.view());
            unread.iter().filter(|&&u| u).count()
        }
        None => 0,
    };
    let unbatch = |a: &Array4<f32>| -> ArrayD<f32> {
        if batched {
            a.clone().into_dyn()
        } else {
            a.index_axis(Axis(0), 0).to_owned().into_dyn()
        }
    };
    let [confidence, intensity, depth] = companions(output);
    let files: Vec<(PathBuf, &Array4<f32>)> =
        match (&decoded.cube, &decoded.lifetime, &decoded.depth, &decoded.confidence, &decoded.intensity) {
            (Some(x), _, Some(d), Some(c), _) => vec![(output.to_path_buf(), x), (depth, d), (confidence, c)],
            (Some(c), ..) => vec![(output.to_path_buf(), c)],
            (None, Some(l), _, Some(c), Some(i)) => vec![(output.to_path_buf(), l), (confidence, c), (intensity, i)],
            (None, None, Some(d), Some(c), _) => vec![(output.to_path_buf(), d), (confidence, c)],
            _ => {
                return Err(InferError::InvalidParam {
                    field: "decoder",
                    got: decoder.name().into(),
                    expected: "a decoder that gives a cube, depth with confidence or lifetimes".into(),
                })
            }
        };
    let mut written = Vec::with_capacity(files.len());
    for (path, a) in files {
        write_npy(&outputs.stage(&path)?, &unbatch(a).view())?;
        written.push(path);
    }
    Ok(DecodedFile { decoded, batched, frames, seconds_per_frame, written, clipped })
}
