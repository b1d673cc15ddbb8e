//! A delay-prior ADMM-Net trains to the same losses whether its layers run on the delay-tap
//! kernels or composed from roll + concatenate + 3×3 conv (the path before the kernels, and
//! the GPU's). Its own test binary: the path is a process-wide switch.

use std::sync::atomic::AtomicBool;
use tcsense_datasets::flim::FlimParams;
use tcsense_datasets::store::{generate, Generator, WriteOptions};
use tcsense_datasets::TimeGrid;
use tcsense_models::admm::Prior;
use tcsense_models::runs::ModelConfig;
use tcsense_models::AdmmNetConfig;
use tcsense_sensor::codes::{CodeShape, Constraints};
use tcsense_sensor::generate::random_codes;
use tcsense_sensor::Sampling;
use tcsense_train::{train, Loss, Quiet, TrainConfig};

#[test]
fn a_delay_prior_run_trains_the_same_on_either_path() {
    let dir = std::env::temp_dir().join(format!("tcsense-delay-path-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    // FLIm, 8×8, 16 bins (more than the largest dilation, 9)
    let gen = Generator::Flim(FlimParams { height: 8, width: 8, ..Default::default() });
    let grid = TimeGrid { length: 16, ..TimeGrid::default() };
    let cancel = AtomicBool::new(false);
    generate(&gen, &grid, 8, 3, &dir.join("ds"), &WriteOptions { shard_size: 8, force: false, progress: &|| {}, cancel: &cancel }).unwrap();
    let codes = random_codes(
        CodeShape { bh: 2, bw: 2, taps: 4, length: 16, drain: false },
        607e6,
        Constraints { tap: true, ..Default::default() },
        5,
    )
    .unwrap();
    let model = ModelConfig::AdmmNet(AdmmNetConfig::new(4, 16).with_stages(2).with_channels(3).with_prior(Prior::Delay));
    let mut cfg = TrainConfig::new(model, &dir.join("ds"), Loss::RmseMae, Sampling::Oversample(1));
    cfg.epochs = 3;
    cfg.learning_rate = 1e-2;

    let never = AtomicBool::new(false);
    let calls = tcsense_kernels::delay_op::kernel_calls;
    tcsense_kernels::delay_op::use_composed(true);
    let composed = train(&cfg, &codes, &dir.join("composed"), false, &Quiet, &never).unwrap();
    assert_eq!(calls(), 0, "the composed run never reaches the kernels");
    tcsense_kernels::delay_op::use_composed(false);
    let kernels = train(&cfg, &codes, &dir.join("kernels"), false, &Quiet, &never).unwrap();
    assert!(calls() > 0, "the kernels ran");
    eprintln!(
        "losses composed {:?}\n       kernels  {:?}",
        composed.iter().map(|m| m.train_loss).collect::<Vec<_>>(),
        kernels.iter().map(|m| m.train_loss).collect::<Vec<_>>()
    );

    assert_eq!(composed.len(), 3);
    assert!(kernels[2].train_loss < kernels[0].train_loss, "it trains: {} -> {}", kernels[0].train_loss, kernels[2].train_loss);
    for (c, k) in composed.iter().zip(&kernels) {
        let rel = (c.train_loss - k.train_loss).abs() / c.train_loss;
        assert!(rel < 1e-4, "epoch {}: loss {} composed, {} on the kernels ({rel})", c.epoch, c.train_loss, k.train_loss);
        let (pc, pk) = (c.get("val_psnr_db"), k.get("val_psnr_db"));
        assert!(pc.is_finite() && (pc - pk).abs() < 1e-2, "epoch {}: validation PSNR {pc} vs {pk} dB", c.epoch);
    }
    std::fs::remove_dir_all(&dir).ok();
}
