//! The lifetime decoder: tap images straight to fluorescence lifetimes, fit-free (in the manner
//! of FLI-Net, Smith et al., PNAS 2019, and Net-FLICS, Yao et al., Light Sci. Appl. 2019, on
//! the compressed measurement `y = A x` of paper eq. (1)).
//!
//! ```text
//! y [B, M, H, W] ──Aᵀ──▶ x₀ [B, T, H, W] ──DFT over t, harmonics 0..K──▶ F [B, 2K+1, H, W]
//! F_k ← F_k · e^{−ikφ},  e^{iφ} = Σ_pixels F₁ / |Σ_pixels F₁|            (delay reference)
//! F ÷ (‖F‖₂ per pixel + 10⁻³·mean‖F‖₂), and ‖F‖₂ / mean‖F‖₂ as one more channel
//! ──▶ U-Net (levels, base width) ──1×1──▶ [B, 5, H, W]
//! τ_m, τ₁, τ₂ = τ_lo·(τ_hi/τ_lo)^sigmoid(o)  (ns; τ₁ ≤ τ₂),  α₁ = sigmoid(o₃),  confidence logit o₄
//! ```
//!
//! **Why the Fourier harmonics.** A delay of the decay by `d` bins (the instrument's cables and
//! trigger; the codes loop, so it is a cyclic shift of the cube) multiplies harmonic `k` of
//! `x₀` by `e^{−2πikd/T}` — the frame's summed first harmonic turns by the same angle, so
//! `F_k·e^{−ikφ}` does not change: the network's input, and so its output, is exactly the same
//! for `Aᵀy` and for `Aᵀy` delayed cyclically (tested). The harmonics are a fixed linear
//! pooling of the time axis (`T = 256` bins to `2K + 1 = 33` channels by default), so the
//! learned part is a 2-D U-Net on a few channels: cheap enough for the sensor's frame rate.
//! The per-pixel normalisation makes the output independent of the scale of `y`; the relative
//! brightness channel tells the network how much light a pixel has (its confidence).
//!
//! Outputs: the amplitude-weighted mean lifetime `τ_m = Σ a_i τ_i / Σ a_i` (what a lifetime map
//! shows), two components `τ₁ ≤ τ₂` with the amplitude fraction `α₁` of `τ₁` (one component:
//! `τ₁ = τ₂`), and a confidence logit (the pixel holds a fluorophore). The intensity is not
//! learned: it is the photo-charge the taps collected, `Σ_m y_m` ([`intensity`]).

use burn::config::Config;
use burn::module::{Module, Param};
use burn::nn::conv::{Conv2d, Conv2dConfig};
use burn::nn::Initializer;
use burn::tensor::activation::log_softmax;
use burn::tensor::activation::sigmoid;
use burn::tensor::Int;
use burn::tensor::{Device, Tensor, TensorData};

use crate::evidence_tensors::windowed_likelihood;
use crate::evidence_tensors::with_gradient_of;
use crate::lifetime_evidence::{decays_tensor, lifetime_evidence};
use crate::net::{Network, Prediction};
use crate::sensor_tensors::SensorTensors;
use crate::unet::{conv1x1, trunk, trunk_flops, Block, Unet, NORM_FLOOR};
use tcsense_fits::lifetime_taps::evidence::{evidence_into, feature_channels_with, Evidence, EvidenceBuffers};
use tcsense_fits::lifetime_taps::{estimate_instrument, Instrument, LifetimeCosts, LifetimeTemplates, TapFitOptions};

/// Channels of the prediction: `τ_m`, `τ₁`, `τ₂` (ns), `α₁`, confidence logit.
pub const OUTPUTS: usize = 5;
/// Floor of the delay reference's magnitude (a dark frame has no phase).
const REF_FLOOR: f32 = 1e-20;

/// The head's raw output `o_s` each wider window starts at: its weight `e^{clip(6·o_s − 6)}`
/// starts at `e^{−3}`.
pub const WIDER_START: f64 = 0.5;

/// Gain of the head's temperature channel `o_t`: the log-likelihood is weighed by
/// `e^{clip(TEMPER_GAIN·o_t)}` pixel by pixel ([`LifetimeNetConfig::temper`]); `o_t = 0` (the
/// untrained head) is a weight of 1, the fit's own likelihood.
pub const TEMPER_GAIN: f64 = 2.0;
/// Bounds of the log-weight of a tempered log-likelihood: from `e^{−4}` (the evidence all but
/// ignored where the network has learnt it misleads) to `e^{1}` (sharpened).
pub const TEMPER_RANGE: [f64; 2] = [-4.0, 1.0];

/// Lifetime-decoder hyper-parameters.
#[derive(Config, Debug, PartialEq)]
pub struct LifetimeNetConfig {
    /// Taps `M`.
    pub taps: usize,
    /// Bins `T` of `x₀ = Aᵀy`.
    pub bins: usize,
    /// Harmonics `K` of the cycle kept (input channels `2K + 2`).
    #[config(default = 16)]
    pub harmonics: usize,
    /// Channels of the U-Net's first level, doubled at every level down.
    #[config(default = 16)]
    pub base_width: usize,
    /// Resolutions (`levels − 1` down-samplings by 2).
    #[config(default = 3)]
    pub levels: usize,
    /// Lifetimes the outputs span, `[τ_lo, τ_hi]` (ns).
    #[config(default = "[0.05, 25.0]")]
    pub tau_range_ns: [f64; 2],
    /// What the network reads (`harmonics` in runs written before the fit's evidence).
    #[config(default = "LifetimeInput::Harmonics")]
    pub input: LifetimeInput,
    /// Points `G` of the log grid of lifetimes over `tau_range_ns` ([`LifetimeInput::Costs`]).
    #[config(default = 96)]
    pub points: usize,
    /// Grid points pooled into one feature channel ([`LifetimeInput::Costs`]).
    #[config(default = 2)]
    pub pool: usize,
    /// Sides of the wider windows whose log-likelihoods the network adds to the fit's 3×3
    /// window's, each with a weight it sets pixel by pixel ([`LifetimeInput::Costs`]; none in
    /// runs written before them).
    #[config(default = "Vec::new()")]
    pub windows: Vec<usize>,
    /// Side of the neighbourhood over which the fit's window's log-likelihood is pooled with
    /// the neighbours of like lifetime before the prior is added (0: the window alone;
    /// [`tcsense_fits::evidence::similarity_pool`], [`LifetimeInput::Costs`]; 0 in runs
    /// written before it).
    #[config(default = 0)]
    pub pool_like: usize,
    /// Side, in blocks of the mosaic, of the superpixels each frame's instrument is fitted on
    /// (0: from the frame's photons, [`tcsense_fits::lifetime_taps::TapFitOptions::instrument_blocks`];
    /// 1: every pixel, as in runs written before it; [`LifetimeInput::Costs`]).
    #[config(default = 0)]
    pub instrument_blocks: usize,
    /// With `instrument_blocks` 0, a dim frame's instrument in training on its brightest pixels
    /// under the frame's mixture (true), or on superpixels (false: about 5× faster to train, and as
    /// in runs written before it; [`tcsense_fits::lifetime_taps::TapFitOptions::instrument_mixture`]).
    /// The network decodes with the mixture whatever it was trained with (its
    /// [`Network::decode_frames`], and so its validation and every decoder of the run).
    #[config(default = false)]
    pub instrument_mixture: bool,
    /// Weigh the log-likelihood (the window's, pooled or widened) by a temperature the head
    /// sets pixel by pixel, `e^{clip(2·o_t, −4, 1)}`, before the prior is added: the network
    /// may soften evidence that is sharp and wrong (a pooled likelihood across a cell's edge, a
    /// biased instrument) instead of fighting it with its prior ([`LifetimeInput::Costs`];
    /// false in runs written before it).
    #[config(default = false)]
    pub temper: bool,
    /// Refine the posterior's mode in the tap domain wherever it is within one point of the
    /// grid of the fit's own argmin, not only at it ([`TapFitOptions::refine_near_mode`]; false
    /// in runs written before it).
    #[config(default = false)]
    pub refine_near_mode: bool,
}

/// What the lifetime decoder reads from the taps (see the module documentation).
#[derive(Config, Debug, PartialEq, Eq, Copy)]
pub enum LifetimeInput {
    /// The harmonics of `Aᵀy`, turned by the frame's own phase.
    Harmonics,
    /// The fit to the taps' evidence ([`tcsense_fits::lifetime_taps::evidence`]): its
    /// log-likelihood of every lifetime of a log grid (the instrument estimated from the frame)
    /// plus a learned log-prior over the grid, read from the per-pixel posteriors of the
    /// neighbourhood; the lifetime is the posterior's mode, refined by a parabola.
    Costs,
}

/// The network.
#[derive(Module, Debug)]
pub struct LifetimeNet {
    down: Vec<Block>,
    up: Vec<Block>,
    head: Conv2d,
    harmonics: usize,
    bins: usize,
    tau_range_ns: [f64; 2],
    /// Grid points `G` of the fit's evidence; 0 for the harmonics ([`LifetimeInput::Costs`]).
    points: usize,
    /// Grid points pooled into one feature channel.
    pool: usize,
    /// Sides of the wider windows of the fit's evidence.
    windows: Vec<usize>,
    /// Side of the neighbourhood the evidence is pooled over by likeness (0: none).
    pool_like: usize,
    /// Side of the superpixels of the instrument's fit (0: from the frame's photons).
    instrument_blocks: usize,
    /// A dim frame's instrument under the frame's mixture (else on superpixels).
    instrument_mixture: bool,
    /// The log-likelihood weighed by a learned temperature (the head's last channel).
    temper: bool,
    /// The mode refined in the tap domain within a point of the fit's argmin.
    refine_near_mode: bool,
    /// The decays' onset (s) when known (a calibration): the fit whose evidence the network
    /// reads searches only the IRF's width. Not trained: set when decoding
    /// ([`LifetimeNet::with_onset`]).
    onset_s: Option<f64>,
}

impl LifetimeNetConfig {
    /// Channels of level `l`.
    pub fn width(&self, l: usize) -> usize {
        self.base_width << l
    }

    /// Input channels of the U-Net: `2K + 1` harmonics and the relative brightness, or the
    /// pooled per-pixel posteriors, the log intensity and the lit mask.
    pub fn features(&self) -> usize {
        match self.input {
            LifetimeInput::Harmonics => 2 * self.harmonics + 2,
            LifetimeInput::Costs => feature_channels_with(self.points, self.pool, self.windows.len()),
        }
    }

    /// Channels of the head: the five outputs, or a log-prior per grid point, the confidence,
    /// a log-weight per wider window and the temperature (when tempered).
    pub fn head_channels(&self) -> usize {
        match self.input {
            LifetimeInput::Harmonics => OUTPUTS,
            LifetimeInput::Costs => self.points + 1 + self.windows.len() + usize::from(self.temper),
        }
    }

    /// Frames must be multiples of this (the model pads to it internally).
    pub fn stride(&self) -> usize {
        1 << self.levels.saturating_sub(1)
    }

    /// Build the network.
    pub fn init(&self, device: &Device) -> LifetimeNet {
        let down =
            (0..self.levels).map(|l| Block::new(if l == 0 { self.features() } else { self.width(l - 1) }, self.width(l), device)).collect();
        let up = (0..self.levels.saturating_sub(1)).map(|l| Block::new(self.width(l + 1) + self.width(l), self.width(l), device)).collect();
        let costs = self.input == LifetimeInput::Costs;
        // the evidence's log-prior starts at zero: the untrained network is the fit
        let mut head = Conv2dConfig::new([self.width(0), self.head_channels()], [1, 1]);
        if costs {
            head = head.with_initializer(Initializer::Zeros);
        }
        let mut head = head.init(device);
        if costs && !self.windows.is_empty() {
            // the wider windows start half open (`e^{6·½ − 6} = e^{−3}`): at `e^{−6}` their
            // weights' gradients (6·e^{−6}) are too small for training to open them
            let mut bias = vec![0.0f32; self.head_channels()];
            bias[self.points + 1..self.points + 1 + self.windows.len()].fill(WIDER_START as f32);
            head.bias = Some(Param::from_tensor(Tensor::<1>::from_data(TensorData::new(bias, [self.head_channels()]), device)));
        }
        LifetimeNet {
            down,
            up,
            head,
            harmonics: self.harmonics,
            bins: self.bins,
            tau_range_ns: self.tau_range_ns,
            points: if costs { self.points } else { 0 },
            pool: self.pool,
            windows: if costs { self.windows.clone() } else { Vec::new() },
            pool_like: if costs { self.pool_like } else { 0 },
            instrument_blocks: self.instrument_blocks,
            instrument_mixture: self.instrument_mixture,
            temper: costs && self.temper,
            refine_near_mode: costs && self.refine_near_mode,
            onset_s: None,
        }
    }

    /// Multiply-adds ×2 per frame of `h × w`: `Aᵀ` and the harmonics folded into one
    /// `(2K+1) × M` matrix per pixel (as exported), the U-Net and the head.
    pub fn flops(&self, h: usize, w: usize) -> f64 {
        let px = (h * w) as f64;
        let input = match self.input {
            LifetimeInput::Harmonics => 2.0 * px * ((2 * self.harmonics + 1) * self.taps) as f64,
            LifetimeInput::Costs => 0.0, // the evidence is the fit's, counted with it
        };
        input
            + trunk_flops(self.features(), self.levels, |l| self.width(l), h, w)
            + 2.0 * px * (self.width(0) * self.head_channels()) as f64
    }

    /// The lifetime grid of the fit's evidence, `ln τ₀` (τ in ns) and the step of `ln τ`;
    /// `None` for the harmonics.
    pub fn log_grid_ns(&self) -> Option<(f64, f64)> {
        let [lo, hi] = self.tau_range_ns;
        (self.input == LifetimeInput::Costs).then(|| (lo.ln(), (hi / lo).ln() / (self.points.max(2) - 1) as f64))
    }

    /// Checks the settings; the error names the field.
    pub fn validate(&self) -> Result<(), String> {
        let [lo, hi] = self.tau_range_ns;
        if !(lo > 0.0 && hi > lo && hi.is_finite()) {
            return Err(format!("tau_range_ns: [{lo}, {hi}], expected 0 < lo < hi"));
        }
        if self.input == LifetimeInput::Costs && !(3..=1024).contains(&self.points) {
            return Err(format!("points: {}, expected 3 to 1024 points of the lifetime grid", self.points));
        }
        if self.pool == 0 || self.pool > self.points {
            return Err(format!("pool: {}, expected 1 to points ({})", self.pool, self.points));
        }
        if self.windows.len() > 8 {
            return Err(format!("windows: {:?}, expected at most 8 wider windows", self.windows));
        }
        let fit = TapFitOptions::default().window;
        let mut last = fit;
        for &side in &self.windows {
            if side % 2 == 0 || side <= last || side > tcsense_fits::range::MAX_WINDOW {
                return Err(format!(
                    "windows: {:?}, expected odd sides above the fit's {fit}, increasing, up to {}",
                    self.windows,
                    tcsense_fits::range::MAX_WINDOW
                ));
            }
            last = side;
        }
        let max = tcsense_fits::range::MAX_WINDOW;
        let most = tcsense_fits::lifetime_taps::MAX_INSTRUMENT_BLOCKS;
        if self.instrument_blocks > most {
            return Err(format!(
                "instrument_blocks: {}, expected 0 (chosen from each frame's photons) or a superpixel side of 1 to {most} blocks",
                self.instrument_blocks
            ));
        }
        if self.pool_like != 0 && !tcsense_fits::lifetime_taps::pooled_side(self.pool_like, fit) {
            return Err(format!(
                "pool_like: {}, expected 0 (the window alone) or an odd multiple of the fit's window {fit} above it, up to {max} (e.g. 9, 15)",
                self.pool_like
            ));
        }
        if self.pool_like != 0 && self.input != LifetimeInput::Costs {
            return Err(format!("pool_like: {} with the harmonics input, expected the fit's evidence (input costs)", self.pool_like));
        }
        if !self.windows.is_empty() && self.input != LifetimeInput::Costs {
            return Err(format!("windows: {:?} with the harmonics input, expected the fit's evidence (input costs)", self.windows));
        }
        if self.refine_near_mode && self.input != LifetimeInput::Costs {
            return Err("refine_near_mode: true with the harmonics input, expected the fit's evidence (input costs)".into());
        }
        if self.temper && self.input != LifetimeInput::Costs {
            return Err("temper: true with the harmonics input, expected the fit's evidence (input costs)".into());
        }
        Ok(())
    }
}

/// The DFT basis `[2K + 1, T]`: row 0 the sum, rows `1..=K` `cos(2πkt/T)`, rows `K+1..=2K`
/// `−sin(2πkt/T)` (so row pairs are the real and imaginary parts of `Σ_t x(t)e^{−2πikt/T}`).
pub fn dft_basis(harmonics: usize, bins: usize) -> Vec<f32> {
    let f = 2 * harmonics + 1;
    let mut b = vec![0f32; f * bins];
    for t in 0..bins {
        b[t] = 1.0;
        for k in 1..=harmonics {
            let a = 2.0 * std::f64::consts::PI * (k * t % bins) as f64 / bins as f64;
            b[k * bins + t] = a.cos() as f32;
            b[(harmonics + k) * bins + t] = (-a.sin()) as f32;
        }
    }
    b
}

/// The intensity of each pixel: the photo-charge of all its taps, `Σ_m y_m` (every bin of the
/// cycle goes to one tap, so it is the decay's integral over the cycle).
///
/// # Shapes
/// - `y`: `[B, M, H, W]` → `[B, 1, H, W]`
pub fn intensity(y: Tensor<4>) -> Tensor<4> {
    y.sum_dim(1)
}

impl LifetimeNet {
    /// The delay-referenced, normalised harmonics of `x₀` and the relative brightness.
    ///
    /// # Shapes
    /// - `x0`: `[B, T, H, W]` → `[B, 2K + 2, H, W]`
    pub fn features(&self, x0: Tensor<4>) -> Tensor<4> {
        let [b, t, h, w] = x0.dims();
        let k = self.harmonics;
        let f = 2 * k + 1;
        let device = x0.device();
        let basis = Tensor::<2>::from_data(TensorData::new(dft_basis(k, t), [f, t]), &device);
        let spec = basis.unsqueeze::<3>().expand([b, f, t]).matmul(x0.reshape([b, t, h * w])).reshape([b, f, h, w]); // [B, 2K+1, H, W]
        Self::reference(spec, k)
    }

    /// Turn harmonic `k` by `e^{−ikφ}` (`φ` the phase of the frame's summed first harmonic),
    /// normalise each pixel and append its relative brightness.
    ///
    /// Both norms are `√(Σ… + 10⁻³⁰)` ([`Unet::pixel_norm`] per pixel): a finite gradient
    /// where there is no light, which deep sensing differentiates through to the codes.
    ///
    /// # Shapes
    /// - `spec`: `[B, 2K + 1, H, W]` (sum, real parts, imaginary parts) → `[B, 2K + 2, H, W]`
    pub fn reference(spec: Tensor<4>, k: usize) -> Tensor<4> {
        let total = spec.clone().sum_dim(2).sum_dim(3); // [B, 2K+1, 1, 1]
        let (re1, im1) = (total.clone().narrow(1, 1, 1), total.narrow(1, k + 1, 1)); // [B, 1, 1, 1]
        let r = (re1.clone().powi_scalar(2) + im1.clone().powi_scalar(2)).add_scalar(1e-30).sqrt().add_scalar(REF_FLOOR);
        let (c1, s1) = (re1 / r.clone(), im1 / r);
        // cos kφ, sin kφ by the angle-addition recursion
        let (mut cs, mut ss) = (vec![c1.clone()], vec![s1.clone()]);
        for j in 1..k {
            let (c, s) = (cs[j - 1].clone(), ss[j - 1].clone());
            cs.push(c.clone() * c1.clone() - s.clone() * s1.clone());
            ss.push(s * c1.clone() + c * s1.clone());
        }
        let (c, s) = (Tensor::cat(cs, 1), Tensor::cat(ss, 1)); // [B, K, 1, 1]
        let dc = spec.clone().narrow(1, 0, 1);
        let (re, im) = (spec.clone().narrow(1, 1, k), spec.narrow(1, k + 1, k)); // [B, K, H, W]
        let re_r = re.clone() * c.clone() + im.clone() * s.clone();
        let im_r = im * c - re * s;
        let z = Tensor::cat(vec![dc, re_r, im_r], 1); // [B, 2K+1, H, W]
        let norm = Unet::pixel_norm(z.clone()); // [B, 1, H, W]
        let mean = norm.clone().mean_dim(2).mean_dim(3); // [B, 1, 1, 1]
        let rel = norm.clone() / (mean.clone() + 1e-30);
        Tensor::cat(vec![z / (norm + mean * NORM_FLOOR + 1e-30), rel], 1)
    }

    /// The prediction from `x₀ = Aᵀy` (what the delay invariance is a property of).
    ///
    /// # Shapes
    /// - `x0`: `[B, T, H, W]` → `[B, 5, H, W]`: `τ_m`, `τ₁`, `τ₂` (ns), `α₁`, confidence logit
    pub fn from_adjoint(&self, x0: Tensor<4>) -> Tensor<4> {
        let o = conv1x1(&self.head, trunk(&self.down, &self.up, self.features(x0))); // [B, 5, H, W]
        let [lo, hi] = self.tau_range_ns;
        let (lo, span) = (lo.ln(), (hi / lo).ln());
        let tau = |o: Tensor<4>| (sigmoid(o) * span).add_scalar(lo).exp();
        let (ta, tb) = (tau(o.clone().narrow(1, 1, 1)), tau(o.clone().narrow(1, 2, 1)));
        Tensor::cat(
            vec![
                tau(o.clone().narrow(1, 0, 1)),
                ta.clone().min_pair(tb.clone()),
                ta.max_pair(tb),
                sigmoid(o.clone().narrow(1, 3, 1)),
                o.narrow(1, 4, 1),
            ],
            1,
        )
    }

    /// Whether the network reads the fit's evidence ([`LifetimeInput::Costs`]).
    pub fn input_kind(&self) -> LifetimeInput {
        if self.points > 0 {
            LifetimeInput::Costs
        } else {
            LifetimeInput::Harmonics
        }
    }

    /// Sides of the wider windows of the fit's evidence (none: the fit's own window only).
    pub fn windows(&self) -> &[usize] {
        &self.windows
    }

    /// Side of the neighbourhood the fit's evidence is pooled over by likeness (0: none).
    pub fn pool_like(&self) -> usize {
        self.pool_like
    }

    /// The network decoding with the decays' onset known (s; `None`: fitted to each frame, as
    /// in training): its evidence comes from the fit at that onset, which then searches only
    /// the IRF's width (`reconstruct --onset-ns`, as `infer --onset-ns` for its exported graph).
    /// The harmonics network fits no instrument: an error names it.
    pub fn with_onset(mut self, onset_s: Option<f64>) -> std::result::Result<Self, String> {
        if onset_s.is_some() && self.input_kind() != LifetimeInput::Costs {
            return Err(
                "a known onset is for a lifetime network on the fit's evidence; this one reads the harmonics of Aᵀy and fits no onset"
                    .into(),
            );
        }
        self.onset_s = onset_s;
        if onset_s.is_some() {
            self.fit_options().validate()?;
        }
        Ok(self)
    }

    /// Side of the superpixels each frame's instrument is fitted on (0: from its photons).
    pub fn instrument_blocks(&self) -> usize {
        self.instrument_blocks
    }

    /// Whether the log-likelihood is weighed by a learned temperature (the head's last channel,
    /// after the log-prior, the confidence and the wider windows' log-weights).
    pub fn tempered(&self) -> bool {
        self.temper
    }

    /// Points `G` of the lifetime grid and the points pooled per feature channel.
    pub fn grid_points(&self) -> (usize, usize) {
        (self.points, self.pool)
    }

    /// The lifetime grid: `ln τ₀` (τ in ns) and the step of `ln τ`.
    pub fn log_grid_ns(&self) -> (f64, f64) {
        let [lo, hi] = self.tau_range_ns;
        (lo.ln(), (hi / lo).ln() / (self.points.max(2) - 1) as f64)
    }

    /// The settings of the fit whose evidence the network reads: its grid, every lit pixel
    /// (no intensity floor: the network decides), the instrument fitted to the frame.
    pub fn fit_options(&self) -> TapFitOptions {
        let [lo, hi] = self.tau_range_ns;
        TapFitOptions {
            tau_range_s: [lo * 1e-9, hi * 1e-9],
            points: self.points,
            min_intensity: 0.0,
            pool_like: self.pool_like,
            instrument_blocks: self.instrument_blocks,
            instrument_mixture: self.instrument_mixture,
            refine_near_mode: self.refine_near_mode,
            onset_s: self.onset_s,
            ..Default::default()
        }
    }

    /// The fit's evidence of every frame of a batch, on the CPU (no gradient reaches `y`).
    ///
    /// # Shapes
    /// - `y`: `[B, M, H, W]` → features `[B, F, H, W]`, skip `[B, G, H, W]`
    pub fn evidence(&self, y: Tensor<4>, sensor: &SensorTensors) -> (Tensor<4>, Tensor<4>) {
        let (features, skip, _) = self.evidence_frames(y, sensor);
        (features, skip)
    }

    /// [`Self::evidence`] and, per frame, the instrument the fit found and the noise level.
    fn evidence_frames(&self, y: Tensor<4>, sensor: &SensorTensors) -> (Tensor<4>, Tensor<4>, Vec<(Instrument, f32)>) {
        let [b, m, h, w] = y.dims();
        let device = y.device();
        let v: Vec<f32> = y.into_data().convert::<f32>().try_into_vec::<f32>().unwrap_or_default();
        let opts = self.fit_options();
        let (g, f) = ((1 + self.windows.len()) * self.points, feature_channels_with(self.points, self.pool, self.windows.len()));
        let mut features: Vec<f32> = Vec::with_capacity(b * f * h * w);
        let mut skip: Vec<f32> = Vec::with_capacity(b * g * h * w);
        let mut frames = Vec::with_capacity(b);
        for i in 0..b {
            let yi = ndarray::ArrayView3::from_shape((m, h, w), &v[i * m * h * w..(i + 1) * m * h * w]).expect("[M, H, W] frame");
            let templates = frame_templates(&yi, &sensor.matrix, &opts);
            let (e, _) = evidence_at(&yi, &templates, self.pool, &self.windows);
            features.extend(e.features.iter());
            skip.extend(e.skip.iter());
            frames.push((templates.instrument(), e.noise));
        }
        // (the evidence is pixel-major)
        (
            Tensor::<4>::from_data(TensorData::new(features, [b, h, w, f]), &device).permute([0, 3, 1, 2]),
            Tensor::<4>::from_data(TensorData::new(skip, [b, h, w, g]), &device).permute([0, 3, 1, 2]),
            frames,
        )
    }

    /// [`Self::evidence`] carrying the gradient of the evidence in the taps and in the sensor's
    /// `A` (deep sensing): the fit's values, the gradient of its differentiable copy at the
    /// instrument the fit found ([`crate::lifetime_evidence`]).
    ///
    /// # Shapes
    /// - `y`: `[B, M, H, W]` → features `[B, F, H, W]`, skip `[B, G, H, W]`
    pub fn evidence_with_gradient(&self, y: Tensor<4>, sensor: &SensorTensors) -> (Tensor<4>, Tensor<4>) {
        // (training refuses to learn codes for a network with wider windows: TrainConfig::validate)
        debug_assert!(self.windows.is_empty() && self.pool_like == 0, "the evidence's differentiable copy has the fit's window only");
        let b = y.dims()[0];
        let device = y.device();
        let (features, skip, frames) = self.evidence_frames(y.clone().detach(), sensor);
        let opts = self.fit_options();
        let instruments: Vec<Instrument> = frames.iter().map(|(instrument, _)| *instrument).collect();
        let decays = decays_tensor(&sensor.matrix, &instruments, &opts, &device);
        let nats: Vec<f32> = frames.iter().map(|(_, noise)| 1.0 / (2.0 * noise)).collect();
        let nats = Tensor::<1>::from_data(TensorData::new(nats, [b]), &device);
        let (post, copy) = lifetime_evidence(y, sensor.a.clone(), sensor.block, decays, nats, opts.window, self.pool, opts.background);
        with_gradient_of(features, skip, post, copy)
    }

    /// The posterior's logits over the grid (the fit's log-likelihood, at the learned
    /// temperature when tempered, plus the learned log-prior) and the confidence logit.
    ///
    /// # Shapes
    /// - `features`: `[B, F, H, W]`, `skip`: `[B, G, H, W]` → `([B, G, H, W], [B, 1, H, W])`
    pub fn posterior(&self, features: Tensor<4>, skip: Tensor<4>) -> (Tensor<4>, Tensor<4>) {
        let o = conv1x1(&self.head, trunk(&self.down, &self.up, features)); // [B, G + 1 + S (+ 1), H, W]
        let (g, wide) = (self.points, self.windows.len());
        let prior = o.clone().narrow(1, 0, g);
        let logit = o.clone().narrow(1, g, 1);
        let likelihood = if wide == 0 { skip } else { windowed_likelihood(&o, skip, g, wide) };
        if !self.temper {
            return (likelihood + prior, logit);
        }
        let [lo, hi] = TEMPER_RANGE;
        let weight = o.narrow(1, g + 1 + wide, 1).mul_scalar(TEMPER_GAIN).clamp(lo, hi).exp(); // [B, 1, H, W]
        (likelihood * weight + prior, logit)
    }

    /// The lifetime (ns) at a continuous grid coordinate `u`.
    ///
    /// # Shapes
    /// - `u`: `[B, 1, H, W]` → `[B, 1, H, W]`
    fn tau_at(&self, u: Tensor<4>) -> Tensor<4> {
        let (l0, step) = self.log_grid_ns();
        u.mul_scalar(step).add_scalar(l0).exp()
    }

    /// The five outputs from a lifetime and the confidence logit: `τ_m = τ₁ = τ₂`, `α₁ = 1`.
    fn one_component(tau: Tensor<4>, logit: Tensor<4>) -> Tensor<4> {
        let one = tau.ones_like();
        Tensor::cat(vec![tau.clone(), tau.clone(), tau, one, logit], 1)
    }

    /// The posterior's mode refined by a parabola through its log at the neighbouring points
    /// (within half a step; none at the grid's ends or where a neighbour ties with it).
    ///
    /// # Shapes
    /// - `logits`: `[B, G, H, W]` → `u` `[B, 1, H, W]` (grid coordinate)
    pub fn mode(logits: Tensor<4>) -> Tensor<4> {
        let g = logits.dims()[1];
        let best: Tensor<4, Int> = logits.clone().argmax(1); // [B, 1, H, W]
        let lo = best.clone().sub_scalar(1).clamp_min(0);
        let hi = best.clone().add_scalar(1).clamp_max(g as i64 - 1);
        let (l0, lm, lp) = (logits.clone().gather(1, best.clone()), logits.clone().gather(1, lo), logits.gather(1, hi));
        // an interior maximum: both neighbours below it (at either end of the grid a neighbour
        // is the point itself)
        let interior = lm.clone().lower(l0.clone()).bool_and(lp.clone().lower(l0.clone()));
        let curv = lm.clone() + lp.clone() - l0.mul_scalar(2.0); // < 0 there
        let delta = ((lm - lp) / curv.clone().clamp_max(-1e-12)).mul_scalar(0.5).clamp(-0.5, 0.5);
        let delta = delta.mask_fill(interior.bool_not(), 0.0);
        best.float() + delta
    }

    /// Encoder blocks, finest level first (for exporters).
    pub fn down(&self) -> &[Block] {
        &self.down
    }

    /// Decoder blocks: `up()[l]` runs at level `l` on `[up-sampled level l+1, skip l]`.
    pub fn up(&self) -> &[Block] {
        &self.up
    }

    /// The 1×1 head to the five raw outputs.
    pub fn head(&self) -> &Conv2d {
        &self.head
    }

    /// Bins `T` of `x₀`.
    pub fn bins(&self) -> usize {
        self.bins
    }

    /// Harmonics `K`.
    pub fn harmonics(&self) -> usize {
        self.harmonics
    }

    /// `[τ_lo, τ_hi]` (ns).
    pub fn tau_range_ns(&self) -> [f64; 2] {
        self.tau_range_ns
    }
}

impl Network for LifetimeNet {
    const PREDICTION: Prediction = Prediction::Lifetime;

    /// `[B, 5, H, W]`: `τ_m`, `τ₁`, `τ₂` (ns), `α₁`, confidence logit.
    fn predict(&self, y: Tensor<4>, sensor: &SensorTensors) -> Tensor<4> {
        match self.input_kind() {
            LifetimeInput::Harmonics => self.from_adjoint(sensor.adjoint(y)),
            LifetimeInput::Costs => {
                let (features, skip) = self.evidence(y, sensor);
                let (logits, confidence) = self.posterior(features, skip);
                Self::one_component(self.tau_at(Self::mode(logits)), confidence)
            }
        }
    }

    /// On the fit's evidence: per frame the instrument, the evidence, the posterior's mode, and
    /// the mode refined in the tap domain where it is the fit's own argmin
    /// ([`LifetimeTemplates::refine_modes`]), `[B, 5, H, W]` as [`Network::predict`].
    fn decode_frames(&self, y: &ndarray::ArrayView4<'_, f32>, sensor: &SensorTensors) -> Option<ndarray::Array4<f32>> {
        (self.input_kind() == LifetimeInput::Costs).then(|| {
            let (b, _, h, w) = y.dim();
            let device = sensor.lambda.device();
            // (the instrument's search is not learned: decoded with the best, whatever the
            // training's evidence used)
            let opts = TapFitOptions { instrument_mixture: true, ..self.fit_options() };
            let mut out = ndarray::Array4::<f32>::zeros((b, OUTPUTS, h, w));
            for i in 0..b {
                let yi = y.index_axis(ndarray::Axis(0), i);
                let templates = frame_templates(&yi, &sensor.matrix, &opts);
                let (e, costs) = evidence_at(&yi, &templates, self.pool, &self.windows);
                let tensor = |a: ndarray::Array3<f32>| {
                    let (h, w, c) = a.dim();
                    Tensor::<4>::from_data(TensorData::new(a.into_raw_vec_and_offset().0, [1, h, w, c]), &device).permute([0, 3, 1, 2])
                };
                let (logits, confidence) = self.posterior(tensor(e.features), tensor(e.skip));
                let u: Vec<f32> = Self::mode(logits).into_data().try_into_vec().unwrap_or_default();
                let conf: Vec<f32> = confidence.into_data().try_into_vec().unwrap_or_default();
                let tau = templates.refine_modes(&yi, &costs, &u);
                let mut o = out.index_axis_mut(ndarray::Axis(0), i);
                for ((r, c), &t) in tau.indexed_iter() {
                    let ns = t * 1e9;
                    o[(0, r, c)] = ns;
                    o[(1, r, c)] = ns;
                    o[(2, r, c)] = ns;
                    o[(3, r, c)] = 1.0;
                    o[(4, r, c)] = conf[r * w + c];
                }
            }
            out
        })
    }

    /// The harmonics' five outputs; with the fit's evidence, the five outputs at the
    /// posterior's mean grid point (differentiable) and the log-posterior over the grid,
    /// `[B, 5 + G, H, W]`.
    fn train_output(&self, y: Tensor<4>, sensor: &SensorTensors) -> Tensor<4> {
        match self.input_kind() {
            LifetimeInput::Harmonics => self.from_adjoint(sensor.adjoint(y)),
            LifetimeInput::Costs => {
                let (features, skip) =
                    if sensor.differentiable { self.evidence_with_gradient(y, sensor) } else { self.evidence(y, sensor) };
                let (logits, confidence) = self.posterior(features, skip);
                let logp = log_softmax(logits, 1);
                let g = self.points;
                let index: Vec<f32> = (0..g).map(|i| i as f32).collect();
                let index = Tensor::<1>::from_floats(index.as_slice(), &logp.device()).reshape([1, g, 1, 1]);
                let mean = (logp.clone().exp() * index).sum_dim(1);
                Tensor::cat(vec![Self::one_component(self.tau_at(mean), confidence), logp], 1)
            }
        }
    }
}

/// The fit's templates for one frame through sensor `a`: the instrument estimated from the
/// frame.
///
/// # Shapes
/// - `y`: `[M, H, W]`
pub fn frame_templates(y: &ndarray::ArrayView3<'_, f32>, a: &tcsense_sensor::MeasurementMatrix, opts: &TapFitOptions) -> LifetimeTemplates {
    LifetimeTemplates::new(a, estimate_instrument(y, a, opts), opts)
}

/// The fit's evidence of one frame through templates built once (a stream's instrument), with
/// the `wider` windows' (sides) besides the fit's own, and the costs it came from (for
/// [`LifetimeTemplates::refine_modes`]).
///
/// # Shapes
/// - `y`: `[M, H, W]` → [`Evidence`] of `[·, H, W]`
pub fn evidence_at(
    y: &ndarray::ArrayView3<'_, f32>,
    templates: &LifetimeTemplates,
    pool: usize,
    wider: &[usize],
) -> (Evidence, LifetimeCosts) {
    evidence_at_into(y, templates, pool, wider, EvidenceBuffers::default())
}

/// [`evidence_at`] written into an earlier frame's `buffers` (a stream's): the same numbers.
///
/// # Shapes
/// - as [`evidence_at`]
pub fn evidence_at_into(
    y: &ndarray::ArrayView3<'_, f32>,
    templates: &LifetimeTemplates,
    pool: usize,
    wider: &[usize],
    buffers: EvidenceBuffers,
) -> (Evidence, LifetimeCosts) {
    let costs = templates.costs(y);
    (evidence_into(&costs, &y.sum_axis(ndarray::Axis(0)), y.dim().0, pool, wider, buffers), costs)
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::Distribution;
    use tcsense_sensor::codes::{CodeShape, Constraints};
    use tcsense_sensor::generate::random_codes;
    use tcsense_sensor::{MeasurementMatrix, SensorParams};

    fn sensor(t_len: usize, h: usize, w: usize, device: &Device) -> SensorTensors {
        let shape = CodeShape { bh: 2, bw: 2, taps: 4, length: t_len, drain: false };
        let codes = random_codes(shape, 607e6, Constraints { tap: true, ..Default::default() }, 1).unwrap();
        let a = MeasurementMatrix::synthesize(&codes, &SensorParams::from_codes(&codes).validate().unwrap()).unwrap();
        SensorTensors::new(&a, h, w, device).unwrap()
    }

    fn roll_t(x: &Tensor<4>, d: usize) -> Tensor<4> {
        let t = x.dims()[1];
        Tensor::cat(vec![x.clone().narrow(1, t - d, d), x.clone().narrow(1, 0, t - d)], 1)
    }

    #[test]
    fn same_lifetimes_for_a_cyclically_delayed_input() {
        let device = Device::flex();
        let cfg = LifetimeNetConfig::new(4, 16).with_harmonics(5).with_base_width(4).with_levels(2);
        device.seed(3);
        let net = cfg.init(&device);
        let (h, w) = (8, 8);
        let st = sensor(16, h, w, &device);
        let y = Tensor::<4>::random([2, 4, h, w], Distribution::Uniform(0.0, 1.0), &device);
        let x0 = st.adjoint(y.clone());
        let base = net.from_adjoint(x0.clone());
        assert_eq!(base.dims(), [2, OUTPUTS, h, w]);
        let v: Vec<f32> = base.clone().into_data().try_into_vec().unwrap();
        for (i, px) in v.chunks(h * w).enumerate() {
            let ch = i % OUTPUTS;
            if ch < 3 {
                assert!(px.iter().all(|&t| (0.05..=25.0).contains(&t)), "lifetimes within the range (ns)");
            }
            if ch == 3 {
                assert!(px.iter().all(|&a| (0.0..=1.0).contains(&a)));
            }
        }
        for c in 0..h * w * 2 {
            let (b, p) = (c / (h * w), c % (h * w));
            assert!(v[(b * OUTPUTS + 1) * h * w + p] <= v[(b * OUTPUTS + 2) * h * w + p], "τ₁ ≤ τ₂");
        }
        for d in [1, 5, 11] {
            let shifted = net.from_adjoint(roll_t(&x0, d));
            let diff = (shifted.clone() - base.clone()).abs().max().into_scalar::<f32>();
            assert!(diff < 2e-4, "delay {d}: outputs move by {diff}");
        }
        // the prediction does depend on the waveform's shape (a reversed input differs)
        let rev = Tensor::cat((0..16).rev().map(|j| x0.clone().narrow(1, j, 1)).collect(), 1);
        let diff = (net.from_adjoint(rev) - base.clone()).abs().max().into_scalar::<f32>();
        assert!(diff > 1e-3, "time reversal changes the outputs ({diff})");
        // y and 10·y give the same lifetimes
        let d10 = (net.predict(y.clone() * 10.0, &st) - net.predict(y, &st)).abs().max().into_scalar::<f32>();
        assert!(d10 < 1e-4, "scale changes the output by {d10}");
    }

    /// With wider windows the posterior is the fit's window's log-likelihood plus each wider
    /// window's at its learned weight `e^{clip(6·o_s − 6)}` (`e^{−3}` untrained) plus the
    /// log-prior; the head has a log-weight per window and the input the windows' posteriors.
    #[test]
    fn wider_windows_add_their_weighted_log_likelihoods() {
        let device = Device::flex();
        let cfg = LifetimeNetConfig::new(4, 16)
            .with_input(LifetimeInput::Costs)
            .with_points(12)
            .with_pool(2)
            .with_windows(vec![5, 9])
            .with_base_width(4)
            .with_levels(2);
        cfg.validate().unwrap();
        assert_eq!((cfg.features(), cfg.head_channels()), (3 * 6 + 2, 12 + 1 + 2));
        let net = cfg.init(&device);
        let (h, w) = (8, 8);
        let features = Tensor::<4>::random([1, cfg.features(), h, w], Distribution::Uniform(0.0, 1.0), &device);
        let skip = Tensor::<4>::random([1, 36, h, w], Distribution::Uniform(-50.0, 0.0), &device);
        let (logits, _) = net.posterior(features, skip.clone());
        let weight = (crate::depth_evidence::WIDER_OFFSET + crate::depth_evidence::WIDER_GAIN * WIDER_START).exp() as f32;
        assert!((weight - (-3.0f32).exp()).abs() < 1e-6);
        let want = skip.clone().narrow(1, 0, 12) + (skip.clone().narrow(1, 12, 12) + skip.narrow(1, 24, 12)).mul_scalar(weight);
        let diff = (logits - want).abs().max().into_scalar::<f32>();
        assert!(diff < 1e-4, "untrained: L_0 + e^-3 (L_5 + L_9), off by {diff}");
        for bad in [vec![4], vec![3, 9], vec![9, 5], vec![65]] {
            assert!(cfg.clone().with_windows(bad.clone()).validate().is_err(), "{bad:?}");
        }
        assert!(LifetimeNetConfig::new(4, 16).with_windows(vec![5]).validate().is_err(), "windows of the harmonics");
    }

    /// Tempered (`temper`), the head's last channel `o_t` weighs the log-likelihood by
    /// `e^{clip(2·o_t, −4, 1)}` before the prior is added: untrained (`o_t = 0`) the logits are
    /// the plain network's; with the channel's bias at `b` they are `e^{2b}·L` (clipped at the
    /// bounds), the wider windows' weights untouched.
    #[test]
    fn a_tempered_likelihood_is_weighed_by_the_heads_temperature() {
        let device = Device::flex();
        let base =
            LifetimeNetConfig::new(4, 16).with_input(LifetimeInput::Costs).with_points(12).with_pool(2).with_base_width(4).with_levels(2);
        for windows in [vec![], vec![5]] {
            let cfg = base.clone().with_windows(windows.clone()).with_temper(true);
            cfg.validate().unwrap();
            assert_eq!(cfg.head_channels(), 12 + 1 + windows.len() + 1);
            let (h, w) = (8, 8);
            let features = Tensor::<4>::random([1, cfg.features(), h, w], Distribution::Uniform(0.0, 1.0), &device);
            let skip = Tensor::<4>::random([1, 12 * (1 + windows.len()), h, w], Distribution::Uniform(-50.0, 0.0), &device);
            let plain = base.clone().with_windows(windows.clone()).init(&device);
            let (want, _) = plain.posterior(features.clone(), skip.clone());
            let mut net = cfg.init(&device);
            assert!(net.tempered() && !plain.tempered());
            let (untrained, _) = net.posterior(features.clone(), skip.clone());
            let diff = (untrained - want.clone()).abs().max().into_scalar::<f32>();
            assert!(diff < 1e-4, "untrained, windows {windows:?}: the plain network's logits, off by {diff}");
            for (b, weight) in [(-0.5f32, (-1.0f32).exp()), (0.3, 0.6f32.exp()), (-3.0, (-4.0f32).exp()), (2.0, 1f32.exp())] {
                let mut bias: Vec<f32> = net.head.bias.as_ref().unwrap().val().into_data().try_into_vec().unwrap();
                *bias.last_mut().unwrap() = b;
                net.head.bias = Some(Param::from_tensor(Tensor::<1>::from_data(TensorData::new(bias, [cfg.head_channels()]), &device)));
                let (logits, _) = net.posterior(features.clone(), skip.clone());
                // the plain logits are L (the prior is zero): tempered, weight · L
                let diff = (logits - want.clone().mul_scalar(weight)).abs().max().into_scalar::<f32>();
                assert!(diff < 1e-3, "bias {b}, windows {windows:?}: {weight}·L, off by {diff}");
            }
        }
        assert!(LifetimeNetConfig::new(4, 16).with_temper(true).validate().is_err(), "a tempered harmonics network");
    }

    /// The network on the fit's evidence, untrained (its log-prior is zero), is the fit: on
    /// clean taps of a two-lifetime scene at an onset of its own, the posterior's mode is the
    /// truth to a step of the grid and, refined in the tap domain, to 1 %; τ₁ = τ₂ = τ_m, α₁ = 1;
    /// training sees the posterior's mean and the log-posterior.
    #[test]
    fn on_the_fit_evidence_an_untrained_network_is_the_fit() {
        use tcsense_sensor::waveform::{decay_bin_averages, Cycle, IrfKernel};
        let device = Device::flex();
        let a = crate::evidence_tensors::testing::prototype_flim_matrix();
        let (h, w, t) = (8, 8, a.bins());
        let c = Cycle::new(t, a.bin_width_s());
        let tau = |j: usize| -> f64 {
            if j < 4 {
                1.2e-9
            } else {
                3.5e-9
            }
        };
        let k = IrfKernel::gaussian(c, 0.5e-9);
        let curves = [k.apply(&decay_bin_averages(c, 1.2e-9, 9e-9)), k.apply(&decay_bin_averages(c, 3.5e-9, 9e-9))];
        let x = Tensor::<4>::from_data(
            TensorData::new(
                (0..t * h * w).map(|i| (1e3 * curves[((i % w) >= 4) as usize][i / (h * w)]) as f32).collect::<Vec<f32>>(),
                [1, t, h, w],
            ),
            &device,
        );
        let st = SensorTensors::new(&a, h, w, &device).unwrap();
        let y = st.forward(x);
        let cfg = LifetimeNetConfig::new(4, t).with_base_width(4).with_levels(2).with_input(LifetimeInput::Costs).with_points(64);
        assert!(cfg.validate().is_ok() && cfg.clone().with_pool(0).validate().is_err());
        let net = cfg.init(&device);
        let out: Vec<f32> = net.predict(y.clone(), &st).into_data().try_into_vec().unwrap();
        assert_eq!(out.len(), OUTPUTS * h * w);
        let yv: Vec<f32> = y.clone().into_data().try_into_vec().unwrap();
        let ya = ndarray::Array4::from_shape_vec((1, 4, h, w), yv).unwrap();
        let refined = net.decode_frames(&ya.view(), &st).expect("the evidence's product");
        let (_, step) = net.log_grid_ns();
        for p in 0..h * w {
            let (tm, t1, t2, a1) = (out[p], out[h * w + p], out[2 * h * w + p], out[3 * h * w + p]);
            let want = tau(p % w) * 1e9;
            // the window straddles the edge at columns 3 and 4
            if !(3..=4).contains(&(p % w)) {
                assert!(((tm as f64).ln() - want.ln()).abs() < step, "pixel {p}: mode τ {tm} ns, want {want}");
                let r = refined[(0, 0, p / w, p % w)] as f64;
                assert!((r - want).abs() < 0.01 * want, "pixel {p}: refined τ {r} ns, want {want}");
            }
            assert!(tm == t1 && tm == t2 && a1 == 1.0);
            assert_eq!(refined[(0, 4, p / w, p % w)], out[4 * h * w + p], "the same confidence");
        }
        let train = net.train_output(y, &st);
        assert_eq!(train.dims(), [1, OUTPUTS + 64, h, w]);
        let total: Vec<f32> = train.narrow(1, OUTPUTS, 64).exp().sum_dim(1).into_data().try_into_vec().unwrap();
        assert!(total.iter().all(|v| (v - 1.0).abs() < 1e-4), "a posterior sums to 1: {total:?}");
        // the mode's parabola: a quadratic log-posterior peaking at 2.3 gives 2.3
        let logits = Tensor::<4>::from_data(
            TensorData::new((0..6).map(|i| -((i as f32 - 2.3).powi(2))).collect::<Vec<f32>>(), [1, 6, 1, 1]),
            &device,
        );
        let u: f32 = LifetimeNet::mode(logits).into_scalar();
        assert!((u - 2.3).abs() < 1e-5, "{u}");
    }

    /// Pooled by likeness (`pool_like`), the network's log-likelihood is the fit's window's
    /// pooled with its neighbours ([`tcsense_fits::evidence::similarity_pool`] at the window's
    /// noise level), 0 at its argmin; its features are the fit's own; the setting is checked.
    #[test]
    fn pooled_by_likeness_the_evidence_is_the_pooled_fit() {
        use tcsense_sensor::waveform::{decay_bin_averages, Cycle};
        let device = Device::flex();
        let a = crate::evidence_tensors::testing::prototype_flim_matrix();
        let (h, w, t) = (8, 8, a.bins());
        let c = Cycle::new(t, a.bin_width_s());
        let curves = [decay_bin_averages(c, 1.0e-9, 5e-9), decay_bin_averages(c, 3.0e-9, 5e-9)];
        let x: Vec<f32> = (0..t * h * w).map(|i| (50.0 * curves[((i % w) >= 4) as usize][i / (h * w)]) as f32).collect();
        let st = SensorTensors::new(&a, h, w, &device).unwrap();
        let y = st.forward(Tensor::<4>::from_data(TensorData::new(x, [1, t, h, w]), &device));
        let cfg = LifetimeNetConfig::new(4, t).with_base_width(4).with_levels(2).with_input(LifetimeInput::Costs).with_points(32);
        for bad in [2, 3, 6, 7, 12, 999] {
            assert!(cfg.clone().with_pool_like(bad).validate().is_err(), "{bad}");
        }
        assert!(LifetimeNetConfig::new(4, t).with_pool_like(9).validate().is_err(), "pooled harmonics");
        let (plain, pooled) = (cfg.init(&device), cfg.clone().with_pool_like(9).init(&device));
        assert_eq!(pooled.pool_like(), 9);
        let (f0, s0) = plain.evidence(y.clone(), &st);
        let (f1, s1) = pooled.evidence(y.clone(), &st);
        let v = |x: Tensor<4>| -> Vec<f32> { x.into_data().try_into_vec().unwrap() };
        assert_eq!(v(f0), v(f1), "the same features");
        // the pooled log-likelihood by hand
        let yv: Vec<f32> = y.into_data().try_into_vec().unwrap();
        let ya = ndarray::ArrayView3::from_shape((4, h, w), &yv).unwrap();
        let opts = plain.fit_options();
        let templates = frame_templates(&ya, &st.matrix, &opts);
        let costs = templates.costs(&ya);
        let window = costs.window_sums();
        let volume = costs.volume(&window, 4);
        let noise = tcsense_fits::evidence::noise_level(&volume);
        let want = tcsense_fits::evidence::similarity_pool(&volume, 1.0 / (2.0 * noise), 9);
        let (s0, s1) = (v(s0), v(s1));
        let g = 32;
        let mut differ = 0;
        for p in (0..h * w).filter(|&p| costs.lit[p]) {
            let col = &want[p * g..(p + 1) * g];
            let least = col.iter().fold(f32::INFINITY, |a, &b| a.min(b));
            for k in 0..g {
                let expect = -(col[k] - least) / (2.0 * noise);
                let got = s1[k * h * w + p];
                assert!((got - expect).abs() <= 1e-4 * expect.abs().max(1.0), "pixel {p}, point {k}: {got} against {expect}");
                differ += (s0[k * h * w + p] - got).abs().gt(&1e-3) as usize;
            }
        }
        assert!(differ > 0, "pooling changed nothing");
    }

    #[test]
    fn harmonics_are_the_dft_and_intensity_sums_the_taps() {
        let device = Device::flex();
        // one pixel, T = 8, x(t) = cos(2π·2t/8): harmonic 2 has real part T/2, the rest 0
        let t = 8;
        let b = dft_basis(3, t);
        let x: Vec<f32> = (0..t).map(|j| (2.0 * std::f64::consts::PI * 2.0 * j as f64 / t as f64).cos() as f32).collect();
        let f: Vec<f32> = (0..7).map(|r| (0..t).map(|j| b[r * t + j] * x[j]).sum()).collect();
        for (r, v) in f.iter().enumerate() {
            let want = if r == 2 { 4.0 } else { 0.0 };
            assert!((v - want).abs() < 1e-5, "row {r}: {v}");
        }
        let y = Tensor::<4>::from_floats([[[[1.0, 2.0]], [[3.0, 4.0]]]], &device); // [1, 2, 1, 2]
        let i: Vec<f32> = intensity(y).into_data().try_into_vec().unwrap();
        assert_eq!(i, vec![4.0, 6.0]);
        // FLOPs at 8×8, K = 2 (6 features), widths 4, 8: folded Aᵀ + DFT, trunk, head
        let cfg = LifetimeNetConfig::new(4, 16).with_harmonics(2).with_base_width(4).with_levels(2);
        let want = 2.0 * 64.0 * 20.0
            + 18.0 * 64.0 * (6.0 * 4.0 + 16.0)
            + 18.0 * 64.0 * (12.0 * 4.0 + 16.0)
            + 18.0 * 16.0 * (4.0 * 8.0 + 64.0)
            + 2.0 * 64.0 * 20.0;
        assert_eq!(cfg.flops(8, 8), want);
    }

    #[test]
    fn the_features_have_a_finite_gradient_at_a_dark_pixel() {
        // deep sensing differentiates through the features to the codes: √0 at a dark pixel
        // gave NaN (`train lifetime --learn-codes` diverged at its second step)
        let device = Device::flex().autodiff();
        // K = 1: [sum, Re, Im] of two pixels, the second dark
        let spec: Vec<f32> = vec![2.0, 0.0, 1.0, 0.0, 0.5, 0.0];
        let weights = Tensor::<4>::from_floats([[[[0.3, -0.7]], [[1.1, 0.2]], [[-0.4, 0.9]], [[0.6, -0.5]]]], &device); // [1, 4, 1, 2]
        let input = |v: &[f32]| Tensor::<4>::from_data(TensorData::new(v.to_vec(), [1, 3, 1, 2]), &device);
        let loss = |t: Tensor<4>| (LifetimeNet::reference(t, 1) * weights.clone()).sum();
        let x = input(&spec).require_grad();
        let grads = loss(x.clone()).backward();
        let g: Vec<f32> = x.grad(&grads).expect("gradient").into_data().try_into_vec().unwrap();
        assert!(g.iter().all(|v| v.is_finite()), "{g:?}");
        // the lit pixel's gradient is the loss's slope (central differences)
        for c in 0..3 {
            let i = 2 * c;
            let (mut up, mut down) = (spec.clone(), spec.clone());
            up[i] += 1e-2;
            down[i] -= 1e-2;
            let slope = (loss(input(&up)).into_scalar::<f32>() - loss(input(&down)).into_scalar::<f32>()) / 2e-2;
            assert!((g[i] - slope).abs() < 2e-2 * slope.abs().max(1.0), "channel {c}: {} against {slope}", g[i]);
        }
    }
}
