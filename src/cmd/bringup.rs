//! `tcsense bringup`: a sweep of a sensor on the bench → calibration → the zoo's decoders
//! fine-tuned to it within a budget → ONNX models that take its raw tap images → a check and
//! `DIR/report.html`. The pipeline is `tcsense_pipeline::bringup`; this module parses the flags.

use anyhow::Result;
use clap::Args;
use std::path::PathBuf;
use std::process::ExitCode;
use tcsense_pipeline::bringup::{self, BringupOptions};

use super::dataset::interrupt_flag;
use super::demo::Terminal;

#[derive(Args)]
pub struct BringupArgs {
    /// The sweep directory (`sweep.json`; `tcsense simulate --sweep` writes one of a simulated sensor).
    #[arg(long)]
    sweep: PathBuf,
    /// The codes the sensor runs.
    #[arg(long)]
    codes: PathBuf,
    /// Nominal instrument response: `physical` (laser pulse ⋆ tap response) or `ideal`.
    #[arg(long, default_value = "physical")]
    irf: String,
    /// Heterodyne sweep with K steps (FLIm); default: the LiDAR grid (T = L).
    #[arg(long, value_name = "K")]
    heterodyne: Option<usize>,
    /// A zoo entry to fine-tune (repeat for several; default: the designed-codes entries of
    /// the sensor's domain, unet-lidar-designed and admm-lidar-designed, or lifetime-flim-designed).
    #[arg(long = "decoder", value_name = "NAME")]
    decoders: Vec<String>,
    /// Time for the whole path in minutes; the fine-tunings get 80 % of it, sized from a
    /// measured step time.
    #[arg(long, default_value_t = 20.0, value_parser = super::number_in(0.01, 10080.0))]
    budget_minutes: f64,
    /// Epochs of every fine-tuning instead of sizing them to the budget.
    #[arg(long, value_parser = super::count_in(1, 100_000))]
    epochs: Option<usize>,
    /// Training scenes generated for the sensor's grid.
    #[arg(long, default_value_t = 400, value_parser = super::count_in(4, 100_000))]
    scenes: usize,
    /// Their frame size.
    #[arg(long, value_parser = super::parse_hw, default_value = "64x64")]
    size: (usize, usize),
    /// Held-back scenes of the check.
    #[arg(long, default_value_t = 8, value_parser = super::count_in(1, 10_000))]
    check_items: usize,
    /// Seed of the scenes, the weights' training order and the noise.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Output directory (rerunning into it resumes; a directory brought up from another sweep,
    /// codes or settings is refused, naming the difference).
    #[arg(short, long)]
    output: PathBuf,
}

pub fn run(a: BringupArgs) -> Result<ExitCode> {
    let sampling = tcsense_sensor::Sampling::from_factors(None, a.heterodyne, tcsense_sensor::Sampling::Oversample(1))?;
    let options = BringupOptions {
        sweep: a.sweep,
        codes: a.codes,
        sampling,
        irf: super::sensor::parse_irf(&a.irf)?,
        decoders: a.decoders,
        budget_minutes: a.budget_minutes,
        epochs: a.epochs,
        scenes: a.scenes,
        size: a.size,
        check_items: a.check_items,
        seed: a.seed,
    };
    let term = Terminal::new();
    let cancel = interrupt_flag();
    let res = bringup::run(&options, &a.output, &term, &cancel);
    term.items.finish_and_clear();
    term.training.pb.finish_and_clear();
    let s = res?;
    println!("wrote {}: {} models in {}", s.report.display(), s.models.len(), a.output.join("onnx").display());
    Ok(ExitCode::SUCCESS)
}
