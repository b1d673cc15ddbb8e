//! One module per subcommand family.

pub mod analyze;
pub mod bench;
pub mod bench_decoders;
pub mod bringup;
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

/// The longest side of a frame any command takes (pixels).
pub const MAX_SIDE: usize = 65_536;
/// The most worker threads (`--threads`, `--ort-threads`).
pub const MAX_THREADS: usize = 256;

/// Parse `HxW` (e.g. `2x2`, `188x212`), each side from 1 to [`MAX_SIDE`].
pub fn parse_hw(s: &str) -> Result<(usize, usize), String> {
    let (a, b) = s.split_once(['x', 'X']).ok_or_else(|| format!("{s:?} is not of the form HxW (e.g. 2x2)"))?;
    let p = |v: &str| v.trim().parse::<usize>().map_err(|_| format!("{s:?} is not of the form HxW (e.g. 2x2)"));
    let (h, w) = (p(a)?, p(b)?);
    if !(1..=MAX_SIDE).contains(&h) || !(1..=MAX_SIDE).contains(&w) {
        return Err(format!("{s:?}: expected each side from 1 to {MAX_SIDE} pixels"));
    }
    Ok((h, w))
}

/// Parse a range `LO,HI` of finite numbers with `LO ≤ HI` (the ranges' own bounds are checked
/// where they are used, with the field's name).
pub fn parse_range(s: &str) -> Result<(f64, f64), String> {
    let form = || format!("{s:?} is not a range LO,HI of two numbers (e.g. 0.002,0.9)");
    let (a, b) = s.split_once(',').ok_or_else(form)?;
    let p = |v: &str| v.trim().parse::<f64>().ok().filter(|v| v.is_finite()).ok_or_else(form);
    let (lo, hi) = (p(a)?, p(b)?);
    if lo > hi {
        return Err(format!("{s:?}: LO is above HI"));
    }
    Ok((lo, hi))
}

/// A clap value parser of whole numbers from `lo` to `hi`: an absurd count is a usage error
/// naming the flag and the range, before anything is allocated.
pub fn count_in(lo: usize, hi: usize) -> impl Fn(&str) -> Result<usize, String> + Clone + Send + Sync + 'static {
    move |s: &str| {
        let v: usize = s.trim().parse().map_err(|_| format!("{s:?} is not a whole number (expected {lo} to {hi})"))?;
        if (lo..=hi).contains(&v) {
            Ok(v)
        } else {
            Err(format!("{v} is out of range: expected {lo} to {hi}"))
        }
    }
}

/// A clap value parser of finite numbers from `lo` to `hi`.
pub fn number_in(lo: f64, hi: f64) -> impl Fn(&str) -> Result<f64, String> + Clone + Send + Sync + 'static {
    move |s: &str| {
        let v: f64 = s.trim().parse().map_err(|_| format!("{s:?} is not a number (expected {lo} to {hi})"))?;
        if v.is_finite() && (lo..=hi).contains(&v) {
            Ok(v)
        } else {
            Err(format!("{v} is out of range: expected a finite number from {lo} to {hi}"))
        }
    }
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
