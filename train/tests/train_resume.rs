//! The training loop on a tiny LiDAR problem (8×8, T = 8): the loss falls, the run directory
//! holds what the contract says, the trained run opens as a decoder without this crate's
//! help, and 2 epochs straight equal 1 epoch + a resume for 1 more.

use ndarray::Array4;
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use tcsense_datasets::lidar::LidarParams;
use tcsense_datasets::store::{generate, Generator, WriteOptions};
use tcsense_datasets::TimeGrid;
use tcsense_models::decoder::Control;
use tcsense_models::runs::{self, ModelConfig};
use tcsense_models::{AdmmNetConfig, Device};
use tcsense_sensor::codes::{CodeShape, Constraints};
use tcsense_sensor::generate::random_codes;
use tcsense_sensor::{Codes, Sampling};
use tcsense_train::fit::run_state;
use tcsense_train::{train, Loss, Quiet, TrainConfig, TrainError};

fn tmp() -> PathBuf {
    let d = std::env::temp_dir().join(format!(
        "tcsense-train-{}-{}",
        std::process::id(),
        std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_nanos()
    ));
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn setup(dir: &Path) -> (TrainConfig, Codes) {
    let gen = Generator::Lidar(LidarParams { height: 8, width: 8, ..Default::default() });
    let grid = TimeGrid { length: 8, ..TimeGrid::default() };
    let cancel = AtomicBool::new(false);
    generate(&gen, &grid, 8, 1, &dir.join("ds"), &WriteOptions { shard_size: 8, force: false, progress: &|| {}, cancel: &cancel }).unwrap();
    let codes = random_codes(
        CodeShape { bh: 2, bw: 2, taps: 4, length: 8, drain: false },
        607e6,
        Constraints { tap: true, ..Default::default() },
        2,
    )
    .unwrap();
    let model = ModelConfig::AdmmNet(AdmmNetConfig::new(4, 8).with_stages(2).with_channels(4));
    let mut cfg = TrainConfig::new(model, &dir.join("ds"), Loss::RmseMae, Sampling::Oversample(1));
    cfg.epochs = 2;
    cfg.learning_rate = 1e-2;
    (cfg, codes)
}

/// The reconstruction of `y` by the run's latest weights, opened through `runs::open`.
fn weights_output(run: &Path, y: &Array4<f32>) -> Vec<f32> {
    let mut r = runs::open(run, &Device::flex()).unwrap();
    let never = AtomicBool::new(false);
    let out = r.decoder.decode(y.view(), &r.sensor, &Control::quiet(&never)).unwrap();
    out.cube.unwrap().iter().copied().collect()
}

#[test]
fn training_reduces_loss_saves_and_resumes() {
    let dir = tmp();
    let (cfg, codes) = setup(&dir);
    let never = AtomicBool::new(false);
    let mut long = cfg.clone();
    long.epochs = 6;
    let m = train(&long, &codes, &dir.join("run"), false, &Quiet, &never).unwrap();
    assert_eq!(m.len(), 6);
    assert!(m[5].train_loss < m[0].train_loss, "loss {} -> {}", m[0].train_loss, m[5].train_loss);
    let csv = std::fs::read_to_string(dir.join("run/metrics.csv")).unwrap();
    assert_eq!(csv.lines().count(), 7);
    let saved: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(dir.join("run/config.json")).unwrap()).unwrap();
    assert_eq!(
        (saved["decoder"].as_str(), saved["model"]["stages"].as_u64(), saved["epochs"].as_u64()),
        (Some("admm-net"), Some(2), Some(6))
    );
    assert_eq!(TrainConfig::load(&dir.join("run/config.json")).unwrap(), long, "config.json reads back as written");

    // save -> load gives identical outputs
    let y = Array4::from_shape_fn((1, 4, 8, 8), |(_, m, r, c)| ((m + r * 3 + c) % 5) as f32 * 0.2);
    let a1 = weights_output(&dir.join("run"), &y);
    let a2 = weights_output(&dir.join("run"), &y);
    assert_eq!(a1, a2);

    // 2 epochs straight == 1 epoch + resume for 1 more
    train(&cfg, &codes, &dir.join("straight"), false, &Quiet, &never).unwrap();
    let mut one = cfg.clone();
    one.epochs = 1;
    train(&one, &codes, &dir.join("resumed"), false, &Quiet, &never).unwrap();
    let state = run_state(&dir.join("resumed")).unwrap();
    assert_eq!((state.epoch, state.step), (1, 3));
    let more = train(&cfg, &codes, &dir.join("resumed"), true, &Quiet, &never).unwrap();
    assert_eq!(more.len(), 1);
    assert_eq!((more[0].epoch, more[0].step), (2, 6), "continues from the saved step");
    let s = weights_output(&dir.join("straight"), &y);
    let r = weights_output(&dir.join("resumed"), &y);
    let diff = s.iter().zip(&r).fold(0f32, |m, (a, b)| m.max((a - b).abs()));
    assert!(diff < 1e-4, "resumed run differs from the straight run by {diff}");
    // a fresh run refuses to overwrite
    assert!(train(&cfg, &codes, &dir.join("straight"), false, &Quiet, &never).is_err());
    // a cancelled run stops before its first step
    let stop = AtomicBool::new(true);
    assert!(matches!(train(&cfg, &codes, &dir.join("stopped"), false, &Quiet, &stop), Err(TrainError::Cancelled)));
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn augmented_runs_crop_resume_exactly_and_shift_like_a_delayed_scene() {
    use tcsense_datasets::flim::{FlimKnobs, FlimParams};
    use tcsense_train::Augmentation;
    let dir = tmp();
    let (mut cfg, codes) = setup(&dir);
    cfg.augment = Some(Augmentation { crop: Some([4, 6]), ..Augmentation::default() });
    let never = AtomicBool::new(false);
    let straight = train(&cfg, &codes, &dir.join("straight"), false, &Quiet, &never).unwrap();
    let mut one = cfg.clone();
    one.epochs = 1;
    let first = train(&one, &codes, &dir.join("resumed"), false, &Quiet, &never).unwrap();
    let more = train(&cfg, &codes, &dir.join("resumed"), true, &Quiet, &never).unwrap();
    assert_eq!((first[0].train_loss, first[0].get("val_mse")), (straight[0].train_loss, straight[0].get("val_mse")));
    assert!(
        (more[0].train_loss - straight[1].train_loss).abs() < 1e-6 * straight[1].train_loss.abs().max(1e-9),
        "{} vs {}",
        more[0].train_loss,
        straight[1].train_loss
    );
    // validation runs on whole 8×8 frames
    let y = Array4::from_shape_fn((1, 4, 8, 8), |(_, m, r, c)| ((m + r * 3 + c) % 5) as f32 * 0.2);
    assert_eq!(weights_output(&dir.join("resumed"), &y).len(), 8 * 8 * 8);
    let mut bad = cfg.clone();
    bad.augment = Some(Augmentation { crop: Some([3, 4]), ..Augmentation::default() });
    let err = train(&bad, &codes, &dir.join("bad"), false, &Quiet, &never).unwrap_err().to_string();
    assert!(err.contains("augment.crop") && err.contains("3x4"), "{err}");

    // the time-shift augmentation of a FLIm cube is the scene regenerated with its onset
    // delayed by the same number of bins
    let grid = TimeGrid { sampling: Sampling::Heterodyne(8), ..TimeGrid::default() };
    let p = FlimParams { height: 8, width: 8, ..FlimParams::paper() };
    let (ch, tau) = p.channels(3, 0);
    let knobs = FlimKnobs { tau, onset_s: 1e-9, irf_fwhm_s: 0.0, background: 0.0, brightness: 1.0 };
    let x = tcsense_datasets::flim::render(&ch, &knobs, &grid).x.insert_axis(ndarray::Axis(0)); // [1, T, H, W]
    let shift_only = Augmentation { time_shift: true, flips: false, crop: None, brightness: [1.0, 1.0], ..Augmentation::default() };
    let noise = tcsense_sensor::NoiseParams::default();
    for step in 1..4 {
        let shifted = shift_only.apply(&x.view(), None, None, &noise, (2, 2), 11, step).x;
        let t = grid.bins();
        let k = (0..t).find(|&k| (0..t).all(|j| shifted[(0, (j + k) % t, 0, 0)] == x[(0, j, 0, 0)])).expect("a roll");
        let delayed = tcsense_datasets::flim::render(
            &ch,
            &FlimKnobs { onset_s: (1e-9 + k as f64 * grid.bin_width_s()) % grid.cycle_s(), ..knobs },
            &grid,
        )
        .x;
        let peak = x.iter().fold(0f32, |m, &v| m.max(v));
        let diff = shifted.index_axis(ndarray::Axis(0), 0).iter().zip(delayed.iter()).fold(0f32, |m, (a, b)| m.max((a - b).abs()));
        assert!(diff < 1e-5 * peak, "shift {k}: differs from the regenerated scene by {diff}");
    }
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn unet_trains_on_depth_resumes_and_opens_as_a_depth_decoder() {
    use tcsense_models::UnetConfig;
    let dir = tmp();
    let (mut cfg, codes) = setup(&dir);
    let range_m = tcsense_datasets::grid::C * 8.0 / 607e6 / 2.0;
    cfg.run.model = ModelConfig::Unet(UnetConfig::new(4, 8, range_m).with_base_width(4).with_levels(2));
    cfg.epochs = 8;
    cfg.learning_rate = 3e-3;
    let never = AtomicBool::new(false);
    let m = train(&cfg, &codes, &dir.join("unet"), false, &Quiet, &never).unwrap();
    assert!(m[7].train_loss < m[0].train_loss, "loss {} -> {}", m[0].train_loss, m[7].train_loss);
    let csv = std::fs::read_to_string(dir.join("unet/metrics.csv")).unwrap();
    assert!(csv.starts_with("epoch,step,train_loss,val_depth_rmse_m,val_depth_mae_m,val_detection\n"), "{csv}");
    let det = m[7].get("val_detection");
    assert!((0.0..=1.0).contains(&det) && (det == 0.0 || m[7].get("val_depth_rmse_m").is_finite()), "{:?}", m[7]);
    // resume continues exactly (augmentation on, with depth labels moved along)
    let mut aug = cfg.clone();
    aug.epochs = 2;
    aug.augment = Some(tcsense_train::Augmentation::default());
    let straight = train(&aug, &codes, &dir.join("a-straight"), false, &Quiet, &never).unwrap();
    let mut one = aug.clone();
    one.epochs = 1;
    train(&one, &codes, &dir.join("a-resumed"), false, &Quiet, &never).unwrap();
    let more = train(&aug, &codes, &dir.join("a-resumed"), true, &Quiet, &never).unwrap();
    assert_eq!(more[0].train_loss, straight[1].train_loss);
    // the run opens as a decoder of depth [B, K, H, W] with a confidence per return
    let mut r = runs::open(&dir.join("unet"), &Device::flex()).unwrap();
    assert_eq!(r.spec.model.name(), "unet");
    let y = Array4::from_shape_fn((1, 4, 8, 8), |(_, m, r, c)| ((m + r * 3 + c) % 5) as f32 * 0.2);
    let out = r.decoder.decode(y.view(), &r.sensor, &Control::quiet(&never)).unwrap();
    assert!(out.cube.is_none());
    let (d, c) = (out.depth.unwrap(), out.confidence.unwrap());
    assert_eq!((d.dim(), c.dim()), ((1, 2, 8, 8), (1, 2, 8, 8)));
    assert!(d
        .iter()
        .zip(c.iter())
        .all(|(&d, &c)| (0.0..=1.0).contains(&c) && (d.is_nan() == (c < 0.5)) && (d.is_nan() || (0.0..=range_m as f32).contains(&d))));
    std::fs::remove_dir_all(&dir).ok();
}
