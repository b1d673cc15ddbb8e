//! Where the learned decoders run: the CPU (burn's `flex` backend with this workspace's
//! kernels) or a GPU (burn's `wgpu` backend — Vulkan, Metal or DX12 — in builds with the cargo
//! feature `gpu`). On the GPU every network runs burn's composed ops (see
//! `tcsense_kernels::runs_kernels`); weights and checkpoints are the same files on both.

use crate::{ModelError, Result};
use burn::tensor::Device;

/// A processor to run a decoder on.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Processor {
    /// burn's `flex` device and the custom CPU kernels.
    #[default]
    Cpu,
    /// The best adapter of burn's `wgpu` backend (a discrete GPU first).
    Gpu,
}

/// Whether this build has the GPU backend (cargo feature `gpu`).
pub const GPU_BUILT: bool = cfg!(feature = "gpu");

/// The burn device of `processor` (without autodiff), checked to work: an error, not a panic,
/// when this build has no GPU backend or the machine no adapter.
pub fn device(processor: Processor) -> Result<Device> {
    match processor {
        Processor::Cpu => Ok(Device::flex()),
        Processor::Gpu => gpu(),
    }
}

/// A line that names the device, for the user.
pub fn describe(device: &Device) -> String {
    if tcsense_kernels::runs_kernels(device) {
        return "cpu (burn flex + tcsense kernels)".into();
    }
    describe_gpu(device)
}

#[cfg(feature = "gpu")]
fn describe_gpu(device: &Device) -> String {
    match device.identity() {
        Some(id) => format!("gpu (burn wgpu, adapter {})", id.name),
        None => format!("gpu (burn wgpu: {device:?})"),
    }
}

#[cfg(not(feature = "gpu"))]
fn describe_gpu(device: &Device) -> String {
    format!("{device:?}")
}

#[cfg(feature = "gpu")]
fn gpu() -> Result<Device> {
    use burn::tensor::{DeviceKind, Tensor};
    let device = Device::wgpu(DeviceKind::DefaultDevice);
    // wgpu picks its adapter on the first operation and panics when there is none: run one
    // here, quietly, and turn a failure into an error
    // (wgpu runs on a thread of its own: its panic, the cause, is recorded from any thread)
    let said = std::sync::Arc::new(std::sync::Mutex::new(Vec::<String>::new()));
    let hook = std::panic::take_hook();
    let record = said.clone();
    std::panic::set_hook(Box::new(move |info| {
        if let (Some(msg), Ok(mut v)) = (panic_text(info.payload()), record.lock()) {
            v.push(msg);
        }
    }));
    let probe = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| Tensor::<1>::ones([4], &device).sum().into_scalar::<f32>()));
    std::panic::set_hook(hook);
    let first_said = said.lock().ok().and_then(|v| v.first().cloned());
    // what wgpu said, for the message: an adapter missing and one failing read differently
    let cause = match &probe {
        Ok(v) if *v == 4.0 => return Ok(device),
        Ok(v) => format!("a test sum gave {v}, not 4"),
        Err(payload) => first_said.or_else(|| panic_text(payload.as_ref())).unwrap_or_else(|| "a panic without a message".into()),
    };
    Err(ModelError::InvalidParam {
        field: "--device",
        got: "gpu".into(),
        expected: format!("a machine with a GPU adapter burn's wgpu backend can use (Vulkan, Metal or DX12; none works here — on Linux without a GPU, Mesa's software Vulkan driver `mesa-vulkan-drivers` provides one); wgpu: {}", cause.split_whitespace().collect::<Vec<_>>().join(" ")),
    })
}

/// A panic's message (a `String` or `&str` payload), where it has a non-empty one.
#[cfg(feature = "gpu")]
fn panic_text(payload: &(dyn std::any::Any + Send)) -> Option<String> {
    payload.downcast_ref::<String>().cloned().or_else(|| payload.downcast_ref::<&str>().map(|s| s.to_string())).filter(|m| !m.is_empty())
}

#[cfg(not(feature = "gpu"))]
fn gpu() -> Result<Device> {
    Err(ModelError::InvalidParam {
        field: "--device",
        got: "gpu".into(),
        expected: "cpu: this build has no GPU backend; build tcsense with `cargo build --release --features gpu` (burn's wgpu backend: Vulkan, Metal or DX12)".into(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_cpu_device_runs_the_kernels() {
        let d = device(Processor::Cpu).unwrap();
        assert!(tcsense_kernels::runs_kernels(&d));
        assert!(tcsense_kernels::runs_kernels(&d.clone().autodiff()));
        assert!(describe(&d).starts_with("cpu"));
    }

    #[cfg(not(feature = "gpu"))]
    #[test]
    fn without_the_feature_the_gpu_is_an_error_that_says_how_to_build_it() {
        let e = device(Processor::Gpu).unwrap_err().to_string();
        assert!(e.contains("--features gpu"), "{e}");
    }
}
