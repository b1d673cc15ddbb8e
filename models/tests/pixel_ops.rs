//! The fused per-pixel operators against the same algebra composed from burn ops in block
//! layout: values of `A`, `Aᵀ`, the back-projection and the data-consistency step, and the
//! gradients of the data-consistency step with respect to `v` and `ρ` through autodiff.

use burn::tensor::{Distribution, Tensor};
use tcsense_models::{Device, SensorTensors};
use tcsense_sensor::codes::{CodeShape, Constraints};
use tcsense_sensor::generate::random_codes;
use tcsense_sensor::{Irf, MeasurementMatrix, SensorParams};

fn rel_err<const D: usize>(a: Tensor<D>, b: Tensor<D>) -> f32 {
    let s = b.clone().abs().max().into_scalar::<f32>().max(1e-6);
    (a - b).abs().max().into_scalar::<f32>() / s
}

fn sensor(bh: usize, bw: usize, taps: usize, bins: usize, h: usize, w: usize, device: &Device) -> SensorTensors {
    let shape = CodeShape { bh, bw, taps, length: bins, drain: false };
    let codes = random_codes(shape, 607e6, Constraints { tap: true, ..Default::default() }, 11).unwrap();
    let spec = SensorParams { irf: Irf::Physical { laser_fwhm_s: 2.55e-9, tap_tau_s: 0.3e-9 }, ..SensorParams::from_codes(&codes) }
        .validate()
        .unwrap();
    let a = MeasurementMatrix::synthesize(&codes, &spec).unwrap();
    SensorTensors::new(&a, h, w, device).unwrap()
}

#[test]
fn fused_operators_equal_the_composed_ones() {
    // blocks 2×2 and 1×3 (non-square), frames of one block row and of several bands
    for &(bh, bw, m, t, h, w) in &[(2, 2, 4, 16, 8, 8), (1, 3, 3, 8, 5, 9), (2, 2, 4, 32, 130, 64)] {
        let device = Device::flex();
        let s = sensor(bh, bw, m, t, h, w, &device);
        let x = Tensor::<4>::random([2, t, h, w], Distribution::Uniform(0.0, 1.0), &device);
        let y = Tensor::<4>::random([2, m, h, w], Distribution::Uniform(0.0, 1.0), &device);
        let case = (bh, bw, m, t, h, w);

        let e = rel_err(s.forward(x.clone()), s.from_blocks(s.a.clone().matmul(s.to_blocks(x.clone()))));
        assert!(e < 1e-5, "{case:?}: A x differs by {e}");
        let e = rel_err(s.adjoint(y.clone()), s.from_blocks(s.at.clone().matmul(s.to_blocks(y.clone()))));
        assert!(e < 1e-5, "{case:?}: Aᵀ y differs by {e}");
        let e = rel_err(s.pinv(y.clone()), s.pinv_blocks(y.clone()));
        assert!(e < 1e-4, "{case:?}: back-projection differs by {e}");
        for rho in [0.05f32, 1.0, 7.0] {
            let r = Tensor::<1>::from_floats([rho], &device);
            let fused = s.data_consistency(x.clone(), r.clone());
            let composed = s.from_blocks(s.data_consistency_blocks(s.to_blocks(x.clone()), r));
            let e = rel_err(fused, composed);
            assert!(e < 1e-4, "{case:?}: DC at ρ = {rho} differs by {e}");
        }
    }
}

#[test]
fn fused_data_consistency_has_the_composed_gradients() {
    let device = Device::flex().autodiff();
    let (t, h, w) = (16, 8, 8);
    let s = sensor(2, 2, 4, t, h, w, &device);
    let v0 = Tensor::<4>::random([2, t, h, w], Distribution::Uniform(-1.0, 1.0), &device);
    let wts = Tensor::<4>::random([2, t, h, w], Distribution::Normal(0.0, 1.0), &device);
    let grads_of = |fused: bool| {
        let v = v0.clone().require_grad();
        let log_rho = Tensor::<1>::from_floats([0.3f32.ln()], &device).require_grad();
        let rho = log_rho.clone().exp();
        let x =
            if fused { s.data_consistency(v.clone(), rho) } else { s.from_blocks(s.data_consistency_blocks(s.to_blocks(v.clone()), rho)) };
        let g = (x * wts.clone()).sum().backward();
        (v.grad(&g).unwrap(), log_rho.grad(&g).unwrap())
    };
    let (dv_f, drho_f) = grads_of(true);
    let (dv_c, drho_c) = grads_of(false);
    let e = rel_err(dv_f, dv_c);
    assert!(e < 1e-4, "∂L/∂v differs by {e}");
    let (a, b) = (drho_f.into_scalar::<f32>(), drho_c.into_scalar::<f32>());
    assert!(b.abs() > 1e-3, "the test needs a non-trivial ∂L/∂log ρ, got {b}");
    assert!((a - b).abs() <= 1e-3 * b.abs(), "∂L/∂log ρ: fused {a} vs composed {b}");
}
