//! `tcsense demo`: the paper's prototype end to end with no input files, into
//! `DIR/report.html`. The pipeline is `tcsense_pipeline::demo` (the Python module runs the
//! same); this module parses the flags, draws the progress bars and handles Ctrl-C.

use anyhow::Result;
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use std::path::PathBuf;
use std::process::ExitCode;
use tcsense_pipeline::demo::{self, DemoOptions, Observer};
use tcsense_train::Progress;

use super::dataset::interrupt_flag;

#[derive(Args)]
pub struct DemoArgs {
    /// About 2 minutes instead of about 10: 32×32 frames, fewer scenes, shorter training.
    #[arg(long)]
    quick: bool,
    /// Time for the whole demo in minutes (default 10, or 2 with --quick): the training
    /// epochs are sized to it from a measured step time.
    #[arg(long)]
    budget_minutes: Option<f64>,
    /// Frame size of the datasets (default 64x64, 32x32 with --quick).
    #[arg(long, value_parser = super::parse_hw)]
    size: Option<(usize, usize)>,
    /// LiDAR scenes (FLIm: half as many; default 400, 160 with --quick).
    #[arg(long)]
    scenes: Option<usize>,
    /// Frame size of the timing table (the sensor's 188x212).
    #[arg(long, default_value = "188x212", value_parser = super::parse_hw)]
    timing_size: (usize, usize),
    /// Seed of everything random (scenes, codes, weights, noise).
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Output directory (rerunning into it resumes).
    #[arg(short, long)]
    output: PathBuf,
}

/// Log lines on stdout, one progress bar for item counts and one for trainings.
pub(crate) struct Terminal {
    pub(crate) items: ProgressBar,
    pub(crate) training: super::train::Bar,
}

impl Terminal {
    /// Lines on stdout, item counts and trainings as bars on stderr.
    pub(crate) fn new() -> Self {
        let items = ProgressBar::hidden();
        items.set_style(
            ProgressStyle::with_template("  {msg} [{bar:30}] {pos}/{len}")
                .unwrap_or_else(|_| ProgressStyle::default_bar())
                .progress_chars("=> "),
        );
        items.set_draw_target(indicatif::ProgressDrawTarget::stderr());
        Terminal { items, training: super::train::Bar::new() }
    }
}

impl Observer for Terminal {
    fn line(&self, text: &str) {
        self.items.suspend(|| println!("{text}"));
    }

    fn items(&self, what: &str, done: usize, of: usize) {
        if done <= 1 {
            self.items.reset();
            self.items.set_length(of as u64);
            self.items.set_message(what.to_string());
        }
        self.items.set_position(done as u64);
        if done >= of {
            self.items.finish_and_clear();
        }
    }

    fn training(&self) -> &dyn Progress {
        &self.training
    }
}

pub fn run(a: DemoArgs) -> Result<ExitCode> {
    let options = DemoOptions {
        quick: a.quick,
        budget_minutes: a.budget_minutes,
        size: a.size,
        scenes: a.scenes,
        timing_size: a.timing_size,
        seed: a.seed,
    };
    let term = Terminal::new();
    let cancel = interrupt_flag();
    let res = demo::run(&options, &a.output, &term, &cancel);
    term.items.finish_and_clear();
    term.training.pb.finish_and_clear();
    res?;
    Ok(ExitCode::SUCCESS)
}
