//! ONNX export and ONNX Runtime inference against burn: ADMM-Net and the U-Net, random and
//! trained weights, two frame sizes, the sensor matrix baked in and as an input, square and
//! non-square blocks, oversampled and heterodyne sensors. Needs ONNX Runtime in `.venv`
//! (`scripts/setup.sh`, which `scripts/test.sh` runs first).

mod common;

use common::burn_outputs;
use ndarray::{Array4, Ix4};
use rand::{RngExt, SeedableRng};
use std::path::{Path, PathBuf};
use tcsense_infer::onnx::{export, ExportOptions};
use tcsense_infer::runtime::OnnxModel;
use tcsense_infer::InferError;
use tcsense_models::runs::{self, LoadedRun, ModelConfig, RunSpec, TrainedNet};
use tcsense_models::{AdmmNetConfig, Device, LifetimeNetConfig, Prior, UnetConfig};
use tcsense_sensor::codes::{CodeShape, Constraints};
use tcsense_sensor::generate::random_codes;
use tcsense_sensor::npy::read_npy;
use tcsense_sensor::{Irf, Sampling};

fn fixture() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/admm-net-run-v1")
}

/// A run with fresh (random) weights: `block`, `L = 8`, 4 taps, under `sampling` and `irf`.
fn random_run(model: impl Fn(usize, usize) -> ModelConfig, block: (usize, usize), sampling: Sampling, irf: Irf, seed: u64) -> LoadedRun {
    random_run_of_length(model, block, 8, sampling, irf, seed)
}

/// [`random_run`] with `length` masks per cycle.
fn random_run_of_length(
    model: impl Fn(usize, usize) -> ModelConfig,
    block: (usize, usize),
    length: usize,
    sampling: Sampling,
    irf: Irf,
    seed: u64,
) -> LoadedRun {
    let shape = CodeShape { bh: block.0, bw: block.1, taps: 4, length, drain: false };
    let codes = random_codes(shape, 607e6, Constraints { tap: true, ..Default::default() }, seed).unwrap();
    let probe = RunSpec { model: model(4, 8), sampling, irf, measured: false };
    let bins = probe.sensor(Path::new("."), codes.clone()).unwrap().bins();
    let spec = RunSpec { model: model(4, bins), sampling, irf, measured: false };
    let sensor = spec.sensor(Path::new("."), codes).unwrap();
    let device = Device::flex();
    let net = match &spec.model {
        ModelConfig::AdmmNet(c) => TrainedNet::AdmmNet(c.init(&device)),
        ModelConfig::Unet(c) => TrainedNet::Unet(c.init(&device)),
        ModelConfig::Lifetime(c) => TrainedNet::Lifetime(c.init(&device)),
    };
    LoadedRun { dir: PathBuf::from("."), spec, sensor, net }
}

/// ONNX Runtime's outputs of `run` exported with `opts`, on `y`.
fn ort_outputs(run: &LoadedRun, opts: ExportOptions, y: &Array4<f32>, dir: &Path, name: &str) -> Vec<Array4<f32>> {
    ort_outputs_on(run, opts, y, dir, name, 2)
}

/// [`ort_outputs`] on `threads` intra-op threads.
fn ort_outputs_on(run: &LoadedRun, opts: ExportOptions, y: &Array4<f32>, dir: &Path, name: &str, threads: usize) -> Vec<Array4<f32>> {
    let path = dir.join(name);
    std::fs::write(&path, export(run, opts).unwrap()).unwrap();
    let mut model =
        OnnxModel::open(&path, threads).unwrap_or_else(|e| panic!("{e} (run scripts/setup.sh to install ONNX Runtime into .venv)"));
    model.run(y.view()).unwrap()
}

fn random_y(m: usize, h: usize, w: usize, seed: u64) -> Array4<f32> {
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    Array4::from_shape_fn((2, m, h, w), |_| rng.random_range(0.0..1000.0f32))
}

/// Max |a − b| over the scale of `b`.
fn rel_diff(a: &Array4<f32>, b: &Array4<f32>) -> f32 {
    assert_eq!(a.dim(), b.dim());
    let scale = b.iter().fold(0f32, |m, v| m.max(v.abs())).max(1e-12);
    a.iter().zip(b.iter()).fold(0f32, |m, (x, y)| m.max((x - y).abs())) / scale
}

#[test]
fn admm_net_in_onnx_runtime_equals_burn() {
    let dir = tempfile::tempdir().unwrap();
    let admm = |normalize: bool, prior: Prior| {
        move |m: usize, t: usize| {
            ModelConfig::AdmmNet(AdmmNetConfig::new(m, t).with_stages(3).with_channels(4).with_normalize(normalize).with_prior(prior))
        }
    };
    let physical = Irf::Physical { laser_fwhm_s: 2.55e-9, tap_tau_s: 0.3e-9 };
    let cases = [
        ("2x2 ideal", random_run(admm(true, Prior::Bins), (2, 2), Sampling::Oversample(1), Irf::Ideal, 1)),
        ("2x2 heterodyne physical", random_run(admm(false, Prior::Bins), (2, 2), Sampling::Heterodyne(2), physical, 2)),
        ("1x2 oversampled", random_run(admm(true, Prior::Bins), (1, 2), Sampling::Oversample(2), physical, 3)),
        // the delay prior (16 bins: its dilation 9 wraps around the cycle)
        ("2x2 oversampled, delay prior", random_run(admm(true, Prior::Delay), (2, 2), Sampling::Oversample(2), Irf::Ideal, 4)),
        ("1x2 heterodyne physical, delay prior", random_run(admm(false, Prior::Delay), (1, 2), Sampling::Heterodyne(2), physical, 5)),
    ];
    for (label, run) in &cases {
        ort_equals_burn(label, run, &[(8, 8), (6, 10)], 7, "admm.onnx", &["cube"]);
    }
    // trained weights: the fixture run reconstructs its stored xhat through ONNX Runtime
    let run = runs::load(&fixture(), &Device::flex()).unwrap();
    let y = read_npy(&fixture().join("y.npy")).unwrap().into_dimensionality::<Ix4>().unwrap();
    let xhat = read_npy(&fixture().join("xhat.npy")).unwrap().into_dimensionality::<Ix4>().unwrap();
    for matrix_input in [false, true] {
        let got = ort_outputs(&run, ExportOptions { matrix_input, ..Default::default() }, &y, dir.path(), "trained.onnx");
        let d = rel_diff(&got[0], &xhat);
        assert!(d <= 1e-4, "trained run, matrix input {matrix_input}: {d:e}");
    }
}

/// The FLIm prototype's sensor (L = 32, heterodyne K = 8: T = 256 bins, `λ` of `AAᵀ` up to
/// ~10⁴) with the delay prior and small `ρ` (trained FLIm networks learn them), on a FLIm-like
/// frame (decays of 0.5–5 ns at intensities over two decades, shot noise): burn and ONNX
/// Runtime on 1 and 2 threads agree to 1e-4 of the output's scale. With the x-update in the
/// Woodbury form they differed by up to 2 % (the cancellation `λ/ρ` times the result).
#[test]
fn flim_delay_prior_net_is_the_same_in_burn_and_onnx_runtime_on_any_thread_count() {
    let physical = Irf::Physical { laser_fwhm_s: 2.55e-9, tap_tau_s: 0.3e-9 };
    let net = |m: usize, t: usize| {
        ModelConfig::AdmmNet(
            AdmmNetConfig::new(m, t).with_stages(3).with_channels(2).with_normalize(true).with_prior(Prior::Delay).with_rho_init(0.02),
        )
    };
    let run = random_run_of_length(net, (2, 2), 32, Sampling::Heterodyne(8), physical, 8);
    let (t, h, w) = (run.sensor.bins(), 8, 8);
    assert_eq!(t, 256);
    let mut rng = rand::rngs::StdRng::seed_from_u64(3);
    let bin_ns = run.sensor.bin_width_s() * 1e9;
    let x = Array4::from_shape_fn((1, t, h, w), |(_, j, r, c)| {
        let (tau, amp) = (0.5 + 4.5 * ((r * w + c) as f64 / (h * w) as f64), 10f64.powf(2.0 * ((r + 3 * c) % 7) as f64 / 6.0));
        let dt = (j as f64 - 10.0) * bin_ns;
        if dt < 0.0 {
            0.0
        } else {
            (amp * (-dt / tau).exp()) as f32
        }
    });
    let plan = run.sensor.plan(h, w).unwrap();
    let mut y = plan.forward_batch(&x.view()).unwrap();
    y.mapv_inplace(|v| v + rng.random_range(-1.0f32..1.0) * v.max(0.0).sqrt());
    let want = burn_outputs(&run, &y);
    let dir = tempfile::tempdir().unwrap();
    let one = ort_outputs_on(&run, ExportOptions::default(), &y, dir.path(), "flim1.onnx", 1);
    let two = ort_outputs_on(&run, ExportOptions::default(), &y, dir.path(), "flim2.onnx", 2);
    let (d1, d2, d12) = (rel_diff(&one[0], &want[0]), rel_diff(&two[0], &want[0]), rel_diff(&one[0], &two[0]));
    assert!(d1 <= 1e-4 && d2 <= 1e-4 && d12 <= 1e-4, "burn vs ort on 1 thread {d1:e}, on 2 threads {d2:e}, 1 vs 2 threads {d12:e}");
}

/// Export `run` (sensor baked in and as an input), run it through ONNX Runtime on frames of
/// each size and assert every output named in `names` equals burn's to 1e-4; returns ONNX
/// Runtime's outputs for further checks.
fn ort_equals_burn(label: &str, run: &LoadedRun, sizes: &[(usize, usize)], seed: u64, file: &str, names: &[&str]) -> Vec<Vec<Array4<f32>>> {
    let dir = tempfile::tempdir().unwrap();
    let mut all = Vec::new();
    for &(h, w) in sizes {
        let y = random_y(4, h, w, seed);
        let want = burn_outputs(run, &y);
        for matrix_input in [false, true] {
            let got = ort_outputs(run, ExportOptions { matrix_input, ..Default::default() }, &y, dir.path(), file);
            for (k, name) in names.iter().enumerate() {
                let d = rel_diff(&got[k], &want[k]);
                assert!(
                    d <= 1e-4,
                    "{label}, {h}x{w}, matrix input {matrix_input}, {name}: ort differs from burn by {d:e} of the output scale"
                );
            }
            all.push(got);
        }
    }
    all
}

#[test]
fn unet_in_onnx_runtime_equals_burn() {
    let unet = |m: usize, t: usize| ModelConfig::Unet(UnetConfig::new(m, t, 12.0).with_base_width(4).with_levels(3).with_returns(2));
    let run = random_run(unet, (2, 2), Sampling::Oversample(1), Irf::Ideal, 4);
    for got in ort_equals_burn("unet", &run, &[(8, 8), (12, 16)], 9, "unet.onnx", &["depth", "confidence"]) {
        // depth in metres within the range, confidence a probability
        assert!(got[0].iter().all(|v| (0.0..=12.0).contains(v)) && got[1].iter().all(|v| (0.0..=1.0).contains(v)));
    }
    // the score-volume head: the soft-argmax in the graph, depth between the first and last bin centres
    let scores = |m: usize, t: usize| {
        ModelConfig::Unet(
            UnetConfig::new(m, t, 12.0).with_base_width(4).with_levels(3).with_returns(2).with_head(tcsense_models::UnetHead::ScoreVolume),
        )
    };
    let run = random_run(scores, (2, 2), Sampling::Oversample(2), Irf::Ideal, 5);
    for got in ort_equals_burn("unet score volume", &run, &[(8, 8), (12, 16)], 10, "unet-scores.onnx", &["depth", "confidence"]) {
        assert!(got[0].iter().all(|v| (0.37..=11.63).contains(v)) && got[1].iter().all(|v| (0.0..=1.0).contains(v)));
    }
    // the matched filters as input (baked, and formed in the graph from an input matrix), with
    // a physical IRF so that the templates are not the code bits
    let matched = |m: usize, t: usize| {
        ModelConfig::Unet(
            UnetConfig::new(m, t, 12.0)
                .with_base_width(4)
                .with_levels(3)
                .with_returns(2)
                .with_head(tcsense_models::UnetHead::ScoreVolume)
                .with_input(tcsense_models::UnetInput::Matched),
        )
    };
    let physical = Irf::Physical { laser_fwhm_s: 2.55e-9, tap_tau_s: 0.3e-9 };
    let run = random_run(matched, (2, 2), Sampling::Oversample(1), physical, 6);
    let outs = ort_equals_burn("unet matched", &run, &[(8, 8), (12, 16)], 11, "unet-matched.onnx", &["depth", "confidence"]);
    // another input, another network output on the same weights
    let backprojection = random_run(scores, (2, 2), Sampling::Oversample(1), physical, 6);
    let other = ort_equals_burn("unet backprojection", &backprojection, &[(8, 8)], 11, "unet-bp.onnx", &["depth", "confidence"]);
    assert!(rel_diff(&outs[0][0], &other[0][0]) > 1e-3, "the matched input changes the ranges");
}

#[test]
fn lifetime_decoder_in_onnx_runtime_equals_burn() {
    let net = |m: usize, t: usize| ModelConfig::Lifetime(LifetimeNetConfig::new(m, t).with_harmonics(6).with_base_width(4).with_levels(2));
    let run = random_run(net, (2, 2), Sampling::Heterodyne(4), Irf::Ideal, 6);
    for got in ort_equals_burn("lifetime", &run, &[(8, 8), (12, 16)], 10, "lifetime.onnx", &["lifetime", "confidence", "intensity"]) {
        assert!(got[0].iter().all(|v| v.is_finite()) && got[1].iter().all(|v| (0.0..=1.0).contains(v)));
    }
    // streamed deployment: lifetime, intensity and phasor products of the exported model
    use tcsense_infer::stream::{run_stream, FrameSource, ModelKind, Products};
    let dir = tempfile::tempdir().unwrap();
    let (onnx, stack, out) = (dir.path().join("l.onnx"), dir.path().join("y.npy"), dir.path().join("out"));
    std::fs::write(&onnx, export(&run, ExportOptions::default()).unwrap()).unwrap();
    let y = random_y(4, 8, 8, 11);
    tcsense_sensor::npy::write_npy(&stack, &y.view()).unwrap();
    let mut model = OnnxModel::open(&onnx, 1).unwrap();
    assert!(Products::parse("cube", ModelKind::Lifetime).is_err(), "a lifetime model has no cube");
    let products = Products::parse("lifetime,intensity,phasor", ModelKind::Lifetime).unwrap();
    let cancel = std::sync::atomic::AtomicBool::new(false);
    run_stream(&mut model, FrameSource::open(&stack).unwrap(), &out, &products, &cancel, &|_, _| {}).unwrap();
    let want = model.run(y.view()).unwrap();
    let tau = read_npy(&out.join("lifetime.npy")).unwrap();
    let intensity = read_npy(&out.join("intensity.npy")).unwrap();
    let phasor = read_npy(&out.join("phasor.npy")).unwrap();
    assert_eq!((tau.shape(), intensity.shape(), phasor.shape()), (&[2, 8, 8][..], &[2, 8, 8][..], &[2, 2, 8, 8][..]));
    for b in 0..2 {
        for i in 0..8 {
            for j in 0..8 {
                let conf = want[1][[b, 0, i, j]];
                let t = tau[[b, i, j]];
                assert!(if conf >= 0.5 { t == want[0][[b, 0, i, j]] } else { t.is_nan() }, "τ_m at {b},{i},{j}: {t} (confidence {conf})");
                assert_eq!(intensity[[b, i, j]], want[2][[b, 0, i, j]]);
                let (g, s) = (phasor[[b, 0, i, j]], phasor[[b, 1, i, j]]);
                // mixtures of exponentials fall inside the universal semicircle
                assert!(t.is_nan() || (g - 0.5).powi(2) + s * s <= 0.25 + 1e-5, "phasor ({g}, {s}) outside the semicircle");
            }
        }
    }
}

/// Every float parameter plus seeded Gaussian noise (a zero-initialised head made random).
struct Jitter(u64);

impl burn::module::ModuleMapper for Jitter {
    fn map_float<const D: usize>(
        &mut self,
        param: burn::module::Param<burn::tensor::Tensor<D>>,
    ) -> burn::module::Param<burn::tensor::Tensor<D>> {
        self.0 += 1;
        let device = Device::flex();
        device.seed(self.0);
        param.map(|t| {
            let noise = burn::tensor::Tensor::<D>::random(t.dims(), burn::tensor::Distribution::Normal(0.0, 0.3), &device);
            t + noise
        })
    }
}

/// The lifetime network on the fit's evidence (a randomised head), plain and with its
/// log-likelihood at a learned temperature (`--temper`): ONNX Runtime with the runtime's
/// evidence gives burn's lifetimes and confidences to 1e-4 of their scale.
#[test]
fn lifetime_decoder_on_the_fit_evidence_in_onnx_runtime_equals_burn() {
    for temper in [false, true] {
        lifetime_decoder_on_the_fit_evidence_equals_burn(temper);
    }
}

fn lifetime_decoder_on_the_fit_evidence_equals_burn(temper: bool) {
    use burn::module::Module;
    let net = |m: usize, t: usize| {
        ModelConfig::Lifetime(
            LifetimeNetConfig::new(m, t)
                .with_base_width(4)
                .with_levels(2)
                .with_points(24)
                .with_pool(3)
                .with_tau_range_ns([0.2, 12.0])
                .with_input(tcsense_models::LifetimeInput::Costs)
                .with_temper(temper),
        )
    };
    let physical = Irf::Physical { laser_fwhm_s: 2.55e-9, tap_tau_s: 0.3e-9 };
    let mut run = random_run(net, (2, 2), Sampling::Heterodyne(4), physical, 6);
    if let TrainedNet::Lifetime(n) = run.net {
        assert_eq!(n.tempered(), temper);
        run.net = TrainedNet::Lifetime(n.map(&mut Jitter(40)));
    }
    let dir = tempfile::tempdir().unwrap();
    for (h, w) in [(8, 8), (12, 16)] {
        let y = random_y(4, h, w, 12);
        let want = burn_outputs(&run, &y);
        let got = ort_outputs(&run, ExportOptions::default(), &y, dir.path(), "lifetime-evidence.onnx");
        assert_eq!(got.len(), 3, "lifetime, confidence and the intensity the runtime adds");
        for (k, name) in ["lifetime", "confidence", "intensity"].iter().enumerate() {
            let d = rel_diff(&got[k], &want[k]);
            assert!(d <= 1e-4, "{h}x{w}, {name}, tempered {temper}: ort differs from burn by {d:e} of the output scale");
        }
        // lifetimes on the grid's span, one component, a probability
        let span = (0.2e-9 * (1.0 - 1e-5))..=(12.0e-9 * (1.0 + 1e-5));
        let bad: Vec<f32> = got[0].slice(ndarray::s![.., ..3, .., ..]).iter().copied().filter(|v| !span.contains(&(*v as f64))).collect();
        assert!(bad.is_empty(), "lifetimes off the grid's span: {bad:?}");
        assert!(got[0].slice(ndarray::s![.., 3, .., ..]).iter().all(|&a| a == 1.0));
        assert!(got[1].iter().all(|v| (0.0..=1.0).contains(v)));
    }
    // the runtime computes the evidence from the sensor: no matrix input, no calibration
    let refused = export(&run, ExportOptions { matrix_input: true, ..Default::default() }).unwrap_err();
    assert!(refused.to_string().contains("--matrix-input"), "{refused}");
}

/// The U-Net on the range fit's evidence (a randomised head, so its log-prior and temperature
/// are not the fit's), its window alone and pooled by likeness over 9×9: ONNX Runtime with the
/// runtime's evidence and refinement gives burn's product — the same pixels with a return,
/// ranges and confidences to 1e-4 of their scale.
#[test]
fn unet_on_the_range_fit_evidence_in_onnx_runtime_equals_burn() {
    for pool_like in [0, 9] {
        unet_on_the_range_fit_evidence(pool_like);
    }
}

/// A small U-Net on the range fit's evidence over `range` m (2 candidates a bin, pooled by 3,
/// `pool_like`) with a randomised head, through random codes of 8 masks, physical IRF.
fn evidence_unet_run(range: f64, pool_like: usize) -> LoadedRun {
    use burn::module::Module;
    let net = move |m: usize, t: usize| {
        ModelConfig::Unet(
            UnetConfig::new(m, t, range)
                .with_base_width(4)
                .with_levels(2)
                .with_head(tcsense_models::UnetHead::ScoreVolume)
                .with_input(tcsense_models::UnetInput::Costs)
                .with_oversample(2)
                .with_pool(3)
                .with_pool_like(pool_like),
        )
    };
    let physical = Irf::Physical { laser_fwhm_s: 2.55e-9, tap_tau_s: 0.3e-9 };
    let mut run = random_run(net, (2, 2), Sampling::Oversample(1), physical, 8);
    if let TrainedNet::Unet(n) = run.net {
        run.net = TrainedNet::Unet(n.map(&mut Jitter(41)));
    }
    run
}

fn unet_on_the_range_fit_evidence(pool_like: usize) {
    let run = evidence_unet_run(12.0, pool_like);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("meta.onnx");
    std::fs::write(&path, export(&run, ExportOptions::default()).unwrap()).unwrap();
    let noted = OnnxModel::open(&path, 1).unwrap().meta.range_evidence.map(|e| e.pool_like);
    assert_eq!(noted, Some(pool_like), "the metadata records the pooling");
    for (h, w) in [(8, 8), (12, 16)] {
        let y = random_y(4, h, w, 13);
        let want = burn_outputs(&run, &y);
        let got = ort_outputs(&run, ExportOptions::default(), &y, dir.path(), "unet-evidence.onnx");
        assert_eq!(got.len(), 2, "depth and confidence");
        for (k, name) in ["depth", "confidence"].iter().enumerate() {
            assert_eq!(got[k].dim(), want[k].dim(), "{name}");
            let mismatch = got[k].iter().zip(want[k].iter()).filter(|(a, b)| a.is_finite() != b.is_finite()).count();
            assert_eq!(mismatch, 0, "{h}x{w}, {name}: NaN where burn has a value or the reverse");
            let finite = |a: &Array4<f32>| a.mapv(|v| if v.is_finite() { v } else { 0.0 });
            let d = rel_diff(&finite(&got[k]), &finite(&want[k]));
            assert!(d <= 1e-4, "{h}x{w}, {name}: ort differs from burn by {d:e} of the output scale");
        }
        let lit = got[0].slice(ndarray::s![.., 0, .., ..]).iter().filter(|v| v.is_finite()).count();
        assert!(lit > 0, "some first returns");
        assert!(got[0].iter().filter(|v| v.is_finite()).all(|v| (0.0..12.0).contains(v)), "ranges within the cycle");
    }
    let refused = export(&run, ExportOptions { matrix_input: true, ..Default::default() }).unwrap_err();
    assert!(refused.to_string().contains("--matrix-input"), "{refused}");
}

#[test]
fn measurements_that_break_the_metadata_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let unet = |m: usize, t: usize| ModelConfig::Unet(UnetConfig::new(m, t, 12.0).with_base_width(4).with_levels(3));
    let run = random_run(unet, (2, 2), Sampling::Oversample(1), Irf::Ideal, 5);
    let path = dir.path().join("u.onnx");
    std::fs::write(&path, export(&run, ExportOptions::default()).unwrap()).unwrap();
    let mut model = OnnxModel::open(&path, 1).unwrap();
    assert_eq!(model.meta.frame_multiple, (4, 4), "lcm of the 2x2 block and the stride 4");
    assert_eq!(&model.meta.codes, run.sensor.codes());
    for (y, needle) in [(random_y(3, 8, 8, 1), "M = 4 taps"), (random_y(4, 8, 6, 1), "multiples of 4x4")] {
        let e = model.run(y.view()).unwrap_err().to_string();
        assert!(e.contains(needle) && e.contains("u.onnx"), "{e}");
    }
    let mut y = random_y(4, 8, 8, 1);
    y[(0, 0, 0, 0)] = f32::NAN;
    assert!(model.run(y.view()).unwrap_err().to_string().contains("finite"));
    // a baked model takes no other sensor matrix
    assert!(model.set_matrix(run.sensor.matrix()).unwrap_err().to_string().contains("--matrix-input"));
    // a truncated file and a foreign one
    let bytes = std::fs::read(&path).unwrap();
    std::fs::write(dir.path().join("cut.onnx"), &bytes[..bytes.len() / 2]).unwrap();
    match OnnxModel::open(&dir.path().join("cut.onnx"), 1) {
        Err(InferError::File { path, msg }) => assert!(path.ends_with("cut.onnx") && msg.contains("ONNX"), "{msg}"),
        other => panic!("{other:?}"),
    }
    std::fs::write(dir.path().join("foreign.onnx"), b"not a model").unwrap();
    assert!(OnnxModel::open(&dir.path().join("foreign.onnx"), 1).is_err());
}

/// A U-Net on the range fit's evidence exported as one graph from the taps
/// (`export onnx --from-taps`): ONNX Runtime on the file alone gives the posterior's mode and
/// the first return's confidence that the split graph gives on the evidence `tcsense infer`
/// computes, with and without the pooling by likeness, on two frame sizes of noisy slopes.
#[test]
fn unet_on_the_range_fit_evidence_from_the_taps_equals_the_split_graph() {
    use tcsense_fits::evidence::EvidenceBuffers;
    for pool_like in [0, 9] {
        // (the network's range the sensor's cycle, as in every trained run)
        let probe = evidence_unet_run(12.0, pool_like);
        let cycle = tcsense_sensor::C * probe.sensor.matrix().bin_width_s() / 2.0 * probe.sensor.matrix().bins() as f64;
        let run = evidence_unet_run(cycle, pool_like);
        let dir = tempfile::tempdir().unwrap();
        let (split, whole) = (dir.path().join("split.onnx"), dir.path().join("whole.onnx"));
        std::fs::write(&split, export(&run, ExportOptions::default()).unwrap()).unwrap();
        std::fs::write(&whole, export(&run, ExportOptions { from_taps: true, ..Default::default() }).unwrap()).unwrap();
        let mut split = OnnxModel::open(&split, 1).unwrap();
        let mut whole = OnnxModel::open(&whole, 1).unwrap();
        assert_eq!((whole.meta.range_evidence, whole.meta.returns), (None, 1), "a plain depth model of one return");
        let a = run.sensor.matrix().a().to_owned();
        let (_, m, t) = a.dim();
        for (h, w, amplitude) in [(8, 12, 20000.0), (16, 16, 300.0), (16, 16, 20000.0), (16, 16, 6.0)] {
            // a slope across the frame on an ambient floor, Poisson-like noise, one dark pixel
            let mut rng = rand::rngs::StdRng::seed_from_u64(3 + h as u64);
            let mut y = Array4::<f32>::zeros((1, m, h, w));
            for i in 0..h {
                for j in 0..w {
                    let n = (i % 2) * 2 + j % 2;
                    let tau = 1.0 + (t as f64 - 2.0) * j as f64 / w as f64 + 0.2 * i as f64;
                    let (t0, f) = ((tau - 0.5).floor() as usize % t, (tau - 0.5).fract());
                    for k in 0..m {
                        let g = (1.0 - f) * a[(n, k, t0)] as f64 + f * a[(n, k, (t0 + 1) % t)] as f64;
                        let s: f64 = (0..t).map(|b| a[(n, k, b)] as f64).sum();
                        let mean = amplitude * g + 2.0 * s;
                        y[(0, k, i, j)] = (mean + mean.sqrt() * rng.random_range(-1.7..1.7)).max(0.0) as f32;
                    }
                }
            }
            y.slice_mut(ndarray::s![0, .., 1, 2]).fill(0.0);
            let got = whole.run(y.view()).unwrap();
            // any scale of the taps gives the same products (times a power of two: to the bit)
            for k in [-70, 60] {
                let scaled = whole.run(y.mapv(|v| v * 2f32.powi(k)).view()).unwrap();
                for (a, b) in scaled.iter().zip(&got) {
                    assert!(a.iter().zip(b.iter()).all(|(p, q)| p.to_bits() == q.to_bits()), "{h}x{w}: the taps times 2^{k}");
                }
            }
            let (stage, _) = split.evidence_stages().unwrap();
            let ev = stage.evidence(&y.index_axis(ndarray::Axis(0), 0), EvidenceBuffers::default());
            let want = split.run_graph_on_evidence(&ev).unwrap(); // mode_range, first_confidence
            let product = split.run(y.view()).unwrap(); // the mode refined in the tap domain
            let (depth, conf) = (&got[0], &got[1]);
            assert!(depth[(0, 0, 1, 2)].is_nan() && conf[(0, 0, 1, 2)] == 0.0, "the dark pixel has no return");
            let (cycle, bin) = (cycle as f32, cycle as f32 / t as f32);
            let cyclic = |a: f32, b: f32| (a - b).abs().min(cycle - (a - b).abs());
            let (mut returns, mut at_mode) = (0, 0);
            let (mut diffs, mut mdiffs, mut errors) = (Vec::new(), Vec::new(), Vec::new());
            for i in 0..h {
                for j in 0..w {
                    if (i, j) == (1, 2) {
                        continue;
                    }
                    let (c_got, c_want) = (conf[(0, 0, i, j)], want[1][(0, 0, i, j)]);
                    assert!((c_got - c_want).abs() <= 1e-3, "{h}x{w} ({i}, {j}): confidence {c_got} against {c_want}");
                    let d = depth[(0, 0, i, j)];
                    assert_eq!(d.is_nan(), c_want < 0.5, "{h}x{w} ({i}, {j}): a return exactly where confident");
                    if c_want < 0.5 {
                        continue;
                    }
                    let (mode, refined) = (want[0][(0, 0, i, j)], product[0][(0, 0, i, j)]);
                    returns += 1;
                    let truth = (1.0 + (t as f64 - 2.0) * j as f64 / w as f64 + 0.2 * i as f64) as f32 * bin;
                    errors.push((cyclic(d, truth) / bin, cyclic(refined, truth) / bin));
                    diffs.push(cyclic(d, refined) / bin);
                    mdiffs.push(cyclic(mode, refined) / bin);
                    at_mode += usize::from(cyclic(d, mode) <= 1e-3);
                }
            }
            assert!(returns > (h * w) / 2, "{h}x{w} at {amplitude}: returns on most pixels ({returns})");
            let median = |mut v: Vec<f32>| {
                v.sort_by(f32::total_cmp);
                v[v.len() / 2]
            };
            let (eg, ep): (Vec<f32>, Vec<f32>) = errors.into_iter().unzip();
            let (to_product, mode_to_product, err_graph, err_product) = (median(diffs), median(mdiffs), median(eg), median(ep));
            let what = format!(
                "{h}x{w} at {amplitude}, pool_like {pool_like}: {returns} returns, {at_mode} at the mode; median bins: graph to tcsense's {to_product:.3} (the mode's {mode_to_product:.3}), error {err_graph:.3} against tcsense's {err_product:.3}"
            );
            assert!(returns > (h * w) / 2, "returns on most pixels: {what}");
            assert!(err_graph <= 1.1 * err_product, "as accurate as tcsense infer's ranges: {what}");
            if amplitude > 100.0 {
                // bright: refined in the graph as in the tap domain, far closer than the mode
                assert!(to_product <= 0.06 && 3.0 * to_product < mode_to_product && at_mode < returns / 4, "refined: {what}");
            } else {
                // dim: the windows do not pin the range, and the mode stands on most pixels
                assert!(2 * at_mode >= returns, "the mode stands: {what}");
            }
        }
    }
    // only for a U-Net on the range fit's evidence, with its sensor baked in
    let plain = random_run(
        |m, t| ModelConfig::Unet(UnetConfig::new(m, t, 12.0).with_base_width(4).with_levels(2)),
        (2, 2),
        Sampling::Oversample(1),
        Irf::Ideal,
        9,
    );
    let refused = export(&plain, ExportOptions { from_taps: true, ..Default::default() }).unwrap_err();
    assert!(refused.to_string().contains("--from-taps"), "{refused}");
}
