//! Adjointness `⟨A x, v⟩ = ⟨x, Aᵀ v⟩` for every operator variant, and the ideal forward model
//! against a direct sum of code bits. One line of the table per operator.

use ndarray::{Array, Array3, Array4};
use rand::rngs::StdRng;
use rand::{RngExt, SeedableRng};
use tcsense_sensor::codes::{CodeShape, Codes, Constraints};
use tcsense_sensor::generate::random_codes;
use tcsense_sensor::{Irf, MeasurementMatrix, Sampling, SensorParams};

struct Case {
    name: &'static str,
    block: (usize, usize),
    taps: usize,
    length: usize,
    drain: bool,
    sampling: Sampling,
    irf: Irf,
    measured: bool,
}

const PHYS: Irf = Irf::Physical { laser_fwhm_s: 2.55e-9, tap_tau_s: 0.3e-9 };

fn cases() -> Vec<Case> {
    let c = |name, block, taps, length, drain, sampling, irf, measured| Case { name, block, taps, length, drain, sampling, irf, measured };
    vec![
        c("ideal 2x2 M4 K1", (2, 2), 4, 16, false, Sampling::Oversample(1), Irf::Ideal, false),
        c("ideal 2x2 M4 oversample 4", (2, 2), 4, 16, false, Sampling::Oversample(4), Irf::Ideal, false),
        c("physical 2x2 M4 K1", (2, 2), 4, 16, false, Sampling::Oversample(1), PHYS, false),
        c("physical 2x2 M4 oversample 4", (2, 2), 4, 16, false, Sampling::Oversample(4), PHYS, false),
        c("ideal heterodyne 8", (2, 2), 4, 8, false, Sampling::Heterodyne(8), Irf::Ideal, false),
        c("physical heterodyne 8", (2, 2), 4, 8, false, Sampling::Heterodyne(8), PHYS, false),
        c("ideal 1x1 M1 drain", (1, 1), 1, 8, true, Sampling::Oversample(1), Irf::Ideal, false),
        c("ideal 4x4 M2", (4, 4), 2, 16, false, Sampling::Oversample(1), Irf::Ideal, false),
        c("ideal 1x3 M8 drain", (1, 3), 8, 24, true, Sampling::Oversample(2), Irf::Ideal, false),
        c("measured 2x2 M4 T32", (2, 2), 4, 8, false, Sampling::Oversample(4), Irf::Ideal, true),
    ]
}

fn build(case: &Case, seed: u64) -> (Codes, MeasurementMatrix) {
    let shape = CodeShape { bh: case.block.0, bw: case.block.1, taps: case.taps, length: case.length, drain: case.drain };
    let codes = random_codes(shape, 607e6, Constraints { tap: true, ..Default::default() }, seed).unwrap();
    let spec = SensorParams { sampling: case.sampling, irf: case.irf, ..SensorParams::from_codes(&codes) }.validate().unwrap();
    let a = if case.measured {
        let mut rng = StdRng::seed_from_u64(seed);
        let raw = Array3::from_shape_fn((spec.subpixels(), spec.taps(), spec.bins()), |_| rng.random::<f32>());
        MeasurementMatrix::from_array(raw, &spec).unwrap()
    } else {
        MeasurementMatrix::synthesize(&codes, &spec).unwrap()
    };
    (codes, a)
}

fn random<D: ndarray::Dimension>(shape: D, rng: &mut StdRng) -> Array<f32, D> {
    Array::from_shape_simple_fn(shape, || rng.random::<f32>() * 2.0 - 1.0)
}

fn dot(a: &[f32], b: &[f32]) -> f64 {
    a.iter().zip(b).map(|(x, y)| *x as f64 * *y as f64).sum()
}

#[test]
fn adjointness_for_every_operator() {
    for (i, case) in cases().iter().enumerate() {
        let (_, a) = build(case, 100 + i as u64);
        let (h, w) = (case.block.0 * 3, case.block.1 * 2 + case.block.1 * 3);
        let plan = a.plan(h, w).unwrap();
        let mut rng = StdRng::seed_from_u64(i as u64);
        let x = random(ndarray::Dim([plan.bins(), h, w]), &mut rng);
        let v = random(ndarray::Dim([plan.taps(), h, w]), &mut rng);
        let ax = plan.forward(&x.view()).unwrap();
        let atv = plan.adjoint(&v.view()).unwrap();
        let lhs = dot(ax.as_slice().unwrap(), v.as_slice().unwrap());
        let rhs = dot(x.as_slice().unwrap(), atv.as_slice().unwrap());
        let scale = lhs.abs().max(rhs.abs()).max(1.0);
        assert!((lhs - rhs).abs() / scale < 1e-5, "{}: <Ax,v> = {lhs}, <x,A'v> = {rhs}", case.name);

        // batched operators agree with the single-cube ones and are adjoint too
        let xb = random(ndarray::Dim([2, plan.bins(), h, w]), &mut rng);
        let vb = random(ndarray::Dim([2, plan.taps(), h, w]), &mut rng);
        let axb: Array4<f32> = plan.forward_batch(&xb.view()).unwrap();
        let atvb = plan.adjoint_batch(&vb.view()).unwrap();
        let lhs = dot(axb.as_slice().unwrap(), vb.as_slice().unwrap());
        let rhs = dot(xb.as_slice().unwrap(), atvb.as_slice().unwrap());
        assert!((lhs - rhs).abs() / lhs.abs().max(1.0) < 1e-5, "{} (batch)", case.name);
        let one = plan.forward(&xb.index_axis(ndarray::Axis(0), 1)).unwrap();
        assert_eq!(one, axb.index_axis(ndarray::Axis(0), 1));

        // AᵀA is symmetric positive semi-definite
        let nx = plan.normal(&x.view()).unwrap();
        assert!(dot(nx.as_slice().unwrap(), x.as_slice().unwrap()) >= -1e-6, "{}", case.name);
    }
}

#[test]
fn ideal_forward_is_a_direct_sum_of_code_bits() {
    let case = &cases()[1]; // oversample 4
    let (codes, a) = build(case, 7);
    let (h, w) = (4, 6);
    let plan = a.plan(h, w).unwrap();
    let mut rng = StdRng::seed_from_u64(1);
    let x = random(ndarray::Dim([plan.bins(), h, w]), &mut rng);
    let y = plan.forward(&x.view()).unwrap();
    let k = 4;
    for m in 0..4 {
        for r in 0..h {
            for c in 0..w {
                let n = (r % 2) * 2 + c % 2;
                let mut want = 0f64;
                for j in 0..plan.bins() {
                    if codes.get(n, m, j / k) {
                        want += x[(j, r, c)] as f64;
                    }
                }
                assert!((y[(m, r, c)] as f64 - want).abs() < 1e-4, "m{m} r{r} c{c}");
            }
        }
    }
}

#[test]
fn bad_frames_are_refused() {
    let (_, a) = build(&cases()[0], 1);
    let e = a.plan(5, 4).unwrap_err().to_string();
    assert!(e.contains("multiple of 2"), "{e}");
    let plan = a.plan(4, 4).unwrap();
    let e = plan.forward(&Array3::<f32>::zeros((8, 4, 4)).view()).unwrap_err().to_string();
    assert!(e.contains("[T, H, W] = [16, 4, 4]"), "{e}");
}
