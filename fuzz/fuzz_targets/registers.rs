//! The code-memory reader (`codes import`): any `registers.json` beside a valid image gives
//! codes that meet their declared constraints and export back to the same bytes, or an error.
#![no_main]
use libfuzzer_sys::fuzz_target;
use std::path::PathBuf;
use std::sync::OnceLock;
use tcsense_sensor::export::{export, import};

/// An export of the seed's codes (the fixture's: 4 taps, 2×2, L = 8), made once per process.
fn dir() -> &'static PathBuf {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let d = std::env::temp_dir().join(format!("tcsense-fuzz-registers-{}", std::process::id()));
        let codes = tcsense_sensor::Codes::load(&PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../tests/fixtures/admm-net-run-v1/codes.json"))).expect("fixture codes");
        export(&codes, &d).expect("export the fixture's codes");
        d
    })
}

fuzz_target!(|data: &[u8]| {
    let d = dir();
    std::fs::write(d.join("registers.json"), data).expect("write registers.json");
    if let Ok(codes) = import(d) {
        assert!(codes.violations().is_empty(), "import gave codes that break their constraints");
        let again = std::env::temp_dir().join(format!("tcsense-fuzz-registers-again-{}", std::process::id()));
        export(&codes, &again).expect("imported codes export");
        assert_eq!(import(&again).expect("re-import").digest(), codes.digest());
    }
});
