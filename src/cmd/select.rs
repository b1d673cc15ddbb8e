//! `tcsense codes select`: the best code set of many, by TVAL3 MSE over a dataset or by
//! identifiability (range alias, Cramér–Rao bounds) with the local search.

use anyhow::{bail, Result};
use clap::{Args, ValueEnum};
use indicatif::{ProgressBar, ProgressStyle};
use std::path::PathBuf;
use std::process::ExitCode;
use tcsense_infer::selection::select;
use tcsense_sensor::design::{design, Criterion, DesignOptions, DesignProgress, Objective, Score};
use tcsense_sensor::SensorParams;

use super::code_shape::DesignArgs;
use super::dataset::interrupt_flag;
use super::sweep::{load, EvalArgs};

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
    /// lifetime, which are closed-form; at most 1 000 000).
    #[arg(long, value_parser = super::count_in(1, tcsense_sensor::design::MAX_CANDIDATES))]
    candidates: Option<usize>,
    /// Moves of each local search, from the 8 best candidates (range and lifetime; default
    /// 50000; at most 100 000 000).
    #[arg(long, value_parser = super::count_in(0, tcsense_sensor::design::MAX_MOVES))]
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
            ProgressStyle::with_template(&format!("{what} [{{bar:30}}] {{pos}}/{{len}} eta {{eta}} {{msg}}"))
                .unwrap_or_else(|_| ProgressStyle::default_bar())
                .progress_chars("=> ")
        };
        Bars {
            candidates: ProgressBar::new(candidates as u64).with_style(style("candidates")),
            moves: ProgressBar::new(moves as u64).with_style(style("local search")),
        }
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
    // TVAL3's settings are the MSE criterion's; given here they go unused, but a NaN or a
    // negative one is refused all the same, as `eval` refuses them without a TVAL3 decoder
    a.eval.tval3.options()?;
    // the sensor crate's defaults: 20 000 candidates, 8 searches of 50 000 moves
    let defaults = DesignOptions::default();
    let candidates = a.candidates.unwrap_or(defaults.candidates);
    if candidates == 0 {
        bail!("--candidates 0: at least one candidate");
    }
    let iterations = a.search.unwrap_or(defaults.moves);
    let irf = super::sensor::parse_irf(a.eval.irf.as_deref().unwrap_or("physical"))?;
    let sampling = tcsense_sensor::Sampling::from_factors(a.oversample, a.heterodyne, tcsense_sensor::Sampling::Oversample(1))?;
    let spec = SensorParams {
        block: d.block,
        taps: d.taps,
        drain: d.drain,
        length: d.length,
        clock_hz: d.clock_hz(),
        sampling,
        irf,
        ..Default::default()
    }
    .validate()?;
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
        eprintln!(
            "warning: the best codes found still alias ({:.3} < {threshold}): try more --candidates or --search, or relax the constraints",
            out.score.alias
        );
    }
    codes.save(&a.output)?;
    if out.score.alias < threshold {
        eprintln!(
            "warning: the best codes found still alias ({:.3} < {threshold}): try more --candidates or --search, or relax the constraints",
            out.score.alias
        );
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
    pb.set_style(
        ProgressStyle::with_template("candidates [{bar:30}] {pos}/{len} eta {eta}")
            .unwrap_or_else(|_| ProgressStyle::default_bar())
            .progress_chars("=> "),
    );
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
