//! The GPU path (cargo feature `gpu`: burn's wgpu backend), against the CPU path on tiny
//! problems (8×8, T = 8): a training step of ADMM-Net and of the U-Net on the GPU equals the
//! CPU's, and a run written on one device loads and continues on the other with the same
//! outputs. CI runs this on Mesa's software Vulkan driver; without any Vulkan/Metal/DX12
//! adapter every test says so and passes without checking anything (unless
//! `TCSENSE_REQUIRE_GPU` is set).
#![cfg(feature = "gpu")]

use ndarray::Array4;
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use tcsense_datasets::lidar::LidarParams;
use tcsense_datasets::store::{generate, Generator, WriteOptions};
use tcsense_datasets::TimeGrid;
use tcsense_models::decoder::Control;
use tcsense_models::device::{device, Processor};
use tcsense_models::runs::{self, ModelConfig};
use tcsense_models::{AdmmNetConfig, Device, UnetConfig};
use tcsense_sensor::codes::{CodeShape, Constraints};
use tcsense_sensor::generate::random_codes;
use tcsense_sensor::{Codes, Sampling};
use tcsense_train::{train_on, Loss, Quiet, TrainConfig};

fn tmp() -> PathBuf {
    let d = std::env::temp_dir().join(format!(
        "tcsense-gpu-{}-{}",
        std::process::id(),
        std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_nanos()
    ));
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// The wgpu device, or `None` (with a message) where the machine has no adapter — a failure
/// instead when `TCSENSE_REQUIRE_GPU` is set (`scripts/test.sh` sets it where a Vulkan driver
/// is installed, so CI cannot skip these tests by accident).
fn gpu() -> Option<Device> {
    match device(Processor::Gpu) {
        Ok(d) => Some(d),
        Err(e) if std::env::var_os("TCSENSE_REQUIRE_GPU").is_some() => panic!("TCSENSE_REQUIRE_GPU is set but the GPU does not work: {e}"),
        Err(e) => {
            eprintln!("skipping the GPU test: {e}");
            None
        }
    }
}

/// A tiny LiDAR dataset, codes, and a config of one optimiser step per epoch (2 training
/// items, batch 2).
fn setup(dir: &Path, model: ModelConfig) -> (TrainConfig, Codes) {
    let t = model.bins(); // L = T (no oversampling)
    let gen = Generator::Lidar(LidarParams { height: 8, width: 8, ..Default::default() });
    let grid = TimeGrid { length: t, ..TimeGrid::default() };
    let cancel = AtomicBool::new(false);
    generate(&gen, &grid, 8, 1, &dir.join("ds"), &WriteOptions { shard_size: 8, force: false, progress: &|| {}, cancel: &cancel }).unwrap();
    let codes = random_codes(
        CodeShape { bh: 2, bw: 2, taps: 4, length: t, drain: false },
        607e6,
        Constraints { tap: true, ..Default::default() },
        2,
    )
    .unwrap();
    let mut cfg = TrainConfig::new(model, &dir.join("ds"), Loss::RmseMae, Sampling::Oversample(1));
    cfg.epochs = 1;
    cfg.batch_size = 2;
    cfg.max_train_items = Some(2);
    cfg.max_val_items = Some(1);
    cfg.learning_rate = 1e-2;
    (cfg, codes)
}

/// What the run's latest weights make of `y` on `device` (the cube, or depth and confidence).
fn output(run: &Path, y: &Array4<f32>, device: &Device) -> Vec<f32> {
    let mut r = runs::open(run, device).unwrap();
    let never = AtomicBool::new(false);
    let out = r.decoder.decode(y.view(), &r.sensor, &Control::quiet(&never)).unwrap();
    match (out.cube, out.depth, out.confidence) {
        (Some(c), _, _) => c.iter().copied().collect(),
        (None, Some(d), Some(c)) => d.iter().map(|&v| if v.is_finite() { v } else { 0.0 }).chain(c.iter().copied()).collect(),
        _ => panic!("no output"),
    }
}

/// `max |a − b| / max |b|`.
fn rel(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    let peak = b.iter().fold(0f32, |m, v| m.max(v.abs())).max(1e-12);
    a.iter().zip(b).fold(0f32, |m, (x, y)| m.max((x - y).abs())) / peak
}

fn y() -> Array4<f32> {
    Array4::from_shape_fn((1, 4, 8, 8), |(_, m, r, c)| ((m + r * 3 + c) % 5) as f32 * 0.2)
}

/// One step on each device from the same seed, then every cross-device combination: both
/// runs give the same output on both devices, and the GPU run resumes on the CPU (and the CPU
/// run on the GPU) like the CPU run resumes on the CPU.
fn same_on_both(model: ModelConfig) {
    let Some(gpu) = gpu() else { return };
    let cpu = Device::flex();
    let dir = tmp();
    let (cfg, codes) = setup(&dir, model);
    let never = AtomicBool::new(false);
    let on_cpu = train_on(&cfg, &codes, &dir.join("cpu"), false, &cpu, &Quiet, &never).unwrap();
    let on_gpu = train_on(&cfg, &codes, &dir.join("gpu"), false, &gpu, &Quiet, &never).unwrap();
    let (lc, lg) = (on_cpu[0].train_loss, on_gpu[0].train_loss);
    assert!((lc - lg).abs() <= 1e-4 * lc.abs(), "first-step loss: cpu {lc}, gpu {lg}");
    let y = y();
    let reference = output(&dir.join("cpu"), &y, &cpu);
    // the step's weights: trained on the GPU, read on the CPU and on the GPU
    for (run, dev, what) in [("gpu", &cpu, "gpu run on the cpu"), ("gpu", &gpu, "gpu run on the gpu"), ("cpu", &gpu, "cpu run on the gpu")]
    {
        let r = rel(&output(&dir.join(run), &y, dev), &reference);
        assert!(r <= 1e-4, "{what}: relative difference {r} from the cpu run on the cpu");
    }
    // resume each run on the other device for a second step
    let mut two = cfg.clone();
    two.epochs = 2;
    train_on(&two, &codes, &dir.join("cpu"), true, &gpu, &Quiet, &never).unwrap();
    train_on(&two, &codes, &dir.join("gpu"), true, &cpu, &Quiet, &never).unwrap();
    let r = rel(&output(&dir.join("gpu"), &y, &cpu), &output(&dir.join("cpu"), &y, &cpu));
    assert!(r <= 1e-3, "two steps with the devices swapped: relative difference {r}");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn admm_net_trains_and_runs_the_same_on_the_gpu() {
    same_on_both(ModelConfig::AdmmNet(AdmmNetConfig::new(4, 8).with_stages(2).with_channels(4)));
}

/// The delay prior: the CPU's delay-tap kernels against the GPU's roll + concatenate + conv2d
/// (16 bins: more than the largest dilation, 9).
#[test]
fn the_delay_prior_trains_and_runs_the_same_on_the_gpu() {
    same_on_both(ModelConfig::AdmmNet(
        AdmmNetConfig::new(4, 16).with_stages(2).with_channels(3).with_prior(tcsense_models::admm::Prior::Delay),
    ));
}

#[test]
fn unet_trains_and_runs_the_same_on_the_gpu() {
    let range_m = tcsense_datasets::grid::C * 8.0 / 607e6 / 2.0;
    same_on_both(ModelConfig::Unet(UnetConfig::new(4, 8, range_m).with_base_width(4).with_levels(2)));
}

/// Deep sensing on the GPU: the relaxed phase (codes and network learned together), the
/// projection onto the constraints and the phase on the projected codes run there too, with
/// the CPU's losses and the same projected codes.
#[test]
fn learned_codes_train_the_same_on_the_gpu() {
    let Some(gpu) = gpu() else { return };
    let dir = tmp();
    let (mut cfg, codes) = setup(&dir, ModelConfig::AdmmNet(AdmmNetConfig::new(4, 8).with_stages(2).with_channels(4)));
    cfg.epochs = 2;
    // one relaxed epoch (one step), then one on the projected codes
    let mut lc = tcsense_train::deep_sensing::LearnCodes::new(codes.constraints, 2);
    lc.relaxed_epochs = 1;
    cfg.learn_codes = Some(lc);
    let never = AtomicBool::new(false);
    let on_cpu = train_on(&cfg, &codes, &dir.join("cpu"), false, &Device::flex(), &Quiet, &never).unwrap();
    let on_gpu = train_on(&cfg, &codes, &dir.join("gpu"), false, &gpu, &Quiet, &never).unwrap();
    assert_eq!(on_cpu.len(), on_gpu.len());
    for (c, g) in on_cpu.iter().zip(&on_gpu) {
        assert!(
            (c.train_loss - g.train_loss).abs() <= 1e-3 * c.train_loss.abs(),
            "epoch {}: cpu {}, gpu {}",
            c.epoch,
            c.train_loss,
            g.train_loss
        );
    }
    let read = |run: &str| -> serde_json::Value {
        serde_json::from_str(&std::fs::read_to_string(dir.join(run).join(runs::CODES_FILE)).unwrap()).unwrap()
    };
    let (c, g) = (read("cpu"), read("gpu"));
    assert_eq!(c["bits"], g["bits"], "the projected codes differ");
    // the relaxed logits' score at the projection: the same up to rounding
    let score = |v: &serde_json::Value| v["provenance"]["projection"]["score"].as_f64().unwrap();
    assert!((score(&c) - score(&g)).abs() <= 1e-4 * score(&c).abs(), "projection score: cpu {}, gpu {}", score(&c), score(&g));
    std::fs::remove_dir_all(&dir).ok();
}
