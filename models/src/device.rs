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
    let hook = std::panic::take_hook();
    std::panic::set_hook(Box::new(|_| {}));
    let probe = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| Tensor::<1>::ones([4], &device).sum().into_scalar::<f32>()));
    std::panic::set_hook(hook);
    match probe {
        Ok(v) if v == 4.0 => Ok(device),
        _ => Err(ModelError::InvalidParam {
            field: "--device",
            got: "gpu".into(),
            expected: "a machine with a GPU adapter burn's wgpu backend can use (Vulkan, Metal or DX12; none works here — on Linux without a GPU, Mesa's software Vulkan driver `mesa-vulkan-drivers` provides one)".into(),
        }),
    }
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
