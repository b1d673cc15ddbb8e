//! The `.npy` reader: any bytes give an array or an error, never a panic or a huge allocation.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(a) = tcsense_sensor::npy::parse_npy(data) {
        // what it read is what the header declared
        let h = tcsense_sensor::npy::parse_header(data).expect("a parsed file has a header");
        assert_eq!(a.shape(), h.shape.as_slice());
    }
});
