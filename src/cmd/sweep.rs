//! `tcsense sweep …`: TVAL3 MSE over a dataset against taps, block and constraints (paper
//! Fig. 13, Table 1), and the dataset flags it shares with `codes select`.

use anyhow::{bail, Result};
use clap::{Args, Subcommand, ValueEnum};
use indicatif::{ProgressBar, ProgressStyle};
use ndarray::{Array3, Axis, Ix4};
use std::path::PathBuf;
use std::process::ExitCode;
use tcsense_datasets::Dataset;
use tcsense_infer::figures::{log_chart, Series};
use tcsense_infer::selection::{evaluate_candidates, table1_settings, Candidate, EvalSetup};
use tcsense_sensor::codes::{CodeShape, Constraints};
use tcsense_sensor::npy::write_bytes;
use tcsense_sensor::SensorParams;

use super::dataset::interrupt_flag;
use super::recon::Tval3Args;

/// Dataset and evaluation flags.
#[derive(Args, Clone)]
pub struct EvalArgs {
    /// Dataset directory (the MSE criterion).
    #[arg(long)]
    pub(super) dataset: Option<PathBuf>,
    /// Split to evaluate on.
    #[arg(long, default_value = "test")]
    pub(super) split: String,
    /// Use at most this many items of the split.
    #[arg(long, default_value_t = 2)]
    pub(super) items: usize,
    /// Instrument response: ideal or physical (default: ideal for the MSE, physical for the
    /// identifiability criteria).
    #[arg(long)]
    pub(super) irf: Option<String>,
    #[command(flatten)]
    pub(super) tval3: Tval3Args,
}

pub(super) struct Loaded {
    pub(super) cubes: Vec<Array3<f32>>,
    pub(super) setup: EvalSetup,
    pub(super) length: usize,
    pub(super) clock_hz: f64,
    pub(super) size: (usize, usize),
}

pub(super) fn load(e: &EvalArgs) -> Result<Loaded> {
    let Some(dataset) = &e.dataset else {
        bail!("--dataset DIR is required: the TVAL3 MSE is measured on a dataset's cubes");
    };
    let ds = Dataset::open(dataset)?;
    if e.items == 0 {
        bail!("--items 0: evaluate on at least one item");
    }
    let x = ds.load(&e.split, "x")?.into_dimensionality::<Ix4>()?;
    if x.dim().0 == 0 {
        bail!("{}: split {:?} is empty", dataset.display(), e.split);
    }
    let cubes: Vec<Array3<f32>> = x.axis_iter(Axis(0)).take(e.items).map(|v| v.to_owned()).collect();
    let irf = super::sensor::parse_irf(e.irf.as_deref().unwrap_or("ideal"))?;
    let g = ds.manifest.grid;
    let base = SensorParams { sampling: g.sampling, irf, length: g.length, clock_hz: g.clock_hz, ..Default::default() };
    Ok(Loaded {
        cubes,
        setup: EvalSetup { base, tval3: e.tval3.options()? },
        length: g.length,
        clock_hz: g.clock_hz,
        size: (ds.manifest.size[0], ds.manifest.size[1]),
    })
}

/// Which sweep.
#[derive(Clone, Copy, ValueEnum)]
pub enum Which {
    Taps,
    Block,
    Constraints,
}

#[derive(Subcommand)]
pub enum SweepCmd {
    /// MSE vs taps 1–8 at block 2×2 (Fig. 13a), one series per constraint setting.
    Taps(SweepArgs),
    /// MSE vs block 1×1 … 16×16 at 4 taps (Fig. 13b).
    Block(SweepArgs),
    /// The five constraint settings of Table 1 (4 taps, 2×2).
    Constraints(SweepArgs),
}

#[derive(Args)]
pub struct SweepArgs {
    #[command(flatten)]
    eval: EvalArgs,
    /// Code sets per point (the best is reported; paper: 20).
    #[arg(long, default_value_t = 1, value_parser = super::count_in(1, 10_000))]
    candidates: usize,
    /// Constraint series for taps/block sweeps: comma-separated from none, tap, tap+W2, tap+H2, tap+H2+W2.
    #[arg(long, default_value = "none,tap")]
    series: String,
    /// First seed.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Output directory (sweep.csv, summary.csv, sweep.png).
    #[arg(short, long)]
    output: PathBuf,
}

fn parse_series(s: &str) -> Result<Vec<(String, Constraints)>> {
    s.split(',')
        .map(|name| {
            let name = name.trim();
            let c = match name {
                "none" => Constraints::default(),
                "tap" => Constraints { tap: true, ..Default::default() },
                "tap+W2" => Constraints { tap: true, window: Some(2), ..Default::default() },
                "tap+H2" => Constraints { tap: true, hamming: Some(2), ..Default::default() },
                "tap+H2+W2" => Constraints { tap: true, hamming: Some(2), window: Some(2) },
                other => bail!("--series: unknown setting {other:?}; expected none, tap, tap+W2, tap+H2, tap+H2+W2"),
            };
            Ok((name.to_string(), c))
        })
        .collect()
}

pub fn sweep(cmd: SweepCmd) -> Result<ExitCode> {
    let (which, a) = match cmd {
        SweepCmd::Taps(a) => (Which::Taps, a),
        SweepCmd::Block(a) => (Which::Block, a),
        SweepCmd::Constraints(a) => (Which::Constraints, a),
    };
    let l = load(&a.eval)?;
    if a.candidates == 0 {
        bail!("--candidates 0: at least one code set per point");
    }
    let (h, w) = l.size;
    // points: (series name, constraints, x value, shape)
    let mut points: Vec<(String, Constraints, f64, CodeShape)> = Vec::new();
    let shape = |taps: usize, b: usize| CodeShape { bh: b, bw: b, taps, length: l.length, drain: false };
    match which {
        Which::Taps => {
            for (name, c) in parse_series(&a.series)? {
                for m in 1..=8 {
                    points.push((name.clone(), c, m as f64, shape(m, 2)));
                }
            }
        }
        Which::Block => {
            for (name, c) in parse_series(&a.series)? {
                for b in [1usize, 2, 4, 8, 16] {
                    if h % b == 0 && w % b == 0 {
                        points.push((name.clone(), c, b as f64, shape(4, b)));
                    }
                }
            }
        }
        Which::Constraints => {
            for (i, (name, c)) in table1_settings().into_iter().enumerate() {
                points.push((name.to_string(), c, i as f64, shape(4, 2)));
            }
        }
    }
    if h % 2 != 0 || w % 2 != 0 {
        bail!("{}: frame {h}x{w} is not a multiple of the 2x2 block", a.eval.dataset.clone().unwrap_or_default().display());
    }
    let cancel = interrupt_flag();
    let total = (points.len() * a.candidates) as u64;
    let pb = ProgressBar::new(total);
    pb.set_style(
        ProgressStyle::with_template("sweep [{bar:30}] {pos}/{len} eta {eta} {msg}")
            .unwrap_or_else(|_| ProgressStyle::default_bar())
            .progress_chars("=> "),
    );
    let mut csv = String::from("setting,param,candidate_seed,mse\n");
    let mut summary = String::from("setting,param,best_mse,mean_mse\n");
    let mut series: Vec<(String, Vec<(f64, f64)>)> = Vec::new();
    for (name, c, x, sh) in &points {
        let mut mses = Vec::new();
        let seeds: Vec<u64> = (0..a.candidates as u64).map(|k| a.seed.wrapping_add(k)).collect();
        let mut on = |cand: &Candidate| {
            csv.push_str(&format!("{name},{x},{},{:.6e}\n", cand.seed, cand.mse));
            pb.set_message(format!("{name} @ {x}: {:.3e}", cand.mse));
            pb.inc(1);
            mses.push(cand.mse);
        };
        evaluate_candidates(*sh, l.clock_hz, *c, &seeds, &l.setup, &l.cubes, &mut on, &cancel)?;
        let best = mses.iter().copied().fold(f64::INFINITY, f64::min);
        let mean = mses.iter().sum::<f64>() / mses.len() as f64;
        summary.push_str(&format!("{name},{x},{best:.6e},{mean:.6e}\n"));
        pb.suspend(|| println!("{name:>24} {x:>4}  best {best:.3e}  mean {mean:.3e}"));
        match series.iter_mut().find(|s| &s.0 == name) {
            Some(s) => s.1.push((*x, best)),
            None => series.push((name.clone(), vec![(*x, best)])),
        }
    }
    pb.finish_and_clear();
    // Table 1: one point per setting; draw them as a single series over the setting index.
    if matches!(which, Which::Constraints) {
        series = vec![("table1".into(), series.iter().flat_map(|s| s.1.clone()).collect())];
    }
    std::fs::create_dir_all(&a.output).map_err(|e| anyhow::anyhow!("{}: {e}", a.output.display()))?;
    write_bytes(&a.output.join("sweep.csv"), csv.as_bytes())?;
    write_bytes(&a.output.join("summary.csv"), summary.as_bytes())?;
    let (title, x_label) = match which {
        Which::Taps => ("TVAL3 MSE against the number of taps (2×2 block; paper Fig. 13a)", "taps M"),
        Which::Block => ("TVAL3 MSE against the block size (4 taps; paper Fig. 13b)", "block side (pixels)"),
        Which::Constraints => ("TVAL3 MSE of the constraint settings of the paper's Table 1", "setting (row of summary.csv)"),
    };
    let series: Vec<Series> = series.into_iter().map(|(label, points)| Series { label, points }).collect();
    log_chart(&a.output.join("sweep.png"), title, x_label, "MSE of the best of the candidates", &series)?;
    print!("{summary}");
    println!("wrote {}/sweep.csv, summary.csv, sweep.png", a.output.display());
    Ok(ExitCode::SUCCESS)
}
