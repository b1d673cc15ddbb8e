//! The sweep manifest reader: any text gives a checked manifest (known units, finite delays,
//! a valid recorded sensor) or an error.
#![no_main]
use libfuzzer_sys::fuzz_target;
use tcsense_sensor::sweep::SweepManifest;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else { return };
    if let Ok(m) = SweepManifest::parse(text, std::path::Path::new("sweep.json")) {
        assert!(tcsense_sensor::Units::parse(&m.units).is_ok());
        assert!(!m.delays_s.is_empty() && m.delays_s.iter().all(|d| d.is_finite()));
        assert!(m.full_scale.is_finite() && m.full_scale > 0.0);
        if let Some(s) = m.sensor {
            assert!(s.validate().is_ok());
        }
    }
});
