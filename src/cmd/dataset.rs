//! `tcsense dataset …` and `tcsense bench dataset`.

use anyhow::{bail, Result};
use clap::{Args, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Instant;
use tcsense_datasets::flim::FlimParams;
use tcsense_datasets::import::{self, ImportOptions, Source};
use tcsense_datasets::lidar::LidarParams;
use tcsense_datasets::store::{self, Dataset, Generator, WriteOptions, DEFAULT_SHARD};
use tcsense_datasets::{montage, TimeGrid};
use tcsense_sensor::Sampling;

/// Time-grid flags: T = L·K bins of T_c/K.
#[derive(Args, Clone)]
pub struct GridArgs {
    /// Masks per cycle L (multiple of 8, 8–256).
    #[arg(long, default_value_t = 32)]
    pub length: usize,
    /// Code clock in MHz.
    #[arg(long, default_value_t = 607.0)]
    pub clock_mhz: f64,
    /// Oversampling factor K.
    #[arg(long, value_name = "K", conflicts_with = "heterodyne")]
    pub oversample: Option<usize>,
    /// Heterodyne steps K.
    #[arg(long, value_name = "K")]
    pub heterodyne: Option<usize>,
}

impl GridArgs {
    pub fn grid(&self, default: Sampling) -> Result<TimeGrid> {
        let sampling = match (self.oversample, self.heterodyne) {
            (_, Some(k)) => Sampling::Heterodyne(k),
            (Some(k), None) => Sampling::Oversample(k),
            (None, None) => default,
        };
        Ok(TimeGrid { length: self.length, clock_hz: self.clock_mhz * 1e6, sampling }.validate()?)
    }
}

/// Flags shared by the generators.
#[derive(Args, Clone)]
pub struct CommonArgs {
    /// Number of items (split into train/val/test in the paper's proportions).
    #[arg(long)]
    count: usize,
    /// Frame size HxW.
    #[arg(long, default_value = "64x64", value_parser = super::parse_hw)]
    size: (usize, usize),
    /// Pixel block the frames must tile.
    #[arg(long, default_value = "2x2", value_parser = super::parse_hw)]
    block: (usize, usize),
    /// Random seed.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Items per shard file.
    #[arg(long, default_value_t = DEFAULT_SHARD)]
    shard_size: usize,
    /// Replace an existing output directory.
    #[arg(long)]
    force: bool,
    /// Output directory.
    #[arg(short, long)]
    output: PathBuf,
}

#[derive(Subcommand)]
pub enum DatasetCmd {
    /// LiDAR scenes with multipath (sheet, interreflections, ambient light).
    Lidar {
        #[command(flatten)]
        common: CommonArgs,
        #[command(flatten)]
        grid: GridArgs,
        /// Horizontal field of view (degrees).
        #[arg(long, default_value_t = 40.0)]
        fov: f64,
        /// At most this many objects in front of the back wall.
        #[arg(long, default_value_t = 4)]
        max_objects: usize,
        /// Probability of a weakly diffusive sheet in front of the scene.
        #[arg(long, default_value_t = 0.5)]
        sheet_probability: f64,
        /// Add interreflection tails.
        #[arg(long)]
        interreflection: bool,
        /// Ambient light level (relative to the peak voxel).
        #[arg(long, default_value_t = 0.0)]
        ambient: f64,
    },
    /// Fluorescence-lifetime samples (eq. 5) on the heterodyne grid (default K = 8).
    Flim {
        #[command(flatten)]
        common: CommonArgs,
        #[command(flatten)]
        grid: GridArgs,
        /// Decay onset in ns.
        #[arg(long, default_value_t = 2.0)]
        onset_ns: f64,
        /// At most this many cells per image.
        #[arg(long, default_value_t = 8)]
        max_cells: usize,
    },
    /// Import cubes (.npy [T,H,W] or [F,T,H,W]) or depth (+ albedo) maps (.npy or PNG).
    Import {
        /// Transient cube files.
        #[arg(long, num_args = 1.., conflicts_with = "depth")]
        cube: Vec<PathBuf>,
        /// Depth (range) maps; 0 = no return.
        #[arg(long, num_args = 1..)]
        depth: Vec<PathBuf>,
        /// Albedo maps, one per depth map.
        #[arg(long, num_args = 1.., requires = "depth")]
        albedo: Vec<PathBuf>,
        /// Metres per depth-map unit (e.g. 0.001 for millimetre PNGs).
        #[arg(long, default_value_t = 1.0)]
        depth_scale: f64,
        #[command(flatten)]
        grid: GridArgs,
        /// Pixel block the frames must tile.
        #[arg(long, default_value = "2x2", value_parser = super::parse_hw)]
        block: (usize, usize),
        /// Split to import into.
        #[arg(long, default_value = "test")]
        split: String,
        /// Items per shard file.
        #[arg(long, default_value_t = DEFAULT_SHARD)]
        shard_size: usize,
        /// Replace an existing output directory.
        #[arg(long)]
        force: bool,
        /// Output directory.
        #[arg(short, long)]
        output: PathBuf,
    },
    /// Draw one item: intensity, depth or lifetime, and a few waveforms.
    Show {
        /// Dataset directory.
        dir: PathBuf,
        /// Split.
        #[arg(long, default_value = "train")]
        split: String,
        /// Item index within the split.
        #[arg(long, default_value_t = 0)]
        index: usize,
        /// Output PNG.
        #[arg(short, long)]
        output: PathBuf,
    },
}

/// A flag set by Ctrl-C; long work checks it and stops without writing output.
pub fn interrupt_flag() -> Arc<AtomicBool> {
    let flag = Arc::new(AtomicBool::new(false));
    let f = flag.clone();
    // A second handler cannot be installed; then Ctrl-C simply ends the process (outputs are atomic).
    let _ = ctrlc::set_handler(move || f.store(true, Ordering::SeqCst));
    flag
}

fn progress_bar(len: u64, what: &str) -> ProgressBar {
    let pb = ProgressBar::new(len);
    let style = ProgressStyle::with_template("{msg} [{bar:30}] {pos}/{len} {per_sec} eta {eta}")
        .unwrap_or_else(|_| ProgressStyle::default_bar())
        .progress_chars("=> ");
    pb.set_style(style);
    pb.set_message(what.to_string());
    pb
}

fn run_generator(gen: Generator, grid: TimeGrid, c: &CommonArgs) -> Result<()> {
    if c.count == 0 {
        bail!("--count 0: a dataset needs at least 1 item");
    }
    let (h, w) = c.size;
    let (bh, bw) = c.block;
    if bh == 0 || bw == 0 || h % bh != 0 || w % bw != 0 {
        bail!("--size {h}x{w} is not a multiple of the {bh}x{bw} pixel block (--block)");
    }
    let pb = progress_bar(c.count as u64, "generating");
    let cancel = interrupt_flag();
    let progress = || pb.inc(1);
    let t0 = Instant::now();
    let m = store::generate(&gen, &grid, c.count, c.seed, &c.output, &WriteOptions { shard_size: c.shard_size, force: c.force, progress: &progress, cancel: &cancel })?;
    pb.finish_and_clear();
    let counts: Vec<String> = m.splits.iter().map(|s| format!("{} {}", s.count, s.name)).collect();
    println!(
        "wrote {}: {} items ({}), {}x{}, T = {} bins of {:.1} ps, {:.1} items/s",
        c.output.display(),
        c.count,
        counts.join(", "),
        h,
        w,
        m.bins,
        m.bin_width_s * 1e12,
        c.count as f64 / t0.elapsed().as_secs_f64()
    );
    Ok(())
}

pub fn run(cmd: DatasetCmd) -> Result<ExitCode> {
    match cmd {
        DatasetCmd::Lidar { common, grid, fov, max_objects, sheet_probability, interreflection, ambient } => {
            let grid = grid.grid(Sampling::Oversample(1))?;
            let p = LidarParams { height: common.size.0, width: common.size.1, fov_deg: fov, max_objects, sheet_probability, interreflection, ambient };
            run_generator(Generator::Lidar(p), grid, &common)?;
        }
        DatasetCmd::Flim { common, grid, onset_ns, max_cells } => {
            let grid = grid.grid(Sampling::Heterodyne(8))?;
            let p = FlimParams { height: common.size.0, width: common.size.1, onset_s: onset_ns * 1e-9, max_cells };
            run_generator(Generator::Flim(p), grid, &common)?;
        }
        DatasetCmd::Import { cube, depth, albedo, depth_scale, grid, block, split, shard_size, force, output } => {
            let grid = grid.grid(Sampling::Oversample(1))?;
            let source = if !cube.is_empty() {
                Source::Cubes(cube)
            } else if !depth.is_empty() {
                Source::DepthMaps { depth, albedo, depth_scale }
            } else {
                bail!("nothing to import: pass --cube FILE… or --depth FILE… [--albedo FILE…]");
            };
            let m = import::import(&source, &ImportOptions { grid, block, split, shard_size, force }, &output)?;
            let n: usize = m.splits.iter().map(|s| s.count).sum();
            println!("wrote {}: {n} imported items, {}x{}, T = {}", output.display(), m.size[0], m.size[1], m.bins);
        }
        DatasetCmd::Show { dir, split, index, output } => {
            let ds = Dataset::open(&dir)?;
            montage::montage(&ds, &split, index, &output)?;
            println!("wrote {}", output.display());
        }
    }
    Ok(ExitCode::SUCCESS)
}

#[derive(Args)]
pub struct BenchDatasetArgs {
    /// Frame size HxW.
    #[arg(long, default_value = "64x64", value_parser = super::parse_hw)]
    size: (usize, usize),
    /// Items per measurement.
    #[arg(long, default_value_t = 32)]
    count: usize,
}

pub fn bench(a: BenchDatasetArgs) -> Result<()> {
    use rayon::prelude::*;
    let (h, w) = a.size;
    println!("dataset generation, {h}x{w}, {} items, {} threads", a.count, rayon::current_num_threads());
    let cases = [
        ("lidar T=32", Generator::Lidar(LidarParams { height: h, width: w, sheet_probability: 0.5, ..Default::default() }), TimeGrid::default()),
        ("lidar T=128 (K=4)", Generator::Lidar(LidarParams { height: h, width: w, ..Default::default() }), TimeGrid { sampling: Sampling::Oversample(4), ..TimeGrid::default() }),
        ("flim T=256 (het K=8)", Generator::Flim(FlimParams { height: h, width: w, ..Default::default() }), TimeGrid { sampling: Sampling::Heterodyne(8), ..TimeGrid::default() }),
    ];
    for (name, gen, grid) in cases {
        gen.validate(&grid)?;
        let t0 = Instant::now();
        let n: usize = (0..a.count as u64).into_par_iter().map(|i| gen.item(&grid, 1, i).len()).sum();
        let dt = t0.elapsed().as_secs_f64();
        println!("{name:>22}: {:8.1} items/s ({:.2} ms/item, {n} fields)", a.count as f64 / dt, dt * 1e3 / a.count as f64);
    }
    Ok(())
}
