//! Speed against accuracy of decoders (`tcsense bench decoders`): each decoder's frames per
//! second on a stream of frames at the sensor's frame size, through the decoder contract (an
//! `onnx:` decoder is the deployed path: ONNX Runtime with the fits around it), beside its
//! accuracy on a light ladder ([`crate::eval::evaluate_ladder`]).

use ndarray::{s, Array3, Array4, ArrayView4, Axis, Ix4};
use serde::Serialize;
use std::sync::atomic::AtomicBool;
use std::time::Instant;
use tcsense_datasets::Dataset;
use tcsense_kernels::timing::median_by;
use tcsense_models::decoder::Control;
use tcsense_models::ModelError;
use tcsense_sensor::measure::measure_batch;
use tcsense_sensor::noise::derive_seed;
use tcsense_sensor::{NoiseParams, Sensor};

use crate::registry::NamedDecoder;
use crate::{InferError, Result};

/// One decoder's speed on a stream.
#[derive(Debug, Clone, Serialize)]
pub struct DecoderSpeed {
    pub decoder: String,
    /// Frames per round and rounds timed (the median round is reported).
    pub frames: usize,
    pub rounds: usize,
    pub ms_per_frame: f64,
    pub frames_per_s: f64,
}

/// `frames` frames of tap images at `(h, w)` from the items of a dataset split: item `i mod n`
/// of the split mirrored (reflected at its edges) to the frame size, then measured by `sensor`
/// with `noise` (seeded per frame). Scenes at the sensor's own size from a dataset of smaller
/// items: what a stream of the sensor's frames holds, without generating new scenes.
///
/// # Shapes
/// → `[frames, M, h, w]`
pub fn tiled_frames(
    ds: &Dataset,
    split: &str,
    sensor: &Sensor,
    (h, w): (usize, usize),
    frames: usize,
    noise: &NoiseParams,
    seed: u64,
) -> Result<Array4<f32>> {
    let bad = |msg: String| InferError::File { path: ds.dir.clone(), msg };
    let x = ds.load(split, "x")?.into_dimensionality::<Ix4>().map_err(|e| bad(format!("field x of split {split}: {e}")))?;
    let (n, _, ih, iw) = x.dim();
    if n == 0 || ih == 0 || iw == 0 {
        return Err(bad(format!("no items in split {split:?}")));
    }
    let a = sensor.nominal();
    let plan = a.plan(h, w)?;
    let mut y = Array4::zeros((frames, a.taps(), h, w));
    for f in 0..frames {
        let cube = mirrored(&x.index_axis(Axis(0), f % n), (h, w));
        let frame = measure_batch(&plan, &cube.insert_axis(Axis(0)).view(), Some(noise), derive_seed(seed, f as u64))?;
        y.slice_mut(s![f..f + 1, .., .., ..]).assign(&frame);
    }
    Ok(y)
}

/// The cube `item` `[T, h₀, w₀]` extended to `(h, w)` by reflection at its edges (rows and
/// columns `0 1 … n−1 n−1 … 1 0 0 1 …`).
///
/// # Shapes
/// - `item`: `[T, h₀, w₀]` → `[T, h, w]`
pub fn mirrored(item: &ndarray::ArrayView3<'_, f32>, (h, w): (usize, usize)) -> Array3<f32> {
    let (t, ih, iw) = item.dim();
    let mirror = |i: usize, n: usize| {
        let k = i % (2 * n);
        if k < n {
            k
        } else {
            2 * n - 1 - k
        }
    };
    Array3::from_shape_fn((t, h, w), |(b, i, j)| item[(b, mirror(i, ih), mirror(j, iw))])
}

/// Time `decoders` on the stream `y` `[F, M, H, W]`, one frame per call as `tcsense infer`
/// decodes a stream: one warm-up frame each, then `rounds` rounds in which every decoder
/// decodes every frame in turn (interleaved: this machine's speed drifts), the median round
/// reported.
pub fn stream_speed(
    decoders: &mut [NamedDecoder],
    sensor: &Sensor,
    y: &ArrayView4<'_, f32>,
    rounds: usize,
    on_round: &dyn Fn(usize, usize),
    cancel: &AtomicBool,
) -> Result<Vec<DecoderSpeed>> {
    let frames = y.dim().0;
    if frames == 0 || rounds == 0 {
        return Err(InferError::InvalidParam {
            field: "frames",
            got: format!("{frames} frames, {rounds} rounds"),
            expected: "at least one frame and one round".into(),
        });
    }
    let ctl = Control::quiet(cancel);
    let cancelled = |e: ModelError| match e {
        ModelError::Cancelled => InferError::Cancelled,
        e => e.into(),
    };
    for d in decoders.iter_mut() {
        d.decoder.decode(y.slice(s![0..1, .., .., ..]), sensor, &ctl).map_err(cancelled)?;
    }
    let mut times = vec![Vec::with_capacity(rounds); decoders.len()];
    for r in 0..rounds {
        for (d, t) in decoders.iter_mut().zip(&mut times) {
            let t0 = Instant::now();
            for f in 0..frames {
                d.decoder.decode(y.slice(s![f..f + 1, .., .., ..]), sensor, &ctl).map_err(cancelled)?;
            }
            t.push(t0.elapsed().as_secs_f64());
        }
        on_round(r + 1, rounds);
    }
    Ok(decoders
        .iter()
        .zip(times)
        .map(|(d, t)| {
            let s = median_by(&t, |v| *v).unwrap_or(f64::NAN);
            DecoderSpeed {
                decoder: d.label.clone(),
                frames,
                rounds,
                ms_per_frame: 1e3 * s / frames as f64,
                frames_per_s: frames as f64 / s,
            }
        })
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_mirrored_item_is_reflected_at_its_edges() {
        let item = Array3::from_shape_fn((2, 3, 4), |(b, i, j)| (100 * b + 10 * i + j) as f32);
        let m = mirrored(&item.view(), (7, 10));
        assert_eq!(m.dim(), (2, 7, 10));
        // rows 0 1 2 2 1 0 0, columns 0 1 2 3 3 2 1 0 0 1
        let rows = [0, 1, 2, 2, 1, 0, 0];
        let cols = [0, 1, 2, 3, 3, 2, 1, 0, 0, 1];
        for b in 0..2 {
            for (i, &r) in rows.iter().enumerate() {
                for (j, &c) in cols.iter().enumerate() {
                    assert_eq!(m[(b, i, j)], item[(b, r, c)], "at ({b}, {i}, {j})");
                }
            }
        }
        // a frame no larger than the item is its corner
        assert_eq!(mirrored(&item.view(), (2, 3)), item.slice(s![.., 0..2, 0..3]));
    }
}
