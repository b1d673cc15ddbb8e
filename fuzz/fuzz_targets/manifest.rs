//! The dataset manifest reader: any text gives a checked manifest or an error.
#![no_main]
use libfuzzer_sys::fuzz_target;
use tcsense_datasets::store::Manifest;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else { return };
    if let Ok(m) = Manifest::parse(text) {
        assert_eq!(m.grid.bins(), m.bins);
    }
});
