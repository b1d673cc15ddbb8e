use anyhow::Result;
use clap::{Args, Subcommand};
use std::process::ExitCode;
#[derive(Subcommand)]
pub enum DatasetCmd { X }
#[derive(Args)]
pub struct BenchDatasetArgs {}
pub fn run(_c: DatasetCmd) -> Result<ExitCode> { Ok(ExitCode::SUCCESS) }
pub fn bench(_a: BenchDatasetArgs) -> Result<()> { Ok(()) }
