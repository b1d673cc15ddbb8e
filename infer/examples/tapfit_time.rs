use std::time::Instant;
use tcsense_infer::tapfit::*;
use tcsense_sensor::{Codes, Irf, Sampling, SensorParams, MeasurementMatrix};
fn main() {
    let args: Vec<String> = std::env::args().collect();
    let codes = Codes::load(std::path::Path::new(&args[1])).unwrap();
    let p = SensorParams { sampling: Sampling::Heterodyne(8), irf: Irf::Physical { laser_fwhm_s: 2.55e-9, tap_tau_s: 0.3e-9 }, ..SensorParams::from_codes(&codes) };
    let a = MeasurementMatrix::synthesize(&codes, &p.validate().unwrap()).unwrap();
    let y = tcsense_sensor::npy::read_npy(std::path::Path::new(&args[2])).unwrap(); let y = if y.ndim() == 4 { y.index_axis(ndarray::Axis(0), 0).to_owned() } else { y }; let y = y.into_dimensionality::<ndarray::Ix3>().unwrap();
    let opts = TapFitOptions::default();
    for _ in 0..(std::env::var("N").map(|v| v.parse().unwrap()).unwrap_or(3)) {
        let t = Instant::now();
        let inst = if std::env::var("ONSET").is_ok() { Instrument { onset_s: 2e-9, irf_fwhm_s: 0.0 } } else { estimate_instrument(&y.view(), &a, &opts) };
        let t1 = t.elapsed().as_secs_f64();
        let t = Instant::now();
        let inst2 = estimate_instrument(&y.view(), &a, &TapFitOptions { onset_s: Some(inst.onset_s), ..opts.clone() });
        let t2 = t.elapsed().as_secs_f64();
        let t = Instant::now();
        let tpl = LifetimeTemplates::new(&a, inst, &opts);
        let t3 = t.elapsed().as_secs_f64();
        let t = Instant::now();
        let fit = tpl.fit(&y.view());
        let t4 = t.elapsed().as_secs_f64();
        let n = fit.lifetime.iter().filter(|v| v.is_finite()).count();
        println!("instrument {:.1} ms ({:?}), widths only {:.1} ms ({:?}), templates {:.1} ms, fit {:.1} ms, {n} px", t1*1e3, inst, t2*1e3, inst2.irf_fwhm_s, t3*1e3, t4*1e3);
    }
}
