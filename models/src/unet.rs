//! Aᵀ + U-Net (paper §III, its ref. [54]; DESIGN §5): a light decoder that estimates the
//! depth of `K` returns directly, correcting multipath on the way.
//!
//! ```text
//! y [B, M, H, W] ──Aᵀ (or F)──▶ x₀ [B, T, H, W] ──÷ (‖x₀‖₂ per pixel + f·mean‖x₀‖₂)──▶ x̄
//!     (f = 10⁻³ for Aᵀ, 1 for F: see MATCHED_NORM_FLOOR)
//! x̄ ──pad to a multiple of 2^(levels−1)──▶ U-Net ──crop──▶ [B, 2K, H, W]
//!     level ℓ: two 3×3 conv + ReLU with w·2^ℓ channels; 2×2 max-pool between levels;
//!     decoder: nearest ×2 up-sampling, concatenation with the skip, two 3×3 conv + ReLU;
//!     head: 1×1 conv to K·T + K channels (score volume) or 2K (regression)
//! score volume: p_{k,t} = softmax_t(s_{k,t}), t̂_k = argmax_t p_{k,t}, Δ = r_max/T,
//!               depth_k = Σ_{|t − t̂_k| ≤ 1} p_{k,t}·(t + ½)·Δ / Σ_{|t − t̂_k| ≤ 1} p_{k,t} (m)
//!               (the local soft-argmax; training's loss takes it over all bins)
//! regression:   depth_k = r_max·sigmoid(o_k) (m)                            (runs before it)
//! confidence_k = sigmoid(o_{K+k})
//! ```
//!
//! The score volume ([`UnetHead::ScoreVolume`]) is what learned single-photon 3-D imaging
//! decoders output: a score per bin and return, the range its soft-argmax. Where the
//! regression head squeezes the whole range through one sigmoid (and was imprecise to a
//! bin and more on scenes unlike its training set), the soft-argmax places a return between
//! bin centres by the weights of the neighbouring bins, as peak fitting does.
//! Inference takes the soft-argmax only within [`SOFT_ARGMAX_HALF_WIDTH`] bins of the most
//! probable bin. Over all bins it is the mean of the scores' distribution, which the rest of
//! that distribution pulls toward the middle of the range wherever the network is unsure (a
//! real scene: on the Middlebury motorcycle the surface came out up to a metre behind where
//! it is, the far wall in front of it; median error 0.17 m over all bins, 0.06 m locally).
//! Training keeps the soft-argmax over all bins in its loss (with the cross-entropy on the
//! true bin it makes the distribution peaked, and it keeps its gradient everywhere).
//!
//! With [`UnetInput::Matched`] the network reads `x₀ = F y` instead of `Aᵀy`: the range fit's
//! matched filters (each bin centre's template with the ambient light projected out, unit
//! norm), whose argmax per pixel is the fit's own range on the bin grid. It is the fit-aware
//! input of photon-efficient LiDAR networks, which decode a per-pixel evidence volume with a
//! learned spatial prior rather than raw measurements.
//!
//! The normalisation is part of the model, so deployment feeds raw tap images, and it makes
//! the output invariant to the scale of `y` (`y` and `10·y` give the same depth). Time is the
//! channel axis. Frames of any size work: the model pads them with zeros to a multiple of
//! `2^(levels−1)` and crops the output back (188×212 needs no padding with 3 levels).
//! The 3×3 convolutions, the pooling and the up-sampling run on the kernels of
//! `tcsense-kernels`.

use burn::config::Config;
use burn::module::Module;
use burn::nn::conv::{Conv2d, Conv2dConfig};
use burn::nn::PaddingConfig2d;
use burn::tensor::activation::{relu, sigmoid};
use burn::tensor::ops::PadMode;
use burn::tensor::{Device, Int, Tensor};
use tcsense_kernels::conv_op::conv3x3_layer as conv;
use tcsense_kernels::resample::{max_pool2, upsample2};

use crate::net::{Network, Prediction};
use crate::sensor_tensors::SensorTensors;

/// Relative floor of the per-pixel normalisation: dark pixels are divided by at least this
/// fraction of the frame's mean norm, so noise alone is not blown up to unit scale.
pub const NORM_FLOOR: f64 = 1e-3;

/// The floor of the normalisation of the matched filters ([`UnetInput::Matched`]): the frame's
/// mean norm itself, so a pixel keeps its brightness relative to the frame (a pixel as bright
/// as the mean comes out at half its norm, one ten times dimmer at a tenth of that) where the
/// back-projection's floor makes every lit pixel's waveform unit-norm. Light is what the
/// network must weigh in dim light: which pixels hold signal and which hold read noise.
pub const MATCHED_NORM_FLOOR: f64 = 1.0;

/// Half width (bins) of the window around the most probable bin over which inference takes
/// the score volume's soft-argmax (see the module documentation).
pub const SOFT_ARGMAX_HALF_WIDTH: usize = 1;

/// U-Net hyper-parameters.
#[derive(Config, Debug, PartialEq)]
pub struct UnetConfig {
    /// Taps `M`.
    pub taps: usize,
    /// Bins `T` of `x₀ = Aᵀy` (input channels).
    pub bins: usize,
    /// Largest range (m): the unambiguous range `c·L·T_c/2` of the codes' cycle.
    pub range_m: f64,
    /// Returns `K` per pixel: 1 (first surface) or 2 (and the one behind a diffusive sheet).
    #[config(default = 2)]
    pub returns: usize,
    /// Channels of the first level, doubled at every level down.
    #[config(default = 8)]
    pub base_width: usize,
    /// Resolutions (`levels − 1` down-samplings by 2).
    #[config(default = 3)]
    pub levels: usize,
    /// How the range is read out (`regression` in runs written before the score volume).
    #[config(default = "UnetHead::Regression")]
    pub head: UnetHead,
    /// What the network reads (`backprojection` in runs written before the matched filters).
    #[config(default = "UnetInput::Backprojection")]
    pub input: UnetInput,
    /// Candidates per bin of the range fit whose evidence the network reads
    /// ([`UnetInput::Costs`]; the fit's own default).
    #[config(default = 4)]
    pub oversample: usize,
    /// Candidates pooled into one feature channel ([`UnetInput::Costs`]).
    #[config(default = 4)]
    pub pool: usize,
    /// The fit's window's log-likelihood pooled by likeness with the neighbouring windows
    /// that tile this side before the learned prior is added, as `depth-fit-pooled` does
    /// ([`UnetInput::Costs`]; 0: the window alone, as in runs written before it).
    #[config(default = 0)]
    pub pool_like: usize,
}

/// What the U-Net reads from the taps (see the module documentation).
#[derive(Config, Debug, PartialEq, Eq, Copy)]
pub enum UnetInput {
    /// `x₀ = Aᵀy`, the back-projection through the code bits.
    Backprojection,
    /// `x₀ = F y`: the range fit's matched filters at every bin centre, ambient light projected
    /// out ([`tcsense_sensor::MeasurementMatrix::matched_filters`]). What the per-pixel fit
    /// maximises, so the network starts from the fit's own evidence for a return at each bin
    /// and learns the spatial prior the fit does not have; ambient light does not reach it
    /// except through its shot noise.
    Matched,
    /// The range fit's evidence ([`tcsense_fits::depth::RangeTemplates::evidence`]): its
    /// log-likelihood of a return at every candidate range of the cycle, plus a learned
    /// log-prior read from the per-pixel posteriors of the neighbourhood; the first return is
    /// the posterior's mode refined in the tap domain, the second the fit's (see
    /// [`crate::depth_evidence`]).
    Costs,
}

/// The U-Net's read-out of the range (see the module documentation).
#[derive(Config, Debug, PartialEq, Eq, Copy)]
pub enum UnetHead {
    /// `depth = r_max·sigmoid(o)`: one regressed value per return.
    Regression,
    /// A score per bin and return, `depth` its soft-argmax over the bin centres (within
    /// [`SOFT_ARGMAX_HALF_WIDTH`] bins of the most probable one at inference).
    ScoreVolume,
}

/// Two 3×3 conv + ReLU.
#[derive(Module, Debug)]
pub struct Block {
    conv1: Conv2d,
    conv2: Conv2d,
}

/// The network.
#[derive(Module, Debug)]
pub struct Unet {
    down: Vec<Block>,
    up: Vec<Block>,
    head: Conv2d,
    returns: usize,
    levels: usize,
    range_m: f64,
    /// Bins `T` of the score volume; 0 for the regression head.
    score_bins: usize,
    /// Reads the matched filters `F y` instead of `Aᵀy` ([`UnetInput::Matched`]).
    matched: bool,
    /// Candidates `C` of the range fit's evidence; 0 for the other inputs ([`UnetInput::Costs`]).
    pub(crate) candidates: usize,
    /// Candidates per bin of that fit.
    pub(crate) oversample: usize,
    /// Candidates pooled into one feature channel.
    pub(crate) pool: usize,
    /// The side of the neighbourhood the fit's window is pooled over by likeness (0: none).
    pub(crate) pool_like: usize,
}

impl UnetConfig {
    /// Channels of level `l`.
    pub fn width(&self, l: usize) -> usize {
        self.base_width << l
    }

    /// Frames must be multiples of this (the model pads to it internally).
    pub fn stride(&self) -> usize {
        1 << self.levels.saturating_sub(1)
    }

    /// Candidates `C = T·oversample` of the range fit's evidence ([`UnetInput::Costs`]).
    pub fn candidates(&self) -> usize {
        self.bins * self.oversample
    }

    /// Input channels: `T` bins, or the pooled per-pixel posteriors, the log intensity and the
    /// lit mask ([`UnetInput::Costs`]).
    pub fn features(&self) -> usize {
        match self.input {
            UnetInput::Costs => tcsense_fits::depth::range_feature_channels(self.candidates(), self.pool),
            _ => self.bins,
        }
    }

    /// Checks the settings; the error names the field.
    pub fn validate(&self) -> Result<(), String> {
        if self.input == UnetInput::Costs {
            if !(1..=16).contains(&self.oversample) {
                return Err(format!("oversample: {}, expected 1 to 16 candidates per bin", self.oversample));
            }
            if self.pool == 0 || self.pool > self.candidates() {
                return Err(format!("pool: {}, expected 1 to the candidates ({})", self.pool, self.candidates()));
            }
            if self.head != UnetHead::ScoreVolume {
                return Err("head: the fit's evidence is read out as a posterior over the candidates, expected score-volume".into());
            }
        }
        let window = tcsense_fits::range::RangeFitOptions::default().window;
        if self.pool_like != 0 && !tcsense_fits::evidence::pooled_side(self.pool_like, window) {
            return Err(format!(
                "pool_like: {}, expected 0 (the window alone) or an odd multiple of the fit's window {window} above it, up to {} (e.g. 9, 15)",
                self.pool_like,
                tcsense_fits::range::MAX_WINDOW
            ));
        }
        if self.pool_like != 0 && self.input != UnetInput::Costs {
            return Err(format!(
                "pool_like: {} with the {:?} input, expected the fit's evidence (input costs)",
                self.pool_like, self.input
            ));
        }
        Ok(())
    }

    /// The grid of the range fit's evidence as the loss places a range on it: candidate
    /// coordinate `u = r·scale − offset` (cyclic over `C`) for a range `r` in metres (the
    /// offset, half the candidates of a bin, is also half a bin); `None` for the other inputs.
    pub fn range_grid(&self) -> Option<(f64, f64)> {
        (self.input == UnetInput::Costs).then(|| (self.candidates() as f64 / self.range_m, 0.5 * self.oversample as f64))
    }

    /// Build the network.
    pub fn init(&self, device: &Device) -> Unet {
        let block = |i: usize, o: usize| Block::new(i, o, device);
        let down = (0..self.levels).map(|l| block(if l == 0 { self.features() } else { self.width(l - 1) }, self.width(l))).collect();
        let up = (0..self.levels.saturating_sub(1)).map(|l| block(self.width(l + 1) + self.width(l), self.width(l))).collect();
        let costs = self.input == UnetInput::Costs;
        let mut head = Conv2dConfig::new([self.width(0), self.head_channels()], [1, 1]);
        if costs {
            // the evidence's log-prior starts at zero: the untrained network is the fit
            head = head.with_initializer(burn::nn::Initializer::Zeros);
        }
        let head = head.init(device);
        let score_bins = if self.head == UnetHead::ScoreVolume { self.bins } else { 0 };
        Unet {
            down,
            up,
            head,
            returns: self.returns,
            levels: self.levels,
            range_m: self.range_m,
            score_bins,
            matched: self.input == UnetInput::Matched,
            candidates: if costs { self.candidates() } else { 0 },
            oversample: self.oversample,
            pool: self.pool,
            pool_like: if costs { self.pool_like } else { 0 },
        }
    }

    /// Output channels of the 1×1 head: `K·T + K` (score volume), `2K` (regression), or a
    /// log-prior per candidate, the first return's confidence and a log-weight per window of the
    /// fit's likelihood ([`UnetInput::Costs`]).
    pub fn head_channels(&self) -> usize {
        if self.input == UnetInput::Costs {
            return self.candidates() + tcsense_fits::depth::SCALES;
        }
        match self.head {
            UnetHead::Regression => 2 * self.returns,
            UnetHead::ScoreVolume => (self.bins + 1) * self.returns,
        }
    }

    /// Multiply-adds ×2 per frame of `h × w` (convolutions, head and `Aᵀ`).
    pub fn flops(&self, h: usize, w: usize) -> f64 {
        let s = self.stride();
        let (h, w) = (h.div_ceil(s) * s, w.div_ceil(s) * s);
        let input = match self.input {
            UnetInput::Costs => 0.0,                           // the evidence is the fit's, counted with it
            _ => 2.0 * (self.taps * self.bins * h * w) as f64, // Aᵀ
        };
        let f = input + trunk_flops(self.features(), self.levels, |l| self.width(l), h, w);
        f + 2.0 * (h * w * self.width(0) * self.head_channels()) as f64
    }
}

impl Block {
    /// Two 3×3 conv + ReLU from `i` to `o` channels.
    pub(crate) fn new(i: usize, o: usize, device: &Device) -> Block {
        let conv = |i: usize, o: usize| Conv2dConfig::new([i, o], [3, 3]).with_padding(PaddingConfig2d::Same).init(device);
        Block { conv1: conv(i, o), conv2: conv(o, o) }
    }

    /// The two 3×3 convolutions (weights `[out, in, 3, 3]`).
    pub fn convs(&self) -> [&Conv2d; 2] {
        [&self.conv1, &self.conv2]
    }

    fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        relu(conv(&self.conv2, relu(conv(&self.conv1, x))))
    }
}

/// The encoder–decoder of a U-Net with `down.len()` levels on frames of any size: padded with
/// zeros to a multiple of `2^(levels−1)`, cropped back.
///
/// # Shapes
/// - `x`: `[B, C, H, W]` → `[B, w₀, H, W]` (`w₀` the first level's width)
pub(crate) fn trunk(down: &[Block], up: &[Block], x: Tensor<4>) -> Tensor<4> {
    let levels = down.len();
    let [_, _, h, w] = x.dims();
    let s = 1usize << levels.saturating_sub(1);
    let (ph, pw) = (h.div_ceil(s) * s - h, w.div_ceil(s) * s - w);
    let mut z = if ph + pw > 0 { x.pad((0, pw, 0, ph), PadMode::Constant(0.0)) } else { x };
    let mut skips = Vec::with_capacity(levels);
    for (l, block) in down.iter().enumerate() {
        z = block.forward(z);
        if l + 1 < levels {
            skips.push(z.clone());
            z = max_pool2(z);
        }
    }
    for (block, skip) in up.iter().zip(skips).rev() {
        z = block.forward(Tensor::cat(vec![upsample2(z), skip], 1));
    }
    if ph + pw > 0 {
        z.narrow(2, 0, h).narrow(3, 0, w)
    } else {
        z
    }
}

/// The 1×1 convolution `head` as one batched matrix product `W [O, C] · z [C, H·W]` + bias
/// (burn-flex's generic conv, forward and backward, was 7.5 % of a U-Net training step; the
/// weights stay the `Conv2d`'s, so runs and exports are unchanged).
///
/// # Shapes
/// - `z`: `[B, C, H, W]` → `[B, O, H, W]`
pub(crate) fn conv1x1(head: &Conv2d, z: Tensor<4>) -> Tensor<4> {
    let [b, c, h, w] = z.dims();
    let o = head.weight.dims()[0];
    let wgt = head.weight.val().reshape([1, o, c]).expand([b, o, c]); // [B, O, C]
    let mut out = wgt.matmul(z.reshape([b, c, h * w])); // [B, O, H·W]
    if let Some(bias) = &head.bias {
        out = out + bias.val().reshape([1, o, 1]);
    }
    out.reshape([b, o, h, w])
}

/// FLOPs of a U-Net trunk from `c_in` channels with widths `width(l)` on an `h × w` frame
/// (padded to its stride).
pub(crate) fn trunk_flops(c_in: usize, levels: usize, width: impl Fn(usize) -> usize, h: usize, w: usize) -> f64 {
    let s = 1usize << levels.saturating_sub(1);
    let (h, w) = (h.div_ceil(s) * s, w.div_ceil(s) * s);
    let mut f = 0.0;
    for l in 0..levels {
        let px = ((h >> l) * (w >> l)) as f64;
        let (i, o) = (if l == 0 { c_in } else { width(l - 1) }, width(l));
        f += 2.0 * 9.0 * px * (i * o + o * o) as f64;
        if l + 1 < levels {
            let i = width(l + 1) + width(l);
            f += 2.0 * 9.0 * px * (i * o + o * o) as f64;
        }
    }
    f
}

impl Unet {
    /// Each pixel's L2 norm over the channels, `√(Σ_c x² + 10⁻³⁰)`: the same value in f32
    /// wherever a pixel has light, and a finite gradient where it has none (`√` of 0 has an
    /// infinite one, which times the zero of `∂Σx²/∂x` is NaN; deep sensing differentiates
    /// through it to the codes).
    ///
    /// # Shapes
    /// - `x`: `[B, C, H, W]` → `[B, 1, H, W]`
    pub fn pixel_norm(x: Tensor<4>) -> Tensor<4> {
        x.powi_scalar(2).sum_dim(1).add_scalar(1e-30).sqrt()
    }

    /// Per-pixel normalisation of `x₀ = Aᵀy`: divide each pixel's waveform by its L2 norm
    /// ([`Self::pixel_norm`]) plus a floor of `NORM_FLOOR` times the frame's mean norm.
    ///
    /// # Shapes
    /// - `x0`: `[B, T, H, W]` → `[B, T, H, W]`
    pub fn normalise(x0: Tensor<4>) -> Tensor<4> {
        Self::normalise_with(x0, NORM_FLOOR)
    }

    /// [`Self::normalise`] with the floor `floor` times the frame's mean norm.
    ///
    /// # Shapes
    /// - `x0`: `[B, T, H, W]` → `[B, T, H, W]`
    pub fn normalise_with(x0: Tensor<4>, floor: f64) -> Tensor<4> {
        let norm = Self::pixel_norm(x0.clone()); // [B, 1, H, W]
        let mean = norm.clone().mean_dim(2).mean_dim(3); // [B, 1, 1, 1]
        x0 / (norm + mean * floor + 1e-30)
    }

    /// The floor of this network's normalisation ([`NORM_FLOOR`], or [`MATCHED_NORM_FLOOR`]
    /// for the matched filters).
    pub fn norm_floor(&self) -> f64 {
        if self.matched {
            MATCHED_NORM_FLOOR
        } else {
            NORM_FLOOR
        }
    }

    /// Raw outputs: depth logits (regression, `K` channels) or scores (score volume, `K·T`
    /// channels, return-major), then `K` confidence logits.
    ///
    /// # Shapes
    /// - `y`: `[B, M, H, W]` → `[B, 2K, H, W]` or `[B, K·T + K, H, W]`
    pub fn logits(&self, y: Tensor<4>, sensor: &SensorTensors) -> Tensor<4> {
        let x0 = if self.matched { sensor.matched(y) } else { sensor.adjoint(y) }; // [B, T, H, W]
        let x = Self::normalise_with(x0, self.norm_floor());
        self.head_1x1(trunk(&self.down, &self.up, x))
    }

    /// Depth (m) and confidence in `[0, 1]`.
    ///
    /// # Shapes
    /// - `y`: `[B, M, H, W]` → `([B, K, H, W], [B, K, H, W])`
    pub fn forward(&self, y: Tensor<4>, sensor: &SensorTensors) -> (Tensor<4>, Tensor<4>) {
        let p = self.predict(y, sensor);
        let k = self.returns;
        (p.clone().narrow(1, 0, k), sigmoid(p.narrow(1, k, k)))
    }

    /// Encoder blocks, finest level first (for exporters).
    pub fn down(&self) -> &[Block] {
        &self.down
    }

    /// Decoder blocks: `up()[l]` runs at level `l` on `[up-sampled level l+1, skip l]`.
    pub fn up(&self) -> &[Block] {
        &self.up
    }

    /// The 1×1 head ([`conv1x1`]).
    ///
    /// # Shapes
    /// - `z`: `[B, C, H, W]` → `[B, 2K, H, W]` or `[B, K·T + K, H, W]`
    fn head_1x1(&self, z: Tensor<4>) -> Tensor<4> {
        conv1x1(&self.head, z)
    }

    /// The 1×1 head (to `2K` channels, or `K·T + K` with the score volume).
    pub fn head(&self) -> &Conv2d {
        &self.head
    }

    /// What the network reads.
    pub fn input_kind(&self) -> UnetInput {
        if self.candidates > 0 {
            UnetInput::Costs
        } else if self.matched {
            UnetInput::Matched
        } else {
            UnetInput::Backprojection
        }
    }

    /// The read-out of the range.
    pub fn head_kind(&self) -> UnetHead {
        if self.score_bins > 0 {
            UnetHead::ScoreVolume
        } else {
            UnetHead::Regression
        }
    }

    /// Bin centres of the score volume (m): `(t + ½)·r_max/T`, `T` values (empty for the
    /// regression head).
    pub fn bin_centres_m(&self) -> Vec<f32> {
        let t = self.score_bins;
        (0..t).map(|j| ((j as f64 + 0.5) * self.range_m / t as f64) as f32).collect()
    }

    /// The soft-argmax of a score volume over all bin centres (training's read-out).
    ///
    /// # Shapes
    /// - `scores`: `[B, K·T, H, W]` → `[B, K, H, W]` (m)
    pub fn soft_argmax(&self, scores: Tensor<4>) -> Tensor<4> {
        let [b, _, h, w] = scores.dims();
        let (k, t) = (self.returns, self.score_bins);
        self.expected_range(burn::tensor::activation::softmax(scores.reshape([b, k, t, h, w]), 2))
    }

    /// The soft-argmax of a score volume over the bin centres within
    /// [`SOFT_ARGMAX_HALF_WIDTH`] bins of each return's most probable bin (inference's
    /// read-out; bins past the ends of the range are left out, not wrapped).
    ///
    /// # Shapes
    /// - `scores`: `[B, K·T, H, W]` → `[B, K, H, W]` (m)
    pub fn local_soft_argmax(&self, scores: Tensor<4>) -> Tensor<4> {
        let [b, _, h, w] = scores.dims();
        let (k, t) = (self.returns, self.score_bins);
        let p = burn::tensor::activation::softmax(scores.reshape([b, k, t, h, w]), 2);
        let peak = p.clone().argmax(2).float(); // [B, K, 1, H, W]
        let bins = Tensor::<1, Int>::arange(0..t as i64, &p.device()).float().reshape([1, 1, t, 1, 1]);
        let window = (bins - peak).abs().lower_equal_elem(SOFT_ARGMAX_HALF_WIDTH as f32).float();
        let p = p * window;
        let mass = p.clone().sum_dim(2).reshape([b, k, h, w]);
        self.expected_range(p) / mass
    }

    /// The range expected under bin probabilities.
    ///
    /// # Shapes
    /// - `p`: `[B, K, T, H, W]` → `[B, K, H, W]` (m)
    fn expected_range(&self, p: Tensor<5>) -> Tensor<4> {
        let [b, k, t, h, w] = p.dims();
        let centres = Tensor::<1>::from_floats(self.bin_centres_m().as_slice(), &p.device()).reshape([1, 1, t, 1, 1]);
        (p * centres).sum_dim(2).reshape([b, k, h, w])
    }

    /// Resolutions (`levels − 1` down-samplings by 2).
    pub fn levels(&self) -> usize {
        self.levels
    }

    /// Returns `K`.
    pub fn returns(&self) -> usize {
        self.returns
    }

    /// Largest range (m).
    pub fn range_m(&self) -> f64 {
        self.range_m
    }
}

impl Network for Unet {
    const PREDICTION: Prediction = Prediction::Depth;

    /// `[B, 2K, H, W]`: depth in metres, then confidence logits.
    fn predict(&self, y: Tensor<4>, sensor: &SensorTensors) -> Tensor<4> {
        if self.candidates > 0 {
            return self.predict_on_evidence(y, sensor);
        }
        let o = self.logits(y, sensor);
        let k = self.returns;
        if self.score_bins > 0 {
            let kt = k * self.score_bins;
            let depth = self.local_soft_argmax(o.clone().narrow(1, 0, kt));
            return Tensor::cat(vec![depth, o.narrow(1, kt, k)], 1);
        }
        let depth = sigmoid(o.clone().narrow(1, 0, k)) * self.range_m;
        Tensor::cat(vec![depth, o.narrow(1, k, k)], 1)
    }

    /// `[B, 2K + K·T, H, W]` with the score volume: depth, confidence logits, and the scores'
    /// log-probabilities over the bins (for the cross-entropy against the true bin).
    fn train_output(&self, y: Tensor<4>, sensor: &SensorTensors) -> Tensor<4> {
        if self.candidates > 0 {
            return self.train_on_evidence(y, sensor);
        }
        let (k, t) = (self.returns, self.score_bins);
        if t == 0 {
            return self.predict(y, sensor);
        }
        let o = self.logits(y, sensor);
        let [b, _, h, w] = o.dims();
        // one log-softmax: the range from its exponential, the cross-entropy from it
        let logp = burn::tensor::activation::log_softmax(o.clone().narrow(1, 0, k * t).reshape([b, k, t, h, w]), 2);
        let depth = self.expected_range(logp.clone().exp());
        Tensor::cat(vec![depth, o.narrow(1, k * t, k), logp.reshape([b, k * t, h, w])], 1)
    }

    /// On the range fit's evidence: the first return, the posterior's mode refined in the tap
    /// domain, and the fit's second return ([`crate::depth_evidence`]).
    fn decode_frames(&self, y: &ndarray::ArrayView4<'_, f32>, sensor: &SensorTensors) -> Option<ndarray::Array4<f32>> {
        (self.candidates > 0).then(|| self.decode_on_evidence(y, sensor))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::{Distribution, TensorData};
    use tcsense_sensor::codes::{CodeShape, Constraints};
    use tcsense_sensor::generate::random_codes;
    use tcsense_sensor::{MeasurementMatrix, SensorParams};

    fn sensor(h: usize, w: usize, device: &Device) -> (MeasurementMatrix, SensorTensors) {
        let shape = CodeShape { bh: 2, bw: 2, taps: 4, length: 8, drain: false };
        let codes = random_codes(shape, 607e6, Constraints { tap: true, ..Default::default() }, 1).unwrap();
        let a = MeasurementMatrix::synthesize(&codes, &SensorParams::from_codes(&codes).validate().unwrap()).unwrap();
        let st = SensorTensors::new(&a, h, w, device).unwrap();
        (a, st)
    }

    #[test]
    fn shapes_units_frame_rule_and_scale_invariance() {
        let device = Device::flex();
        let cfg = UnetConfig::new(4, 8, 12.0).with_base_width(4).with_levels(3);
        assert_eq!(cfg.stride(), 4);
        let net = cfg.init(&device);
        // 6×10 is not a multiple of 4: padded inside, cropped back
        for (h, w) in [(8, 8), (6, 10)] {
            let (_, st) = sensor(h, w, &device);
            let y = Tensor::<4>::random([2, 4, h, w], Distribution::Uniform(0.0, 1.0), &device);
            let (depth, conf) = net.forward(y.clone(), &st);
            assert_eq!((depth.dims(), conf.dims()), ([2, 2, h, w], [2, 2, h, w]));
            let d: Vec<f32> = depth.clone().into_data().try_into_vec().unwrap();
            assert!(d.iter().all(|&v| (0.0..=12.0).contains(&v)), "depth within the range (m)");
            let c: Vec<f32> = conf.into_data().try_into_vec().unwrap();
            assert!(c.iter().all(|&v| (0.0..=1.0).contains(&v)));
            // y and 10·y give the same depth
            let (d10, _) = net.forward(y * 10.0, &st);
            let diff = (d10 - depth).abs().max().into_scalar::<f32>();
            assert!(diff < 1e-4, "scale changes the depth by {diff} m");
        }
        // the normalisation makes every bright pixel's waveform unit length
        let x0 = Tensor::<4>::from_data(TensorData::new(vec![3.0f32, 0.0, 4.0, 0.0], [1, 2, 1, 2]), &device); // pixel 0: (3, 4), pixel 1: dark
        let n: Vec<f32> = Unet::normalise(x0).into_data().try_into_vec().unwrap();
        assert!((n[0] - 0.6).abs() < 1e-2 && (n[1] - 0.0).abs() < 1e-6 && (n[2] - 0.8).abs() < 1e-2);
        // FLOPs at 8×8, widths 4, 8, 16 on 64, 16, 4 pixels: Aᵀ, encoder, decoder, head
        let want = 2.0 * (4.0 * 8.0 * 64.0)
            + 18.0 * 64.0 * (8.0 * 4.0 + 16.0)
            + 18.0 * 64.0 * (12.0 * 4.0 + 16.0)
            + 18.0 * 16.0 * (4.0 * 8.0 + 64.0)
            + 18.0 * 16.0 * (24.0 * 8.0 + 64.0)
            + 18.0 * 4.0 * (8.0 * 16.0 + 256.0)
            + 2.0 * 64.0 * 4.0 * 4.0;
        assert_eq!(cfg.flops(8, 8), want);
    }

    #[test]
    fn the_normalisation_has_a_finite_gradient_at_a_dark_pixel() {
        // deep sensing differentiates through x₀ = Aᵀy: √0 once gave NaN there, and the codes
        // became NaN within a few steps
        let device = Device::flex().autodiff();
        let x0 = Tensor::<4>::from_data(TensorData::new(vec![3.0f32, 0.0, 4.0, 0.0], [1, 2, 1, 2]), &device).require_grad();
        let grads = (Unet::normalise(x0.clone()) * 0.5).sum().backward();
        let g: Vec<f32> = x0.grad(&grads).expect("gradient").into_data().try_into_vec().unwrap();
        assert!(g.iter().all(|v| v.is_finite()), "{g:?}");
        // the lit pixel: ∂/∂x of Σ x/‖x‖ at (3, 4) is (‖x‖² − x·Σx)/‖x‖³ per entry, ×½
        let want = [(25.0 - 3.0 * 7.0) / 125.0 * 0.5, (25.0 - 4.0 * 7.0) / 125.0 * 0.5];
        assert!((g[0] - want[0]).abs() < 1e-2 && (g[2] - want[1]).abs() < 1e-2, "{g:?} against {want:?}");
    }

    #[test]
    fn the_score_volume_reads_the_range_between_bin_centres() {
        let device = Device::flex();
        let cfg = UnetConfig::new(4, 8, 12.0).with_base_width(4).with_levels(2).with_returns(2).with_head(UnetHead::ScoreVolume);
        assert_eq!(cfg.head_channels(), 18);
        let net = cfg.init(&device);
        assert_eq!(net.head_kind(), UnetHead::ScoreVolume);
        // centres of 8 bins of 1.5 m
        assert_eq!(net.bin_centres_m(), vec![0.75, 2.25, 3.75, 5.25, 6.75, 8.25, 9.75, 11.25]);
        // return 0: equal scores at bins 2 and 3 → 4.5 m; return 1: one bin far above the
        // rest → its centre, 9.75 m
        let mut s = vec![0f32; 16];
        (s[2], s[3], s[8 + 6]) = (30.0, 30.0, 40.0);
        let scores = Tensor::<4>::from_data(TensorData::new(s, [1, 16, 1, 1]), &device);
        let d: Vec<f32> = net.soft_argmax(scores).into_data().try_into_vec().unwrap();
        assert!((d[0] - 4.5).abs() < 1e-4 && (d[1] - 9.75).abs() < 1e-4, "{d:?}");
        // inference's local soft-argmax: return 0 has its peak at bin 1 and a second mode at
        // bin 6 that the mean over all bins is pulled to; locally only bins 0–2 count.
        // Return 1 peaks at the last bin: bins 6 and 7, nothing wrapped around to bin 0.
        let mut s = vec![0f32; 16];
        (s[1], s[2], s[6]) = (5.0, 4.0, 4.9);
        (s[8 + 7], s[8 + 6], s[8]) = (6.0, 5.0, 5.5);
        let scores = Tensor::<4>::from_data(TensorData::new(s.clone(), [1, 16, 1, 1]), &device);
        let local: Vec<f32> = net.local_soft_argmax(scores.clone()).into_data().try_into_vec().unwrap();
        let all: Vec<f32> = net.soft_argmax(scores).into_data().try_into_vec().unwrap();
        let c = net.bin_centres_m();
        let mean = |bins: &[usize], r: usize| {
            let (num, den) = bins
                .iter()
                .fold((0f64, 0f64), |(n, d), &j| (n + (s[8 * r + j] as f64).exp() * c[j] as f64, d + (s[8 * r + j] as f64).exp()));
            (num / den) as f32
        };
        assert!((local[0] - mean(&[0, 1, 2], 0)).abs() < 1e-4 && (local[1] - mean(&[6, 7], 1)).abs() < 1e-4, "{local:?}");
        assert!(local[0] < 3.0 && all[0] > 4.0, "the far mode pulls only the global mean: {local:?} {all:?}");
        assert!(local[1] > 10.0 && all[1] < 9.0, "no wrap-around: {local:?} {all:?}");
        // and through the whole network: depth within the range, scale invariant
        let (_, st) = sensor(8, 8, &device);
        let y = Tensor::<4>::random([1, 4, 8, 8], Distribution::Uniform(0.0, 1.0), &device);
        let (depth, conf) = net.forward(y.clone(), &st);
        assert_eq!((depth.dims(), conf.dims()), ([1, 2, 8, 8], [1, 2, 8, 8]));
        let dv: Vec<f32> = depth.clone().into_data().try_into_vec().unwrap();
        assert!(dv.iter().all(|&v| (0.75..=11.25).contains(&v)));
        let diff = (net.forward(y * 7.0, &st).0 - depth).abs().max().into_scalar::<f32>();
        assert!(diff < 1e-4, "scale changes the depth by {diff} m");
    }

    #[test]
    fn save_then_load_gives_identical_outputs() {
        let device = Device::flex();
        let cfg = UnetConfig::new(4, 8, 12.0).with_base_width(4).with_levels(2).with_returns(1);
        let net = cfg.init(&device);
        let (_, st) = sensor(8, 8, &device);
        let y = Tensor::<4>::random([1, 4, 8, 8], Distribution::Uniform(0.0, 1.0), &device);
        let before = net.predict(y.clone(), &st);
        let dir = std::env::temp_dir().join(format!("tcsense-unet-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        net.save_file(dir.join("m")).unwrap();
        let back = cfg.init(&device).try_load_file(dir.join("m")).unwrap();
        let after = back.predict(y, &st);
        assert_eq!(before.into_data(), after.into_data());
        std::fs::remove_dir_all(&dir).ok();
    }
}
