use burn::tensor::{Distribution, Tensor};
use std::time::Instant;
use tcsense_models::{AdmmNetConfig, Device, SensorTensors};
use tcsense_sensor::codes::{CodeShape, Constraints};
use tcsense_sensor::generate::random_codes;
use tcsense_sensor::{MeasurementMatrix, SensorParams};

fn time<F: FnMut()>(name: &str, mut f: F) {
    f();
    let n = 20;
    let t = Instant::now();
    for _ in 0..n { f(); }
    println!("{name:>14}: {:.2} ms", t.elapsed().as_secs_f64() * 1e3 / n as f64);
}

fn main() {
    let shape = CodeShape { bh: 2, bw: 2, taps: 4, length: 32, drain: false };
    let codes = random_codes(shape, 607e6, Constraints { tap: true, ..Default::default() }, 3).unwrap();
    let spec = SensorParams::from_codes(&codes).validate().unwrap();
    let a = MeasurementMatrix::synthesize(&codes, &spec).unwrap();
    for (ad, dev) in [(false, Device::flex()), (true, Device::flex().autodiff())] {
        println!("autodiff {ad}");
        let s = SensorTensors::new(&a, 64, 64, &dev).unwrap();
        let v = Tensor::<4>::random([2, 32, 64, 64], Distribution::Normal(0.0, 1.0), &dev);
        let y = Tensor::<4>::random([2, 4, 64, 64], Distribution::Normal(0.0, 1.0), &dev);
        let mut rho = Tensor::<1>::from_floats([0.1], &dev);
        if ad { rho = rho.require_grad(); }
        time("dc", || { let _ = s.data_consistency(v.clone(), rho.clone()); });
        if ad { time("dc+bwd", || { let _ = s.data_consistency(v.clone(), rho.clone()).sum().backward(); }); }
        time("pinv", || { let _ = s.pinv(y.clone()); });
        time("adjoint", || { let _ = s.adjoint(y.clone()); });
        time("relu+add", || { let _ = burn::tensor::activation::relu(v.clone()) + v.clone(); });
        let m = AdmmNetConfig::new(4, 32).with_stages(1).init(&dev);
        time("model fwd", || { let _ = m.forward(y.clone(), &s); });
    }
}
