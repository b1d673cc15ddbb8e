//! TVAL3 on compressed measurements (M = 4 taps, T = 32 bins: 8× compression).

use ndarray::Array3;
use std::sync::atomic::AtomicBool;
use tcsense_models::{tval3, Tval3Options};
use tcsense_sensor::codes::{CodeShape, Constraints};
use tcsense_sensor::generate::random_codes;
use tcsense_sensor::{MeasurementMatrix, SensorParams};

fn peak(x: &Array3<f32>, r: usize, c: usize) -> usize {
    (0..x.dim().0).max_by(|&a, &b| x[(a, r, c)].total_cmp(&x[(b, r, c)])).unwrap()
}

#[test]
fn compressed_scene_depth_within_one_bin() {
    let shape = CodeShape { bh: 2, bw: 2, taps: 4, length: 32, drain: false };
    let codes = random_codes(shape, 607e6, Constraints { tap: true, ..Default::default() }, 3).unwrap();
    let spec = SensorParams::from_codes(&codes).validate().unwrap();
    let a = MeasurementMatrix::synthesize(&codes, &spec).unwrap();
    let (h, w) = (16, 16);
    let plan = a.plan(h, w).unwrap();
    // two surfaces: a plane at bin 9.3 + a tilt, and a box at bin 20 on the right
    let mut x = Array3::<f32>::zeros((32, h, w));
    let mut truth = vec![0f64; h * w];
    for r in 0..h {
        for c in 0..w {
            let u = if c >= 10 && r >= 4 && r < 12 { 20.0 } else { 9.3 + 0.05 * r as f64 };
            truth[r * w + c] = u;
            let j0 = u.floor() as usize;
            let f = (u - j0 as f64) as f32;
            x[(j0, r, c)] += 1.0 - f;
            x[(j0 + 1, r, c)] += f;
        }
    }
    let y = plan.forward(&x.view()).unwrap();
    let opts = Tval3Options::default();
    let (xh, rep) = tval3(&a, &plan, &y.view(), &opts, &|_, _| {}, &AtomicBool::new(false)).unwrap();
    let mut worst = 0f64;
    let mut errs = Vec::new();
    for r in 0..h {
        for c in 0..w {
            let e = (peak(&xh, r, c) as f64 - truth[r * w + c]).abs();
            worst = worst.max(e);
            errs.push(e);
        }
    }
    let mse = (&xh - &x).mapv(|v| v * v).mean().unwrap();
    let bad = errs.iter().filter(|&&e| e > 1.0).count();
    eprintln!("worst {worst}, bad {bad}, mean {}, mse {mse}, {rep:?}", errs.iter().sum::<f64>() / errs.len() as f64);
    // all but edge pixels of the box (where spatial TV blends the two surfaces) are within a bin
    assert!(bad * 50 <= h * w, "{bad} of {} pixels off by more than one bin", h * w);
    assert!(errs.iter().sum::<f64>() / errs.len() as f64 <= 0.5);
    assert!(mse < 5e-3, "mse {mse}");
    assert!(xh.iter().all(|&v| v >= 0.0), "nonneg holds");
}
