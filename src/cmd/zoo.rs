//! `tcsense zoo …`: the trained decoders shipped with the toolkit (`tcsense_models::zoo`).

use anyhow::Result;
use clap::Subcommand;
use std::process::ExitCode;
use tcsense_models::zoo::{self, Entry};

#[derive(Subcommand)]
pub enum ZooCmd {
    /// The zoo's entries: decoder, domain, codes, epochs and last validation metrics. Use one
    /// wherever a run is taken as `zoo:NAME` (`reconstruct`, `eval`, `export onnx`,
    /// `train --init-from`).
    List,
    /// One entry: what it is, where its files are, and its PROVENANCE.md (commands, commit,
    /// data, wall time, benchmark tables).
    Show {
        /// The entry's name (`NAME` or `zoo:NAME`).
        name: String,
    },
}

pub fn run(cmd: ZooCmd) -> Result<ExitCode> {
    match cmd {
        ZooCmd::List => {
            let entries = zoo::list()?;
            println!("zoo: {} ({} entries)", zoo::root().display(), entries.len());
            println!(
                "{:<28} {:<9} {:<6} {:<8} {:>6}  {:<6} {:<24} {}",
                "NAME", "DECODER", "DOMAIN", "CODES", "EPOCHS", "ALIAS", "LIGHT", "VALIDATION"
            );
            for e in &entries {
                println!(
                    "{:<28} {:<9} {:<6} {:<8} {:>6}  {:<6} {:<24} {}",
                    e.name,
                    e.model.name(),
                    e.domain,
                    codes_kind(e),
                    e.epochs,
                    alias(e),
                    e.light,
                    validation(e)
                );
            }
            println!("LIGHT: the brightest tap's share of the full well it was trained at (a range: the photon ladder, drawn per item), and the ambient light as 1/SBR");
            if entries.iter().any(|e| e.range_alias.is_some_and(|a| a < tcsense_sensor::identify::DEFAULT_ALIAS_THRESHOLD)) {
                println!("ALIAS: the range alias of the entry's codes on its sensor; below 0.5 (*) two ranges two masks or more apart give nearly the same taps (`tcsense codes analyze`)");
            }
            let compared: Vec<&Entry> = entries.iter().filter(|e| e.comparison.is_some()).collect();
            if !compared.is_empty() {
                println!("CODES: learned codes against the same network on designed codes, on the photon ladder of test sets unlike the training data (`zoo show NAME`): learned† a baseline (they lose), learned= on a par (within 5 % at 0.02 and 0.8), learned+ wins (0.8× at 0.02)");
                for e in compared {
                    if let Some(c) = &e.comparison {
                        println!(
                            "  {}: {} against zoo:{} ({}, learned / against: {})",
                            e.name,
                            verdict(c.verdict),
                            c.against,
                            c.product,
                            c.ratios()
                        );
                    }
                }
            }
        }
        ZooCmd::Show { name } => {
            let e = zoo::entry(&name)?;
            println!("zoo:{} — {}", e.name, e.title);
            println!("  directory   {}", e.dir.display());
            println!(
                "  decoder     {} ({} taps, {} bins, {:.2} GFLOP per 188x212 frame)",
                e.model.name(),
                e.model.taps(),
                e.model.bins(),
                e.model.flops(188, 212) / 1e9
            );
            println!("  domain      {}", e.domain);
            println!("  codes       {} ({}), range alias {}", e.codes, codes_kind(&e), alias(&e));
            println!("  trained     {} epochs at light {}; last validation {}", e.epochs, e.light, validation(&e));
            println!("  weights     {:.2} MB", e.weights_bytes as f64 / 1e6);
            if let Some(c) = &e.comparison {
                println!(
                    "  against     zoo:{}, the same network on its codes: {} ({}, learned / against, geometric mean over {} test sets: {})",
                    c.against,
                    verdict(c.verdict),
                    c.product,
                    c.sets.len(),
                    c.ratios()
                );
                // seconds as ns, metres as they are
                let (scale, unit) = if c.product.ends_with("(s)") { (1e9, "ns") } else { (1.0, "m") };
                let cell = |v: &Option<f64>| v.map_or("–".to_string(), |v| format!("{:.3}", v * scale));
                let head: String = c.levels.iter().map(|l| format!("  {:>20}", format!("{l}: learned / vs"))).collect();
                println!("              {:<22}{head}   ({unit})", "set");
                for (set, row) in &c.sets {
                    let cells: String = row
                        .learned
                        .iter()
                        .zip(&row.against)
                        .map(|(a, b)| format!("  {:>20}", format!("{} / {}", cell(a), cell(b))))
                        .collect();
                    println!("              {set:<22}{cells}");
                }
            }
            println!();
            match std::fs::read_to_string(e.dir.join(zoo::PROVENANCE_FILE)) {
                Ok(text) => print!("{text}"),
                Err(_) => println!("(no {} in this entry)", zoo::PROVENANCE_FILE),
            }
        }
    }
    Ok(ExitCode::SUCCESS)
}

/// `0.773`, or `0.011*` below the alias threshold.
fn alias(e: &Entry) -> String {
    match e.range_alias {
        Some(a) if a < tcsense_sensor::identify::DEFAULT_ALIAS_THRESHOLD => format!("{a:.3}*"),
        Some(a) => format!("{a:.3}"),
        None => "–".into(),
    }
}

fn verdict(v: zoo::Verdict) -> &'static str {
    match v {
        zoo::Verdict::Wins => "wins",
        zoo::Verdict::OnPar => "on a par (short of 0.8× at 0.02)",
        zoo::Verdict::Baseline => "baseline (the learned codes lose)",
    }
}

fn codes_kind(e: &Entry) -> &'static str {
    if e.learned_codes {
        match e.comparison.as_ref().map(|c| c.verdict) {
            Some(zoo::Verdict::Baseline) => "learned†",
            Some(zoo::Verdict::Wins) => "learned+",
            Some(zoo::Verdict::OnPar) => "learned=",
            None => "learned",
        }
    } else if e.designed_codes {
        "designed"
    } else {
        "given"
    }
}

/// The last validation metrics, in the units their column names give.
fn validation(e: &Entry) -> String {
    e.validation
        .iter()
        .map(|(n, v)| match n.as_str() {
            "val_psnr_db" => format!("PSNR {v:.2} dB"),
            "val_mse" => format!("MSE {v:.3e}"),
            "val_depth_mae_m" => format!("range MAE {:.1} cm", v * 100.0),
            "val_depth_rmse_m" => format!("range RMSE {:.1} cm", v * 100.0),
            "val_detection" => format!("detected {:.1} %", v * 100.0),
            "val_lifetime_mae_ns" => format!("lifetime MAE {v:.3} ns"),
            "val_coverage" => format!("coverage {:.1} %", v * 100.0),
            other => format!("{other} {v:.4}"),
        })
        .collect::<Vec<_>>()
        .join(", ")
}
