//! One module per subcommand family.

pub mod bench;
pub mod bringup;
pub mod analyze;
pub mod calibrate;
pub mod code_shape;
pub mod codes;
pub mod dataset;
pub mod demo;
pub mod deploy;
pub mod eval;
pub mod recon;
pub mod select;
pub mod sensor;
pub mod sweep;
pub mod train;
pub mod zoo;

/// A run directory argument: a path, or `zoo:NAME` for the zoo's entry (an unknown name is
/// a usage error listing the zoo's entries).
pub fn parse_run(s: &str) -> Result<std::path::PathBuf, String> {
    tcsense_models::zoo::resolve(s).map_err(|e| e.to_string())
}

/// The paper's prototype codes (4 taps, 2×2 blocks, L = 32, 607 MHz, tap constraint, Hamming
/// distance 2, window 2; seed 1), on which the benchmarks and fresh networks run.
pub fn prototype_codes() -> anyhow::Result<tcsense_sensor::Codes> {
    Ok(tcsense_sensor::generate::prototype_codes(1)?)
}

/// Parse `HxW` (e.g. `2x2`, `188x212`).
pub fn parse_hw(s: &str) -> Result<(usize, usize), String> {
    let (a, b) = s
        .split_once(['x', 'X'])
        .ok_or_else(|| format!("{s:?} is not of the form HxW (e.g. 2x2)"))?;
    let p = |v: &str| v.trim().parse::<usize>().map_err(|_| format!("{s:?} is not of the form HxW (e.g. 2x2)"));
    Ok((p(a)?, p(b)?))
}

/// `--device`: where a learned decoder trains or runs.
#[derive(clap::Args, Debug, Clone, Copy, Default)]
pub struct DeviceArgs {
    /// Device of the learned decoders: cpu (burn flex with tcsense's kernels) or gpu (burn's
    /// wgpu backend: Vulkan, Metal or DX12; builds with `--features gpu` only).
    #[arg(long, value_enum, default_value_t = DeviceArg::Cpu)]
    pub device: DeviceArg,
}

#[derive(clap::ValueEnum, Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum DeviceArg {
    #[default]
    Cpu,
    Gpu,
}

impl DeviceArgs {
    /// The burn device, checked to work; the GPU's adapter is named on stderr.
    pub fn device(&self) -> anyhow::Result<tcsense_models::Device> {
        use tcsense_models::device::{describe, device, Processor};
        let d = device(match self.device {
            DeviceArg::Cpu => Processor::Cpu,
            DeviceArg::Gpu => Processor::Gpu,
        })?;
        if self.device == DeviceArg::Gpu {
            eprintln!("device: {}", describe(&d));
        }
        Ok(d)
    }
}
