//! The codes JSON reader: any text gives codes or an error; codes it accepts round-trip.
#![no_main]
use libfuzzer_sys::fuzz_target;
use tcsense_sensor::Codes;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else { return };
    if let Ok(codes) = Codes::from_json(text) {
        let again = Codes::from_json(&codes.to_json()).expect("written codes read back");
        assert_eq!(again.digest(), codes.digest());
        let _ = codes.violations();
    }
});
