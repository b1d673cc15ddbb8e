//! Timings for `tcsense bench train` (printed, never asserted): one training step and one
//! inference frame of a network, medians of several runs.

use burn::module::Module;
use burn::optim::AdamConfig;
use burn::tensor::Device;
use ndarray::Array4;
use std::sync::atomic::AtomicBool;
use std::time::Instant;
use tcsense_kernels::timing::{median_by, median_ms};
use tcsense_models::decoder::{Control, Decoder};
use tcsense_models::net::{to_tensor, NetDecoder, Network, Prediction};
use tcsense_models::runs::{ModelConfig, RunSpec};
use tcsense_models::SensorTensors;
use tcsense_sensor::measure::measure_batch;
use tcsense_sensor::{Codes, Constraints, Irf, MeasurementMatrix, Sampling, Sensor};

use crate::config::Loss;
use crate::deep_sensing::{LearnCodes, Learner};
use crate::fit::{objective, Target};
use crate::{Result, TrainError};

/// Timings of one training step (the median step, ms).
#[derive(Debug, Clone, Copy)]
pub struct StepTiming {
    pub step_ms: f64,
    pub forward_ms: f64,
    pub backward_ms: f64,
    pub optim_ms: f64,
    /// Thread time inside the convolutions' multiply-add loops (GEMM calls, direct loops)
    /// during that step, summed over threads (ms).
    pub conv_ms: f64,
    /// Worker threads the step ran on.
    pub threads: usize,
    /// Floating-point operations of the step: 3× the forward pass of the batch (forward, input
    /// gradient, weight gradient of every layer).
    pub flop: f64,
}

impl StepTiming {
    /// GFLOP/s of the step.
    pub fn gflops(&self) -> f64 {
        self.flop / self.step_ms / 1e6
    }

    /// Share of the machine's core time during the step not spent in the convolutions'
    /// multiply-add loops (idle cores included).
    pub fn outside_conv(&self) -> f64 {
        (1.0 - self.conv_ms / (self.step_ms * self.threads as f64)).clamp(0.0, 1.0)
    }
}

/// Batch of a timed training step.
pub const BENCH_BATCH: usize = 2;

/// Median time of a training step (batch 2, synthetic cubes) at `h × w`.
pub fn bench_step(a: &MeasurementMatrix, model: &ModelConfig, h: usize, w: usize, steps: usize) -> Result<StepTiming> {
    timed(a, model, h, w, steps, None)
}

/// Median time of a deep-sensing training step (batch 2, synthetic cubes) at `h × w`: the
/// network and the code logits together, the gradient reaching the codes through the
/// measurements and the decoder's operators on `A(θ)` (the relaxed phase of `--learn-codes`,
/// tap + Hamming 2 + window 2 penalties on).
pub fn bench_step_learned(codes: &Codes, sampling: Sampling, model: &ModelConfig, h: usize, w: usize, steps: usize) -> Result<StepTiming> {
    let spec = RunSpec { model: model.clone(), sampling, irf: Irf::Ideal, measured: false };
    let a = Sensor::ideal(codes.clone(), sampling, Irf::Ideal)?;
    let a = a.matrix();
    let lc = LearnCodes::new(Constraints { tap: true, hamming: Some(2), window: Some(2) }, 2);
    let mut learner = Learner::new(&lc, codes, &spec, &Device::flex().autodiff())?;
    learner.schedule(0.5);
    timed(a, model, h, w, steps, Some(learner))
}

/// [`time_steps`] for the network of `model`, with the step's floating-point operations.
fn timed(a: &MeasurementMatrix, model: &ModelConfig, h: usize, w: usize, steps: usize, learner: Option<Learner>) -> Result<StepTiming> {
    let mut t = match model {
        ModelConfig::AdmmNet(c) => time_steps(a, |d| c.init(d), h, w, steps, learner),
        ModelConfig::Unet(c) => time_steps(a, |d| c.init(d), h, w, steps, learner),
        ModelConfig::Lifetime(c) => time_steps(a, |d| c.init(d), h, w, steps, learner),
    }?;
    t.flop = 3.0 * BENCH_BATCH as f64 * model.flops(h, w);
    Ok(t)
}

/// Time `steps` Adam steps after a warm-up one and return the median; with a `learner`, each
/// step also learns the codes (measurements and sensor operators from `A(θ)`, the penalty added
/// to the loss, the logits stepped by their own Adam).
fn time_steps<M: Network>(
    a: &MeasurementMatrix,
    init: impl Fn(&Device) -> M,
    h: usize,
    w: usize,
    steps: usize,
    mut learner: Option<Learner>,
) -> Result<StepTiming> {
    let device = Device::flex().autodiff();
    let sensor = SensorTensors::new(a, h, w, &device)?;
    let plan = a.plan(h, w)?;
    let mut model = crate::fit::seeded_init(&device, 1, init);
    let mut optim = AdamConfig::new().init();
    let x = Array4::from_shape_fn((BENCH_BATCH, a.bins(), h, w), |(b, j, r, c)| if (j + r / 8 + c / 8 + b) % 11 == 0 { 1.0 } else { 0.0 });
    let y = measure_batch(&plan, &x.view(), None, 0)?;
    // labels for depth networks: a return at a few metres in every other pixel
    let depth =
        Array4::from_shape_fn(
            (BENCH_BATCH, 2, h, w),
            |(b, k, r, c)| if (r + c + b) % 2 == 0 { 2.0 + k as f32 + (r % 7) as f32 * 0.1 } else { f32::NAN },
        );
    // labels for lifetime networks: 1–3 ns where a fluorophore is, background elsewhere
    let lifetimes = Array4::from_shape_fn((BENCH_BATCH, 5, h, w), |(_, k, r, c)| match (k, (r + c) % 3) {
        (4, s) => (s != 0) as u8 as f32,
        (_, 0) => f32::NAN,
        (3, _) => 0.5,
        (k, s) => (k + s) as f32,
    });
    let target = match M::PREDICTION {
        Prediction::Cube => Target::Cube { x: &x, scales: None, emd: false },
        Prediction::Depth => Target::Depth { depth: &depth, range_m: 10.0, grid: None, cap: None },
        Prediction::Lifetime => Target::Lifetime { labels: &lifetimes, grid: None, terms: crate::loss::LifetimeTerms::default() },
    };
    let mut times: Vec<[f64; 4]> = Vec::new();
    for _ in 0..steps.max(1) + 1 {
        let g0 = tcsense_kernels::conv::conv_seconds();
        let t0 = Instant::now();
        let loss = match &learner {
            None => objective(Loss::RmseMae, model.predict(to_tensor(&y.view(), &device), &sensor), target, &device),
            Some(l) => {
                let (yt, a_theta, penalty) = l.measurements(&x, &y, &device);
                objective(Loss::RmseMae, model.predict(yt, &sensor.clone().with_matrix(a_theta)), target, &device) + penalty
            }
        };
        let _: f32 = loss.clone().into_scalar();
        let t1 = Instant::now();
        let mut grads = loss.backward();
        let net_grads = burn::optim::GradientsParams::from_module(&mut grads, &model);
        let code_grads = learner.as_ref().map(|l| burn::optim::GradientsParams::from_module(&mut grads, &l.logits));
        let t2 = Instant::now();
        if let (Some(l), Some(g)) = (learner.as_mut(), code_grads) {
            l.step(g);
        }
        model = optim.step(1e-3, model, net_grads);
        let t3 = Instant::now();
        let conv = tcsense_kernels::conv::conv_seconds() - g0;
        times.push([(t1 - t0).as_secs_f64(), (t2 - t1).as_secs_f64(), (t3 - t2).as_secs_f64(), conv]);
    }
    times.remove(0); // warm-up
    let m = median_by(&times, |t| t[0] + t[1] + t[2]).ok_or(TrainError::InvalidParam {
        field: "steps",
        got: "0".into(),
        expected: "at least 1".into(),
    })?;
    Ok(StepTiming {
        step_ms: (m[0] + m[1] + m[2]) * 1e3,
        forward_ms: m[0] * 1e3,
        backward_ms: m[1] * 1e3,
        optim_ms: m[2] * 1e3,
        conv_ms: m[3] * 1e3,
        threads: rayon::current_num_threads(),
        flop: 0.0,
    })
}

/// Median inference time (ms) of one `h × w` frame on the CPU without autodiff, through the
/// decoder contract.
pub fn bench_forward(a: &Sensor, model: &ModelConfig, h: usize, w: usize, reps: usize) -> Result<f64> {
    let device = Device::flex();
    let mut decoder: Box<dyn Decoder> = match model {
        ModelConfig::AdmmNet(c) => {
            Box::new(NetDecoder::new(model.name(), crate::fit::seeded_init(&device, 1, |d| c.init(d)), device.clone()))
        }
        ModelConfig::Unet(c) => Box::new(NetDecoder::new(model.name(), crate::fit::seeded_init(&device, 1, |d| c.init(d)), device.clone())),
        ModelConfig::Lifetime(c) => {
            Box::new(NetDecoder::new(model.name(), crate::fit::seeded_init(&device, 1, |d| c.init(d)), device.clone()))
        }
    };
    let y = Array4::from_shape_fn((1, a.taps(), h, w), |(_, m, r, c)| ((m + r + c) % 7) as f32 * 0.1);
    let never = AtomicBool::new(false);
    median_ms(|| decoder.decode(y.view(), a, &Control::quiet(&never)).map(|out| drop(std::hint::black_box(out))), reps).map_err(Into::into)
}

/// Trainable parameters of a network.
pub fn parameters(model: &ModelConfig) -> usize {
    let device = Device::flex();
    match model {
        ModelConfig::AdmmNet(c) => c.init(&device).num_params(),
        ModelConfig::Unet(c) => c.init(&device).num_params(),
        ModelConfig::Lifetime(c) => c.init(&device).num_params(),
    }
}
