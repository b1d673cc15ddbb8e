//! `tcsense codes select` and `tcsense sweep …`: TVAL3 MSE over a dataset.

use anyhow::{bail, Result};
use clap::{Args, Subcommand, ValueEnum};
use indicatif::{ProgressBar, ProgressStyle};
use ndarray::{Array3, Axis, Ix4};
use std::path::PathBuf;
use std::process::ExitCode;
use tcsense_datasets::Dataset;
use tcsense_infer::figures::{log_chart, Series};
use tcsense_infer::selection::{evaluate_candidates, select, table1_settings, Candidate, EvalSetup};
use tcsense_sensor::codes::{CodeShape, Constraints};
use tcsense_sensor::npy::write_bytes;
use tcsense_sensor::design::{design, Criterion, DesignOptions, DesignProgress, Objective, Score};
use tcsense_sensor::SensorParams;

use super::codes::DesignArgs;
use super::dataset::interrupt_flag;
use super::recon::Tval3Args;

/// Dataset and evaluation flags.
#[derive(Args, Clone)]
pub struct EvalArgs {
    /// Dataset directory (the MSE criterion).
    #[arg(long)]
    dataset: Option<PathBuf>,
    /// Split to evaluate on.
    #[arg(long, default_value = "test")]
    split: String,
    /// Use at most this many items of the split.
    #[arg(long, default_value_t = 2)]
    items: usize,
    /// Instrument response: ideal or physical (default: ideal for the MSE, physical for the
    /// identifiability criteria).
    #[arg(long)]
    irf: Option<String>,
    #[command(flatten)]
    tval3: Tval3Args,
}

struct Loaded {
    cubes: Vec<Array3<f32>>,
    setup: EvalSetup,
    length: usize,
    clock_hz: f64,
    size: (usize, usize),
}

fn load(e: &EvalArgs) -> Result<Loaded> {
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
    Ok(Loaded { cubes, setup: EvalSetup { base, tval3: e.tval3.options()? }, length: g.length, clock_hz: g.clock_hz, size: (ds.manifest.size[0], ds.manifest.size[1]) })
}

#[derive(Args)]
pub struct SelectArgs {
    #[command(flatten)]
    design: DesignArgs,
    #[command(flatten)]
    eval: EvalArgs,
    /// What to select for: `mse` (TVAL3 over --dataset, the paper's method), `range` (LiDAR: no
    /// range alias, the smallest worst-case range bound) or `lifetime` (FLIm, with
    /// --heterodyne: no range alias, the smallest worst-case relative lifetime bound).
    #[arg(long, value_enum, default_value_t = SelectCriterion::Mse)]
    criterion: SelectCriterion,
    /// Number of random candidates (default: 20 for mse, as the paper; 20000 for range and
    /// lifetime, which are closed-form).
    #[arg(long)]
    candidates: Option<usize>,
    /// Moves of each local search, from the 8 best candidates (range and lifetime; default 50000).
    #[arg(long)]
    search: Option<usize>,
    /// Grid: oversampling factor K (range and lifetime criteria).
    #[arg(long, value_name = "K", conflicts_with = "heterodyne")]
    oversample: Option<usize>,
    /// Grid: heterodyne sweep with K steps (range and lifetime criteria).
    #[arg(long, value_name = "K")]
    heterodyne: Option<usize>,
    #[command(flatten)]
    light: super::analyze::LightArgs,
    /// Seed of the first candidate (the others follow).
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Output codes JSON of the best candidate.
    #[arg(short, long)]
    output: PathBuf,
}

/// Progress bars of a design: candidates, then the local searches' moves.
struct Bars {
    candidates: ProgressBar,
    moves: ProgressBar,
}

impl Bars {
    fn new(candidates: usize, moves: usize) -> Bars {
        let style = |what: &str| {
            ProgressStyle::with_template(&format!("{what} [{{bar:30}}] {{pos}}/{{len}} eta {{eta}} {{msg}}")).unwrap_or_else(|_| ProgressStyle::default_bar()).progress_chars("=> ")
        };
        Bars { candidates: ProgressBar::new(candidates as u64).with_style(style("candidates")), moves: ProgressBar::new(moves as u64).with_style(style("local search")) }
    }

    fn done(&self) {
        self.candidates.finish_and_clear();
        self.moves.finish_and_clear();
    }
}

impl DesignProgress for Bars {
    fn candidates(&self, done: usize, of: usize) {
        self.candidates.set_position(done as u64);
        if done == of {
            self.candidates.finish_and_clear();
        }
    }
    fn moves(&self, done: usize, score: &Score) {
        self.moves.inc(done as u64);
        self.moves.set_message(format!("alias {:.3}, worst {:.4}", score.alias, score.worst));
    }
}

/// What `codes select` selects for.
#[derive(Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum SelectCriterion {
    Mse,
    Range,
    Lifetime,
}

pub fn select_cmd(a: SelectArgs) -> Result<ExitCode> {
    let criterion = match a.criterion {
        SelectCriterion::Mse => {
            if a.search.is_some() {
                bail!("--search: the local search scores thousands of code sets; use it with --criterion range or lifetime (closed-form), not mse");
            }
            return select_mse(a);
        }
        SelectCriterion::Range => Criterion::Range,
        SelectCriterion::Lifetime => Criterion::Lifetime,
    };
    select_identifiable(a, criterion)
}

/// `codes select --criterion range|lifetime`: best of random candidates, then the local search.
fn select_identifiable(a: SelectArgs, criterion: Criterion) -> Result<ExitCode> {
    let d = &a.design;
    // the sensor crate's defaults: 20 000 candidates, 8 searches of 50 000 moves
    let defaults = DesignOptions::default();
    let candidates = a.candidates.unwrap_or(defaults.candidates);
    if candidates == 0 {
        bail!("--candidates 0: at least one candidate");
    }
    let iterations = a.search.unwrap_or(defaults.moves);
    let irf = super::sensor::parse_irf(a.eval.irf.as_deref().unwrap_or("physical"))?;
    let sampling = tcsense_sensor::Sampling::from_factors(a.oversample, a.heterodyne, tcsense_sensor::Sampling::Oversample(1))?;
    let spec = SensorParams { block: d.block, taps: d.taps, drain: d.drain, length: d.length, clock_hz: d.clock_hz(), sampling, irf, ..Default::default() }.validate()?;
    let light = a.light.light()?;
    let threshold = a.light.alias_threshold;
    let obj = Objective::new(criterion, &spec, light, threshold);
    let cancel = interrupt_flag();
    let t0 = std::time::Instant::now();
    let opts = DesignOptions { candidates, moves: iterations, seed: a.seed, ..defaults };
    let progress = Bars::new(candidates, iterations * opts.starts.min(candidates));
    let out = design(&obj, d.shape(), d.clock_hz(), d.constraints(), &opts, &progress, &cancel)?;
    progress.done();
    let unit = match criterion {
        Criterion::Range => "bins",
        Criterion::Lifetime => "σ(τ)/τ",
    };
    let (best_seed, best) = out.best_candidate;
    println!(
        "{candidates} candidates: median alias {:.3}; best (seed {best_seed}): alias {:.3}, worst bound {:.4} {unit}, mean {:.4}",
        out.median_alias, best.alias, best.worst, best.mean
    );
    for (seed, s) in &out.searches {
        println!(
            "local search from seed {seed}: {} moves ({} broke a constraint and were refused, {} kept): alias {:.3}, worst bound {:.4} {unit}, mean {:.4}",
            s.tried, s.infeasible, s.kept, s.score.alias, s.score.worst, s.score.mean
        );
    }
    println!("{:.1} s in all; kept the search from seed {}", t0.elapsed().as_secs_f64(), out.start_seed);
    let mut codes = out.codes;
    if let serde_json::Value::Object(m) = &mut codes.provenance {
        m.insert("irf".into(), serde_json::json!(a.eval.irf.as_deref().unwrap_or("physical")));
        m.insert("sampling".into(), serde_json::json!(format!("{sampling:?}")));
    }
    if out.score.alias < threshold {
        eprintln!("warning: the best codes found still alias ({:.3} < {threshold}): try more --candidates or --search, or relax the constraints", out.score.alias);
    }
    codes.save(&a.output)?;
    if out.score.alias < threshold {
        eprintln!("warning: the best codes found still alias ({:.3} < {threshold}): try more --candidates or --search, or relax the constraints", out.score.alias);
    }
    println!("wrote {}", a.output.display());
    Ok(ExitCode::SUCCESS)
}

fn select_mse(a: SelectArgs) -> Result<ExitCode> {
    let l = load(&a.eval)?;
    let dataset = a.eval.dataset.clone().unwrap_or_default();
    let d = &a.design;
    if d.length != l.length {
        bail!("--length {} differs from the dataset's L = {} ({})", d.length, l.length, dataset.display());
    }
    let candidates = a.candidates.unwrap_or(20);
    if candidates == 0 {
        bail!("--candidates 0: at least one candidate");
    }
    let (h, w) = l.size;
    if h % d.block.0 != 0 || w % d.block.1 != 0 {
        bail!("{}: frame {h}x{w} is not a multiple of the {}x{} block", dataset.display(), d.block.0, d.block.1);
    }
    let cancel = interrupt_flag();
    let pb = ProgressBar::new(candidates as u64);
    pb.set_style(ProgressStyle::with_template("candidates [{bar:30}] {pos}/{len} eta {eta}").unwrap_or_else(|_| ProgressStyle::default_bar()).progress_chars("=> "));
    println!("candidate seed        MSE");
    let mut on = |c: &tcsense_infer::selection::Candidate| {
        pb.suspend(|| println!("{:>14} {:.4e}", c.seed, c.mse));
        pb.inc(1);
    };
    let (best, all) = select(d.shape(), d.clock_hz(), d.constraints(), candidates, a.seed, &l.setup, &l.cubes, &mut on, &cancel)?;
    pb.finish_and_clear();
    best.save(&a.output)?;
    let bm = all.iter().map(|c| c.mse).fold(f64::INFINITY, f64::min);
    println!("wrote {}: best MSE {bm:.4e} of {} candidates ({})", a.output.display(), all.len(), d.constraints().label());
    Ok(ExitCode::SUCCESS)
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
    #[arg(long, default_value_t = 1)]
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
    pb.set_style(ProgressStyle::with_template("sweep [{bar:30}] {pos}/{len} eta {eta} {msg}").unwrap_or_else(|_| ProgressStyle::default_bar()).progress_chars("=> "));
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
