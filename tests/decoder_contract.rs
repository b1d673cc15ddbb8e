//! Every decoder through the one contract (`Decoder::decode(y [B, M, H, W], &Sensor)`) on the same
//! measurements, and a run directory written by an earlier build (tests/fixtures) opened
//! with one call and reconstructing exactly what that build reconstructed.

use ndarray::{Array4, Axis, Ix3, Ix4};
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use tcsense_datasets::lidar::LidarParams;
use tcsense_datasets::TimeGrid;
use tcsense_models::decoder::{Control, Decoder, Tval3Decoder};
use tcsense_models::metrics::mse;
use tcsense_models::{runs, tval3, Device, ModelError, Tval3Options};
use tcsense_sensor::measure::measure_batch;
use tcsense_sensor::npy::read_npy;
use tcsense_sensor::{Sensor, SensorError};

/// An ADMM-Net run (S = 2, CN = 4, 8×8 LiDAR, T = 8, 2 epochs) written before the decoder
/// contract existed, with noisy measurements `y.npy` [1, 4, 8, 8] and that build's
/// reconstruction `xhat.npy` [1, 8, 8, 8].
fn fixture() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/admm-net-run-v1")
}

fn decode(d: &mut dyn Decoder, y: &Array4<f32>, a: &Sensor) -> Array4<f32> {
    let never = AtomicBool::new(false);
    d.decode(y.view(), a, &Control::quiet(&never)).unwrap().cube.unwrap()
}

fn max_abs_diff(a: &Array4<f32>, b: &Array4<f32>) -> f32 {
    assert_eq!(a.dim(), b.dim());
    a.iter().zip(b.iter()).fold(0f32, |m, (x, y)| m.max((x - y).abs()))
}

#[test]
fn a_run_from_an_earlier_build_opens_and_reconstructs_the_same() {
    let run = runs::open(&fixture(), &Device::flex()).unwrap();
    assert_eq!(run.spec.model.name(), "admm-net", "configs without a decoder field are ADMM-Net runs");
    assert_eq!((run.sensor.taps(), run.sensor.bins(), run.sensor.block()), (4, 8, (2, 2)));
    let y = read_npy(&fixture().join("y.npy")).unwrap().into_dimensionality::<Ix4>().unwrap();
    let want = read_npy(&fixture().join("xhat.npy")).unwrap().into_dimensionality::<Ix4>().unwrap();
    let mut decoder = run.decoder;
    let got = decode(decoder.as_mut(), &y, &run.sensor);
    let scale = want.iter().fold(0f32, |m, v| m.max(v.abs()));
    assert!(scale > 0.1, "the stored reconstruction is not trivial");
    let diff = max_abs_diff(&got, &want);
    assert!(diff <= 1e-5 * scale, "reconstruction differs from the earlier build's by {diff} (scale {scale})");
}

#[test]
fn every_decoder_through_the_contract_on_the_same_measurements() {
    let run = runs::open(&fixture(), &Device::flex()).unwrap();
    let a = run.sensor.clone();
    // two LiDAR scenes on the run's grid (L = 8, K = 1), noise-free measurements [2, 4, 8, 8]
    let grid = TimeGrid { length: 8, ..TimeGrid::default() };
    let gen = LidarParams { height: 8, width: 8, ..Default::default() };
    let cubes: Vec<_> = (0..2).map(|i| gen.sample(&grid, 11, i).x).collect();
    let x = ndarray::stack(Axis(0), &[cubes[0].view(), cubes[1].view()]).unwrap(); // [2, T, H, W]
    let y = measure_batch(&a.plan(8, 8).unwrap(), &x.view(), None, 0).unwrap();
    assert_eq!(y.dim(), (2, 4, 8, 8));

    let opts = Tval3Options { maxit: 60, ..Default::default() };
    let mut decoders: Vec<Box<dyn Decoder>> = vec![Box::new(Tval3Decoder::new(opts).unwrap()), run.decoder];
    let zero_mse = mse(&vec![0.0; x.len()], x.as_slice().unwrap());
    for d in decoders.iter_mut() {
        let name = d.name().to_string();
        let batch = decode(d.as_mut(), &y, &a);
        assert_eq!(batch.dim(), (2, 8, 8, 8), "{name}: [B, T, H, W]");
        // a batch is its frames decoded one by one
        for i in 0..2 {
            let yi = y.slice_axis(Axis(0), ndarray::Slice::from(i..i + 1)).to_owned();
            let one = decode(d.as_mut(), &yi, &a);
            let diff = max_abs_diff(&one, &batch.slice_axis(Axis(0), ndarray::Slice::from(i..i + 1)).to_owned());
            assert!(diff <= 1e-6, "{name}: frame {i} alone differs from the batch by {diff}");
        }
        // both recover the scenes better than nothing (the 2-epoch toy ADMM-Net barely; its
        // values are pinned by the fixture test), and TVAL3 fits the measurements
        let e = mse(batch.as_slice().unwrap(), x.as_slice().unwrap());
        assert!(e < zero_mse, "{name}: MSE {e} vs {zero_mse} for an empty cube");
        if name == "tval3" {
            assert!(e < 0.5 * zero_mse, "{name}: MSE {e} vs {zero_mse} for an empty cube");
            let fit = measure_batch(&a.plan(8, 8).unwrap(), &batch.view(), None, 0).unwrap();
            let rel = (&fit - &y).mapv(|v| v * v).sum().sqrt() / y.mapv(|v| v * v).sum().sqrt();
            assert!(rel < 0.05, "{name}: ‖A x̂ − y‖/‖y‖ = {rel}");
        }

        // the same checks on bad input for every decoder
        let never = AtomicBool::new(false);
        let ctl = Control::quiet(&never);
        let taps3 = Array4::<f32>::zeros((1, 3, 8, 8));
        assert!(matches!(d.decode(taps3.view(), &a, &ctl), Err(ModelError::Sensor(SensorError::Shape { .. }))), "{name}: 3 taps");
        let odd = Array4::<f32>::zeros((1, 4, 7, 8));
        assert!(matches!(d.decode(odd.view(), &a, &ctl), Err(ModelError::Sensor(SensorError::Shape { .. }))), "{name}: 7 rows");
        let mut nan = y.clone();
        nan[(1, 2, 3, 4)] = f32::NAN;
        assert!(matches!(d.decode(nan.view(), &a, &ctl), Err(ModelError::Sensor(SensorError::NonFinite { .. }))), "{name}: NaN");
        let stop = AtomicBool::new(true);
        assert!(matches!(d.decode(y.view(), &a, &Control::quiet(&stop)), Err(ModelError::Cancelled)), "{name}: cancelled");
    }

    // the TVAL3 decoder is the solver itself, frame by frame
    let plan = a.plan(8, 8).unwrap();
    let never = AtomicBool::new(false);
    let (direct, _) = tval3(a.matrix(), &plan, &y.index_axis(Axis(0), 1), &opts, &|_, _| {}, &never).unwrap();
    let via = decode(decoders[0].as_mut(), &y, &a);
    assert_eq!(via.index_axis(Axis(0), 1).into_dimensionality::<Ix3>().unwrap(), direct);
}
