//! The run config reader (`config.json` of a training run, upgraded from older builds): any
//! text gives a checked spec or an error; a checked spec builds its network's config.
#![no_main]
use libfuzzer_sys::fuzz_target;
use tcsense_models::runs::{upgrade_config, RunSpec};

fuzz_target!(|data: &[u8]| {
    let Ok(v) = serde_json::from_slice::<serde_json::Value>(data) else { return };
    let Ok(spec) = serde_json::from_value::<RunSpec>(upgrade_config(v)) else { return };
    if spec.model.validate().is_ok() {
        assert!(spec.model.taps() >= 1 && spec.model.bins() >= 1);
    }
});
