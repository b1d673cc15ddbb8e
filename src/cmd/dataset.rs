//! `tcsense dataset …` and `tcsense bench dataset`.

use anyhow::{bail, Result};
use clap::{Args, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Instant;
use tcsense_datasets::flim::{FlimParams, FlimRandomization};
use tcsense_datasets::import::{self, ImportOptions, Source};
use tcsense_datasets::lidar::{LidarParams, LidarRandomization};
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
        let sampling = Sampling::from_factors(self.oversample, self.heterodyne, default)?;
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

/// A range flag: `LO,HI`, or one value `V` for the fixed setting `V,V`.
fn parse_range(s: &str) -> Result<[f64; 2], String> {
    let bad = || format!("{s:?}: expected LO,HI or one number");
    let v: Vec<f64> = s.split(',').map(|p| p.trim().parse::<f64>().map_err(|_| bad())).collect::<std::result::Result<_, _>>()?;
    match v[..] {
        [a] => Ok([a, a]),
        [a, b] => Ok([a, b]),
        _ => Err(bad()),
    }
}

/// Domain randomisation of the FLIm generator (on by default; `--paper` turns it off). A range
/// flag takes `LO,HI`, or one value to fix the knob.
#[derive(Args, Clone)]
pub struct FlimRandomArgs {
    /// The paper's generator: onset fixed at --onset-ns (default 2 ns), lifetimes in 0.5–1.5,
    /// 1.5–2.5 and 2.5–3.5 ns, no IRF, background or brightness variation.
    #[arg(long)]
    paper: bool,
    /// Decay onset in ns (fixes it; with --paper the default is 2).
    #[arg(long, conflicts_with = "onset_range")]
    onset_ns: Option<f64>,
    /// Onset range as fractions of the code cycle [default: 0,1].
    #[arg(long, value_parser = parse_range)]
    onset_range: Option<[f64; 2]>,
    /// FWHM of the Gaussian instrument response in ns [default: 0,1].
    #[arg(long, value_parser = parse_range)]
    irf_fwhm_ns: Option<[f64; 2]>,
    /// Distinct lifetimes per scene, from LO to HI (1–3) [default: 1,3].
    #[arg(long, value_parser = parse_range)]
    lifetimes: Option<[f64; 2]>,
    /// Lifetime range in ns, log-uniform [default: 0.3,6].
    #[arg(long, value_parser = parse_range)]
    tau_ns: Option<[f64; 2]>,
    /// Background offset as a fraction of the peak [default: 0,0.05].
    #[arg(long, value_parser = parse_range)]
    background: Option<[f64; 2]>,
    /// Brightness factor, log-uniform [default: 0.01,1].
    #[arg(long, value_parser = parse_range)]
    brightness: Option<[f64; 2]>,
}

impl FlimRandomArgs {
    fn params(&self, height: usize, width: usize, max_cells: usize, grid: &TimeGrid) -> Result<FlimParams> {
        let knobs = [
            self.onset_range.is_some(),
            self.irf_fwhm_ns.is_some(),
            self.lifetimes.is_some(),
            self.tau_ns.is_some(),
            self.background.is_some(),
            self.brightness.is_some(),
        ];
        if self.paper && knobs.iter().any(|&k| k) {
            bail!("--paper fixes every knob but the onset (--onset-ns); drop --paper to set ranges");
        }
        let mut p = FlimParams { height, width, max_cells, ..FlimParams::paper() };
        if self.paper {
            p.onset_s = self.onset_ns.unwrap_or(2.0) * 1e-9;
            return Ok(p);
        }
        let d = FlimRandomization::default();
        let ns = |r: [f64; 2]| [r[0] * 1e-9, r[1] * 1e-9];
        let onset_cycle = match (self.onset_ns, self.onset_range) {
            (Some(t), _) => [t * 1e-9 / grid.cycle_s(); 2],
            (None, Some(r)) => r,
            (None, None) => d.onset_cycle,
        };
        let lifetimes = match self.lifetimes {
            Some(r) if r.iter().all(|v| v.fract() == 0.0 && *v >= 0.0) => [r[0] as usize, r[1] as usize],
            Some(r) => bail!("--lifetimes {r:?}: expected whole numbers from 1 to 3"),
            None => d.lifetimes,
        };
        p.randomization = Some(FlimRandomization {
            onset_cycle,
            irf_fwhm_s: self.irf_fwhm_ns.map(ns).unwrap_or(d.irf_fwhm_s),
            lifetimes,
            tau_s: self.tau_ns.map(ns).unwrap_or(d.tau_s),
            background: self.background.unwrap_or(d.background),
            brightness: self.brightness.unwrap_or(d.brightness),
        });
        Ok(p)
    }
}

/// Domain randomisation of the LiDAR generator (on by default; `--paper` turns it off). A
/// range flag takes `LO,HI`, or one value to fix the knob.
#[derive(Args, Clone)]
pub struct LidarRandomArgs {
    /// The generator without randomisation: walls within 70–90 % of the range, checker
    /// textures, boxes and spheres, fixed sheet ranges.
    #[arg(long)]
    paper: bool,
    /// Back-wall distance (farthest corner) as fractions of the unambiguous range [default: 0.3,0.97].
    #[arg(long, value_parser = parse_range)]
    wall_range: Option<[f64; 2]>,
    /// Object distances as fractions of the wall's [default: 0.1,0.9].
    #[arg(long, value_parser = parse_range)]
    object_range: Option<[f64; 2]>,
    /// Probability of a fractal-noise texture instead of checkers [default: 0.7].
    #[arg(long)]
    noise_texture: Option<f64>,
    /// At most this many slanted disks per scene [default: 3].
    #[arg(long)]
    max_slopes: Option<usize>,
    /// Sheet transmittance per pass [default: 0.3,0.95].
    #[arg(long, value_parser = parse_range)]
    sheet_transmission: Option<[f64; 2]>,
    /// Sheet reflectance, log-uniform [default: 0.001,0.05].
    #[arg(long, value_parser = parse_range)]
    sheet_reflectance: Option<[f64; 2]>,
    /// Sheet distance as fractions of the nearest surface's [default: 0.15,0.85].
    #[arg(long, value_parser = parse_range)]
    sheet_distance: Option<[f64; 2]>,
    /// Extra ambient level [default: 0,0.02].
    #[arg(long, value_parser = parse_range)]
    ambient_range: Option<[f64; 2]>,
    /// Interreflection fraction κ of an object's return, log-uniform [default: 0.02,0.3].
    #[arg(long, value_parser = parse_range)]
    interreflection_strength: Option<[f64; 2]>,
}

impl LidarRandomArgs {
    fn randomization(&self) -> Result<Option<LidarRandomization>> {
        let d = LidarRandomization::default();
        let set = [
            self.wall_range.is_some(),
            self.object_range.is_some(),
            self.noise_texture.is_some(),
            self.max_slopes.is_some(),
            self.sheet_transmission.is_some(),
            self.sheet_reflectance.is_some(),
            self.sheet_distance.is_some(),
            self.ambient_range.is_some(),
            self.interreflection_strength.is_some(),
        ];
        if self.paper {
            if set.iter().any(|&k| k) {
                bail!("--paper fixes every knob; drop it to set ranges");
            }
            return Ok(None);
        }
        Ok(Some(LidarRandomization {
            wall_range: self.wall_range.unwrap_or(d.wall_range),
            object_range: self.object_range.unwrap_or(d.object_range),
            noise_texture: self.noise_texture.unwrap_or(d.noise_texture),
            max_slopes: self.max_slopes.unwrap_or(d.max_slopes),
            sheet_transmission: self.sheet_transmission.unwrap_or(d.sheet_transmission),
            sheet_reflectance: self.sheet_reflectance.unwrap_or(d.sheet_reflectance),
            sheet_distance: self.sheet_distance.unwrap_or(d.sheet_distance),
            ambient: self.ambient_range.unwrap_or(d.ambient),
            interreflection: self.interreflection_strength.unwrap_or(d.interreflection),
            ..d
        }))
    }
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
        #[command(flatten)]
        random: LidarRandomArgs,
    },
    /// Fluorescence-lifetime samples (eq. 5) on the heterodyne grid (default K = 8).
    Flim {
        #[command(flatten)]
        common: CommonArgs,
        #[command(flatten)]
        grid: GridArgs,
        /// At most this many cells per image.
        #[arg(long, default_value_t = 8)]
        max_cells: usize,
        #[command(flatten)]
        random: FlimRandomArgs,
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
    let m = store::generate(
        &gen,
        &grid,
        c.count,
        c.seed,
        &c.output,
        &WriteOptions { shard_size: c.shard_size, force: c.force, progress: &progress, cancel: &cancel },
    )?;
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
        DatasetCmd::Lidar { common, grid, fov, max_objects, sheet_probability, interreflection, ambient, random } => {
            let grid = grid.grid(Sampling::Oversample(1))?;
            let p = LidarParams {
                height: common.size.0,
                width: common.size.1,
                fov_deg: fov,
                max_objects,
                sheet_probability,
                interreflection,
                ambient,
                randomization: random.randomization()?,
            };
            run_generator(Generator::Lidar(p), grid, &common)?;
        }
        DatasetCmd::Flim { common, grid, max_cells, random } => {
            let grid = grid.grid(Sampling::Heterodyne(8))?;
            let p = random.params(common.size.0, common.size.1, max_cells, &grid)?;
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
        (
            "lidar T=32",
            Generator::Lidar(LidarParams { height: h, width: w, sheet_probability: 0.5, ..Default::default() }),
            TimeGrid::default(),
        ),
        (
            "lidar T=128 (K=4)",
            Generator::Lidar(LidarParams { height: h, width: w, ..Default::default() }),
            TimeGrid { sampling: Sampling::Oversample(4), ..TimeGrid::default() },
        ),
        (
            "flim T=256 (het K=8)",
            Generator::Flim(FlimParams { height: h, width: w, ..Default::default() }),
            TimeGrid { sampling: Sampling::Heterodyne(8), ..TimeGrid::default() },
        ),
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
