//! `tcsense codes …`

use anyhow::{Context, Result};
use clap::{Args, Subcommand};
use std::path::PathBuf;
use std::process::ExitCode;

use super::code_shape::DesignArgs;
use tcsense_sensor::codes::Codes;
use tcsense_sensor::{export, generate};

#[derive(Subcommand)]
pub enum CodesCmd {
    /// Generate random codes under the chosen constraints.
    Generate(GenerateArgs),
    /// Check codes against their declared constraints (exit 0 feasible, 1 with violations),
    /// and print what the taps can tell apart (alias, range bound; a warning below the alias
    /// threshold).
    Check {
        /// Codes JSON file.
        codes: PathBuf,
        /// Print the violations as JSON.
        #[arg(long)]
        json: bool,
        #[command(flatten)]
        measure: super::analyze::MeasureArgs,
    },
    /// Export codes to the sensor's code memory: chCC.bin, codes.bin, registers.json. Codes
    /// that alias (two ranges, or two decays, the taps cannot tell apart) are refused.
    Export {
        /// Codes JSON file.
        codes: PathBuf,
        /// Output directory.
        #[arg(short, long)]
        output: PathBuf,
        #[command(flatten)]
        measure: super::analyze::MeasureArgs,
        /// Export even codes below the alias threshold.
        #[arg(long)]
        force: bool,
    },
    /// What the taps can tell apart: range alias, range Cramér–Rao bound over the cycle, two
    /// returns' resolution and, for FLIm (--heterodyne), the lifetime alias and bounds.
    Analyze(super::analyze::AnalyzeArgs),
    /// Read an exported code memory back into a codes JSON file.
    Import {
        /// Export directory (with registers.json).
        dir: PathBuf,
        /// Output codes JSON.
        #[arg(short, long)]
        output: PathBuf,
    },
    /// Design codes: the best of random candidates by a criterion (TVAL3 MSE on a dataset, or
    /// the closed-form range / lifetime identifiability), then a local search that keeps every
    /// constraint exact.
    Select(super::select::SelectArgs),
    /// Project code logits (e.g. learned elsewhere) exactly onto the constraints: the feasible
    /// codes of highest total log-probability.
    Project(ProjectArgs),
    /// Draw codes as a PNG (rows = channels grouped by subpixel, columns = masks).
    Show {
        /// Codes JSON file.
        codes: PathBuf,
        /// Output PNG.
        #[arg(short, long)]
        output: PathBuf,
    },
}

#[derive(Args)]
pub struct GenerateArgs {
    #[command(flatten)]
    design: DesignArgs,
    /// Random seed.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Output codes JSON.
    #[arg(short, long)]
    output: PathBuf,
}

#[derive(Args)]
pub struct ProjectArgs {
    /// Logits .npy [N, C, L]: with --tap-constraint a score per tap (C = M, +1 for the drain,
    /// last), e.g. log-probabilities; without it a log-odds per bit (C = M).
    #[arg(long)]
    logits: PathBuf,
    #[command(flatten)]
    design: DesignArgs,
    /// Output codes JSON.
    #[arg(short, long)]
    output: PathBuf,
}

/// `4 taps, block 2x2, L = 32, constraints tap+H2+W2`.
fn summary(codes: &Codes) -> String {
    let (bh, bw) = codes.block();
    format!("{} taps, block {bh}x{bw}, L = {}, constraints {}", codes.taps(), codes.length(), codes.constraints.label())
}

pub fn run(cmd: CodesCmd) -> Result<ExitCode> {
    match cmd {
        CodesCmd::Generate(a) => {
            let d = &a.design;
            let codes = generate::random_codes(d.shape(), d.clock_hz(), d.constraints(), a.seed)?;
            codes.save(&a.output)?;
            let hd: Vec<usize> = (0..codes.length()).map(|l| codes.hamming_at(l)).collect();
            println!("wrote {}: {}, max Hamming distance {}", a.output.display(), summary(&codes), hd.iter().max().unwrap_or(&0));
        }
        CodesCmd::Check { codes, json, measure } => {
            let g = Codes::load_unchecked(&codes)?;
            let v = g.violations();
            if json {
                println!("{}", serde_json::to_string_pretty(&v)?);
            } else if v.is_empty() {
                println!("{}: feasible under {}", codes.display(), g.constraints.label());
                super::analyze::check_measures(&codes, &measure)?;
            } else {
                for x in &v {
                    println!("{x}");
                }
                eprintln!("{}: {} violation(s) of {}", codes.display(), v.len(), g.constraints.label());
            }
            return Ok(if v.is_empty() { ExitCode::SUCCESS } else { ExitCode::from(1) });
        }
        CodesCmd::Export { codes, output, measure, force } => {
            let g = Codes::load(&codes)?;
            super::analyze::export_gate(&codes, &measure, force)?;
            let regs = export::export(&g, &output).with_context(|| format!("cannot export {}", codes.display()))?;
            println!(
                "wrote {} channels of {} bytes to {} (ECLEN = {})",
                regs.channel_count,
                regs.bytes_per_channel,
                output.display(),
                regs.ECLEN
            );
        }
        CodesCmd::Import { dir, output } => {
            let g = export::import(&dir)?;
            g.save(&output)?;
            println!("wrote {}", output.display());
        }
        CodesCmd::Select(a) => return super::select::select_cmd(a),
        CodesCmd::Analyze(a) => return super::analyze::analyze_cmd(a),
        CodesCmd::Project(a) => {
            let d = &a.design;
            let logits = tcsense_sensor::npy::read_npy(&a.logits)?;
            let shape = logits.shape().to_vec();
            let logits = logits.into_dimensionality::<ndarray::Ix3>().map_err(|_| {
                tcsense_sensor::SensorError::file(&a.logits, format!("logits of shape {shape:?}, expected rank 3 [N, C, L]"))
            })?;
            let t0 = std::time::Instant::now();
            let p = tcsense_sensor::project::project(d.shape(), d.clock_hz(), d.constraints(), &logits.view())
                .map_err(|e| e.in_file(&a.logits))?;
            let seconds = t0.elapsed().as_secs_f64();
            let mut codes = p.codes;
            codes.provenance = serde_json::json!({
                "method": "projection",
                "logits": a.logits.display().to_string(),
                "solver": p.method,
                "score": p.score,
                "argmax_score": p.argmax_score,
            });
            codes.save(&a.output)?;
            println!(
                "wrote {}: {}; {:?} projection in {seconds:.2} s, score {:.4} (the unconstrained argmax: {:.4})",
                a.output.display(),
                summary(&codes),
                p.method,
                p.score,
                p.argmax_score
            );
        }
        CodesCmd::Show { codes, output } => {
            let g = Codes::load_unchecked(&codes)?;
            let name = codes.file_name().map_or_else(|| codes.display().to_string(), |n| n.to_string_lossy().into_owned());
            tcsense_infer::figures::codes(&output, &name, &g)?;
            println!("wrote {}", output.display());
        }
    }
    Ok(ExitCode::SUCCESS)
}
