//! The ONNX metadata reader of `tcsense infer`: any bytes parse as a model protobuf or not;
//! its `metadata_props` give checked metadata (codes, sensor model, frame rule) or an error.
#![no_main]
use libfuzzer_sys::fuzz_target;
use protobuf::Message;
use std::path::Path;
use tcsense_infer::onnx::OnnxMeta;

fuzz_target!(|data: &[u8]| {
    let Ok(model) = onnx_protobuf::ModelProto::parse_from_bytes(data) else { return };
    let props: std::collections::HashMap<String, String> = model.metadata_props.iter().map(|p| (p.key.clone(), p.value.clone())).collect();
    if let Ok(meta) = OnnxMeta::from_props(Path::new("fuzz.onnx"), |k| props.get(k).cloned()) {
        assert!(meta.taps >= 1 && meta.frame_multiple.0 >= 1);
    }
});
