//! Learned decoders as burn modules behind the [`Decoder`] contract.
//!
//! A [`Network`] maps measurement tensors to its prediction on a device chosen at run time
//! (the CPU `flex` device by default; nothing here assumes it). [`NetDecoder`] wraps any
//! network for inference: it prepares the sensor tensors ([`SensorTensors`]) for the frame
//! size and the `A` it is given, once, and decodes a batch frame by frame, so memory stays
//! that of one frame.

use burn::module::Module;
use burn::tensor::{Device, Tensor, TensorData};
use ndarray::{Array4, ArrayView4, Axis};
use tcsense_sensor::MeasurementMatrix;

use crate::decoder::{check_measurements, Control, Decoded, Decoder, Step};
use crate::sensor_tensors::SensorTensors;
use crate::{ModelError, Result};
use tcsense_fits::range::{refine_ranges, RangeFitOptions};

/// What a network predicts.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Prediction {
    /// The transient cube `[B, T, H, W]` (trained against the cube).
    Cube,
    /// Depth of `K` returns in metres then confidence logits, `[B, 2K, H, W]` (trained
    /// against the range ground truth).
    Depth,
    /// Lifetimes and a confidence logit, `[B, 5, H, W]`: `τ_m`, `τ₁`, `τ₂` (ns), `α₁`, logit
    /// (trained against the lifetime ground truth; [`crate::lifetime`]).
    Lifetime,
}

/// A return counts as detected where its confidence is at least this.
pub const DETECTION_THRESHOLD: f32 = 0.5;

/// A trainable decoder network: the training loop (`tcsense-train`) and [`NetDecoder`] see
/// networks only through this trait.
pub trait Network: Module + Sized + Send + 'static {
    /// What [`Network::predict`] returns.
    const PREDICTION: Prediction;

    /// Forward pass on a batch.
    ///
    /// # Shapes
    /// - `y`: `[B, M, H, W]` → `[B, T, H, W]` for [`Prediction::Cube`], `[B, 2K, H, W]` for
    ///   [`Prediction::Depth`]
    fn predict(&self, y: Tensor<4>, sensor: &SensorTensors) -> Tensor<4>;

    /// What the training loss sees: [`Network::predict`]'s channels, then any the loss needs
    /// besides (the U-Net's score volume appends its log-probabilities per bin, `[B, K·T, H, W]`).
    fn train_output(&self, y: Tensor<4>, sensor: &SensorTensors) -> Tensor<4> {
        self.predict(y, sensor)
    }

    /// The decoder's product of frames when it is more than [`Network::predict`] (work off
    /// the tensors: the lifetime network on the fit's evidence refines its modes in the tap
    /// domain); `None`: `predict`'s, frame by frame.
    ///
    /// # Shapes
    /// - `y`: `[B, M, H, W]` → as [`Network::predict`]
    fn decode_frames(&self, y: &ArrayView4<'_, f32>, sensor: &SensorTensors) -> Option<Array4<f32>> {
        let _ = (y, sensor);
        None
    }
}

/// An ndarray batch as a tensor on `device`.
///
/// # Shapes
/// - `a`: `[B, C, H, W]` → `[B, C, H, W]`
pub fn to_tensor(a: &ArrayView4<'_, f32>, device: &Device) -> Tensor<4> {
    let (b, c, h, w) = a.dim();
    let data: Vec<f32> = a.iter().copied().collect();
    Tensor::from_data(TensorData::new(data, [b, c, h, w]), device)
}

/// A tensor back as an ndarray batch.
///
/// # Shapes
/// - `t`: `[B, C, H, W]` → `[B, C, H, W]`
pub fn to_array(t: Tensor<4>) -> Result<Array4<f32>> {
    let [b, c, h, w] = t.dims();
    let v: Vec<f32> = t.into_data().try_into_vec::<f32>().map_err(|e| ModelError::InvalidParam {
        field: "tensor",
        got: format!("{e:?}"),
        expected: "f32 data".into(),
    })?;
    Array4::from_shape_vec((b, c, h, w), v).map_err(|e| ModelError::InvalidParam {
        field: "tensor",
        got: e.to_string(),
        expected: "a [B, C, H, W] tensor".into(),
    })
}

/// Depth (NaN where the confidence is below [`DETECTION_THRESHOLD`]) and confidence from a
/// depth network's output.
///
/// # Shapes
/// - `out`: `[B, 2K, H, W]` (depth in metres, confidence logits) → `([B, K, H, W], [B, K, H, W])`
pub fn split_depth(out: &Array4<f32>) -> (Array4<f32>, Array4<f32>) {
    let k = out.dim().1 / 2;
    let mut depth = out.slice(ndarray::s![.., ..k, .., ..]).to_owned();
    let confidence = out.slice(ndarray::s![.., k.., .., ..]).mapv(|l| 1.0 / (1.0 + (-l).exp()));
    mask_depth(&mut depth, &confidence);
    (depth, confidence)
}

/// Lifetimes in seconds (NaN where the confidence is below [`DETECTION_THRESHOLD`]) and the
/// confidence from a lifetime network's output.
///
/// # Shapes
/// - `out`: `[B, 5, H, W]` (`τ_m`, `τ₁`, `τ₂` in ns, `α₁`, confidence logit) → `([B, 4, H, W], [B, 1, H, W])`
pub fn split_lifetime(out: &Array4<f32>) -> (Array4<f32>, Array4<f32>) {
    let mut lifetime = out.slice(ndarray::s![.., ..4, .., ..]).to_owned();
    lifetime.slice_mut(ndarray::s![.., ..3, .., ..]).mapv_inplace(|t| t * 1e-9);
    let confidence = out.slice(ndarray::s![.., 4..5, .., ..]).mapv(|l| 1.0 / (1.0 + (-l).exp()));
    mask_lifetime(&mut lifetime, &confidence);
    (lifetime, confidence)
}

/// Set every lifetime channel to NaN where the confidence is below [`DETECTION_THRESHOLD`].
///
/// # Shapes
/// - `lifetime`: `[B, C, H, W]`, `confidence`: `[B, 1, H, W]`
pub fn mask_lifetime(lifetime: &mut Array4<f32>, confidence: &Array4<f32>) {
    for (mut l, c) in lifetime.outer_iter_mut().zip(confidence.outer_iter()) {
        let c = c.index_axis(Axis(0), 0);
        for mut ch in l.outer_iter_mut() {
            ch.zip_mut_with(&c, |v, &p| {
                if p < DETECTION_THRESHOLD {
                    *v = f32::NAN;
                }
            });
        }
    }
}

/// Set the depth to NaN where the confidence is below [`DETECTION_THRESHOLD`].
///
/// # Shapes
/// - `depth`, `confidence`: `[B, K, H, W]`
pub fn mask_depth(depth: &mut Array4<f32>, confidence: &Array4<f32>) {
    depth.zip_mut_with(confidence, |d, &c| {
        if c < DETECTION_THRESHOLD {
            *d = f32::NAN;
        }
    });
}

/// A [`Network`] for inference behind the [`Decoder`] contract.
#[derive(Debug)]
pub struct NetDecoder<M> {
    name: String,
    model: M,
    device: Device,
    /// Sensor tensors of the last frame size and `A`.
    cache: Option<(MeasurementMatrix, SensorTensors)>,
    /// Depth networks: the returns' ranges refined in the tap domain ([`tcsense_fits::range`]).
    range_fit: Option<RangeFitOptions>,
}

impl<M: Network> NetDecoder<M> {
    /// Wrap `model` (already on `device`, without autodiff for inference).
    pub fn new(name: &str, model: M, device: Device) -> Self {
        NetDecoder { name: name.to_string(), model, device, cache: None, range_fit: Some(RangeFitOptions::default()) }
    }

    /// A depth network's ranges as it outputs them, without the fit in the tap domain.
    pub fn without_range_fit(mut self) -> Self {
        self.range_fit = None;
        self
    }

    /// The wrapped network.
    pub fn model(&self) -> &M {
        &self.model
    }

    /// Sensor tensors for `sensor` and `h × w` frames, reused while both stay the same.
    fn sensor_tensors(&mut self, sensor: &MeasurementMatrix, h: usize, w: usize) -> Result<&SensorTensors> {
        let fits = self.cache.as_ref().is_some_and(|(a, s)| a == sensor && (s.height, s.width) == (h, w));
        if !fits {
            self.cache = Some((sensor.clone(), SensorTensors::new(sensor, h, w, &self.device)?));
        }
        self.cache.as_ref().map(|(_, s)| s).ok_or(ModelError::InvalidParam {
            field: "sensor tensors",
            got: "none".into(),
            expected: "prepared tensors".into(),
        })
    }
}

impl<M: Network> Decoder for NetDecoder<M> {
    fn name(&self) -> &str {
        &self.name
    }

    fn decode(&mut self, y: ArrayView4<'_, f32>, sensor: &tcsense_sensor::Sensor, ctl: &Control<'_>) -> Result<Decoded> {
        let sensor = sensor.matrix();
        check_measurements(&y, sensor)?;
        let (b, _, h, w) = y.dim();
        let device = self.device.clone();
        let st = self.sensor_tensors(sensor, h, w)?.clone();
        let mut frames = Vec::with_capacity(b);
        // a network's own product ([`Network::decode_frames`]) is already refined in the tap domain
        let mut own = false;
        for i in 0..b {
            ctl.check()?;
            let yi = y.slice_axis(Axis(0), ndarray::Slice::from(i..i + 1));
            match self.model.decode_frames(&yi, &st) {
                Some(out) => {
                    own = true;
                    frames.push(out)
                }
                None => frames.push(to_array(self.model.predict(to_tensor(&yi, &device), &st))?),
            }
            (ctl.progress)(Step { frame: i, frames: b, done: 1, total: 1 });
        }
        let views: Vec<_> = frames.iter().map(|f| f.view()).collect();
        let out = ndarray::concatenate(Axis(0), &views).map_err(|e| ModelError::InvalidParam {
            field: "batch",
            got: e.to_string(),
            expected: "frames of one shape".into(),
        })?;
        match M::PREDICTION {
            Prediction::Cube => Ok(Decoded { cube: Some(out), ..Default::default() }),
            Prediction::Depth => {
                let (mut depth, confidence) = split_depth(&out);
                if let (Some(opts), false) = (&self.range_fit, own) {
                    refine_ranges(y, sensor, &mut depth, opts);
                }
                Ok(Decoded { depth: Some(depth), confidence: Some(confidence), ..Default::default() })
            }
            Prediction::Lifetime => {
                let (lifetime, confidence) = split_lifetime(&out);
                Ok(Decoded {
                    lifetime: Some(lifetime),
                    confidence: Some(confidence),
                    intensity: Some(y.sum_axis(Axis(1)).insert_axis(Axis(1))),
                    ..Default::default()
                })
            }
        }
    }
}
