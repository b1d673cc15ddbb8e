//! `tcsense reconstruct …`, `depth`, `lifetime`, `plot`.

use anyhow::{bail, Context, Result};
use clap::{Args, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};
use ndarray::{Array4, ArrayD, Axis, Ix3};
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use tcsense_infer::figures;
use tcsense_infer::products::{depth_map, plot_waveforms, write_ply, PeakOptions};
use tcsense_infer::registry::{entry_name, names, DecoderSettings, Registry};
use tcsense_models::decoder::{Control, Decoder, Step};
use tcsense_models::{TvNorm, Tval3Options};
use tcsense_sensor::npy::{write_bytes, write_npy};
use tcsense_sensor::output::Outputs;

use super::dataset::interrupt_flag;
use super::sensor::{ResponseArgs, SensorArgs};

/// TVAL3 options (defaults: the paper's §IV settings).
#[derive(Args, Clone)]
pub struct Tval3Args {
    /// Penalty of the data term (final value).
    #[arg(long, default_value_t = 512.0)]
    pub mu: f64,
    /// Penalty of Du = w (final value).
    #[arg(long, default_value_t = 32.0)]
    pub beta: f64,
    /// Initial mu of the continuation (default: mu).
    #[arg(long)]
    pub mu0: Option<f64>,
    /// Initial beta of the continuation (default: beta).
    #[arg(long)]
    pub beta0: Option<f64>,
    /// Outer tolerance.
    #[arg(long, default_value_t = 1e-6)]
    pub tol: f64,
    /// Inner tolerance.
    #[arg(long, default_value_t = 1e-3)]
    pub tol_inn: f64,
    /// Maximal total iterations.
    #[arg(long, default_value_t = 200)]
    pub maxit: usize,
    /// Maximal outer iterations.
    #[arg(long, default_value_t = 10)]
    pub maxcnt: usize,
    /// TV norm: 1 anisotropic, 2 isotropic.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u8).range(1..=2))]
    pub tv_norm: u8,
    /// Allow negative values (TVAL3's nonneg = false).
    #[arg(long)]
    pub allow_negative: bool,
    /// TV weights over (t, y, x), e.g. 1,1,1.
    #[arg(long, default_value = "1,1,1")]
    pub tv_weights: String,
}

impl Tval3Args {
    pub fn options(&self) -> Result<Tval3Options> {
        let w: Vec<f64> = self
            .tv_weights
            .split(',')
            .map(|s| s.trim().parse::<f64>())
            .collect::<std::result::Result<_, _>>()
            .ok()
            .filter(|v: &Vec<f64>| v.len() == 3)
            .with_context(|| format!("--tv-weights {:?}: expected three numbers t,y,x (e.g. 1,1,1)", self.tv_weights))?;
        let o = Tval3Options {
            mu: self.mu,
            beta: self.beta,
            mu0: self.mu0,
            beta0: self.beta0,
            tol: self.tol,
            tol_inn: self.tol_inn,
            maxit: self.maxit,
            maxcnt: self.maxcnt,
            nonneg: !self.allow_negative,
            tv_norm: if self.tv_norm == 2 { TvNorm::Isotropic } else { TvNorm::Anisotropic },
            weights: [w[0], w[1], w[2]],
            ..Default::default()
        };
        o.validate()?;
        Ok(o)
    }
}

/// Settings of the tap-domain lifetime fit (`tcsense_fits::lifetime_taps`).
#[derive(Args, Clone)]
pub struct TapFitArgs {
    /// The decay onset in ns when known (e.g. from a calibration); default: fitted to each frame.
    #[arg(long)]
    pub onset_ns: Option<f64>,
    /// Side of the square window of pixels whose fit costs are summed (odd; 1: every pixel
    /// alone) [default: 3]
    #[arg(long)]
    pub window: Option<usize>,
    /// Lifetimes searched, LO,HI in ns [default: 0.1,25]
    #[arg(long)]
    pub tau_ns: Option<String>,
    /// Pixels below this fraction of the brightest pixel's charge get no lifetime [default: 0.02]
    #[arg(long)]
    pub min_intensity: Option<f32>,
    /// No background term (when the scene is known to have none).
    #[arg(long)]
    pub no_background: bool,
}

impl TapFitArgs {
    /// The fit's window side (`--window`, else the fit's default, 3).
    pub fn window(&self) -> usize {
        self.window.unwrap_or(tcsense_fits::lifetime_taps::TapFitOptions::default().window)
    }

    /// The first of the lifetime fit's own flags given (`--window` only where `window_too`
    /// is false: the range fit takes it as well), for a decoder that takes none of them.
    fn given_besides_onset(&self, window_too: bool) -> Option<&'static str> {
        [
            (window_too && self.window.is_some(), "--window"),
            (self.tau_ns.is_some(), "--tau-ns"),
            (self.min_intensity.is_some(), "--min-intensity"),
            (self.no_background, "--no-background"),
        ]
        .into_iter()
        .find_map(|(given, flag)| given.then_some(flag))
    }

    pub fn options(&self) -> Result<tcsense_fits::lifetime_taps::TapFitOptions> {
        let tau_ns = self.tau_ns.as_deref().unwrap_or("0.1,25");
        let r: Vec<f64> = tau_ns
            .split(',')
            .map(|s| s.trim().parse::<f64>())
            .collect::<std::result::Result<_, _>>()
            .ok()
            .filter(|v: &Vec<f64>| v.len() == 2)
            .with_context(|| format!("--tau-ns {tau_ns:?}: expected LO,HI in ns (e.g. 0.1,25)"))?;
        let o = tcsense_fits::lifetime_taps::TapFitOptions {
            tau_range_s: [r[0] * 1e-9, r[1] * 1e-9],
            window: self.window(),
            min_intensity: self.min_intensity.unwrap_or(tcsense_fits::lifetime_taps::TapFitOptions::default().min_intensity),
            onset_s: self.onset_ns.map(|t| t * 1e-9),
            background: !self.no_background,
            ..Default::default()
        };
        if let Err(e) = o.validate() {
            bail!("lifetime fit settings (--onset-ns, --window, --tau-ns, --min-intensity): {e}");
        }
        Ok(o)
    }
}

/// `tcsense reconstruct DECODER …`: any decoder of the registry
/// ([`tcsense_infer::registry`]) on a file of tap images, through one path.
#[derive(Args)]
pub struct ReconstructArgs {
    /// The decoder, by its registry name: `tval3` (cubes), `depth-fit[:K]` (ranges fitted to
    /// the taps, K = 1 or 2 returns), `lifetime-fit` (lifetimes fitted to the taps),
    /// `admm-net:RUN`, `unet:RUN` (ranges refined in the tap domain), `unet-raw:RUN`,
    /// `lifetime:RUN` (training runs; `admm-net --run RUN` is the same), `zoo:NAME`,
    /// `onnx:MODEL.onnx`; a decoder of cubes followed by `+fit` also gives ranges. The list
    /// follows.
    pub decoder: String,
    /// A learned decoder's run directory or zoo entry (`zoo:NAME`), for DECODER `admm-net`,
    /// `unet`, `unet-raw` or `lifetime`.
    #[arg(long, value_parser = super::parse_run)]
    pub run: Option<PathBuf>,
    /// Tap images .npy, [M, H, W] or [B, M, H, W].
    #[arg(long)]
    pub measurements: PathBuf,
    /// Output .npy: the cube [T, H, W], depth [K, H, W] (m, NaN where none; the confidence
    /// next to it, `OUTPUT.confidence.npy`) or lifetimes [4, H, W] (τ_m, τ₁, τ₂ in s, α₁; the
    /// confidence and intensity next to it), with a leading B for a batch.
    #[arg(short, long)]
    pub output: PathBuf,
    /// Codes JSON file: the sensor of the decoders of any sensor (tval3, the fits). A learned
    /// decoder or an exported model brings its own.
    #[arg(long)]
    pub codes: Option<PathBuf>,
    #[command(flatten)]
    pub response: ResponseArgs,
    /// A calibration directory (`tcsense calibrate`): correct the tap images for its dark and
    /// gain maps and decode with its matrix (checked against the decoder's codes).
    #[arg(long, value_name = "DIR")]
    pub calibration: Option<PathBuf>,
    #[command(flatten)]
    pub tval3: Tval3Args,
    #[command(flatten)]
    pub fit: TapFitArgs,
    /// Returns per pixel of `depth-fit`: 1, or 2 (a second where the taps call for it).
    #[arg(long)]
    pub returns: Option<usize>,
    /// The U-Net's own ranges, without the fit of the pulse template to the tap images
    /// (`unet --run RUN --no-range-fit` is `unet-raw:RUN`).
    #[arg(long)]
    pub no_range_fit: bool,
    #[command(flatten)]
    pub products: DepthProductArgs,
    /// What a tap clipped at the full well reads, in the tap images' units (an ADC's full
    /// scale; `simulate` records its own in `y.meta.json`, used when this is not given):
    /// pixels with a tap at it get no range and no lifetime.
    #[arg(long, value_parser = super::number_in(1e-30, 1e30))]
    pub clip_level: Option<f64>,
    #[command(flatten)]
    pub device: super::DeviceArgs,
}

impl ReconstructArgs {
    /// The registry name: DECODER, with `--run` and `--no-range-fit` folded in.
    fn name(&self) -> Result<String> {
        let kinds = [names::ADMM_NET, names::UNET, names::UNET_RAW, names::LIFETIME];
        let name = match &self.run {
            Some(run) if kinds.contains(&self.decoder.as_str()) => format!("{}:{}", self.decoder, run.display()),
            Some(_) => bail!("--run: {:?} takes no run; --run goes with admm-net, unet, unet-raw or lifetime", self.decoder),
            None => self.decoder.clone(),
        };
        if !self.no_range_fit {
            return Ok(name);
        }
        match name.strip_prefix("unet:") {
            Some(run) => Ok(format!("{}:{run}", names::UNET_RAW)),
            None => bail!("--no-range-fit: {name:?} is not a U-Net run (unet --run RUN)"),
        }
    }

    /// The settings of the decoder `name` from the flags (only its own are checked; the
    /// others keep their defaults).
    fn settings(&self, name: &str) -> Result<DecoderSettings> {
        let mut s = DecoderSettings::default();
        let entry = entry_name(name);
        if entry == names::TVAL3 {
            s.tval3 = self.tval3.options()?;
        }
        let lifetime_fit = entry == names::LIFETIME_FIT || entry == names::LIFETIME_FIT_POOLED;
        let depth_fit = entry == names::DEPTH_FIT || entry == names::DEPTH_FIT_POOLED;
        if lifetime_fit {
            s.tap_fit = self.fit.options()?;
        } else {
            if let Some(flag) = self.fit.given_besides_onset(!depth_fit) {
                bail!(
                    "{flag}: a setting of the fit of lifetimes to the taps (lifetime-fit, lifetime-fit-pooled){}; {name} does not take it",
                    if flag == "--window" { " and of depth-fit" } else { "" }
                );
            }
            if let Some(t) = self.fit.onset_ns {
                // a lifetime network on the fit's evidence takes it (the registry refuses any other run)
                if !names::fits_onset(entry) {
                    bail!(
                        "--onset-ns: for the lifetime fits and a lifetime network on the fit's evidence (lifetime:RUN, zoo:NAME; or `tcsense infer --onset-ns` on its exported model); {name} fits no onset"
                    );
                }
                s.tap_fit.onset_s = Some(t * 1e-9);
                if let Err(e) = s.tap_fit.validate() {
                    bail!("--onset-ns {t}: {e}");
                }
            }
        }
        if depth_fit {
            s.depth_fit.fit.window = self.fit.window();
            if let Some(r) = self.returns {
                s.depth_fit.returns = r;
            }
        }
        Ok(s)
    }
}

/// The registry's decoders, one per line, for `reconstruct --help`.
pub fn decoder_listing() -> String {
    format!("Decoders:\n{}", Registry::builtin().listing())
}

pub fn reconstruct(a: ReconstructArgs) -> Result<ExitCode> {
    let name = a.name()?;
    let depth_fit = [names::DEPTH_FIT, names::DEPTH_FIT_POOLED].contains(&entry_name(&name));
    if a.returns.is_some() && !depth_fit {
        bail!("--returns: {name:?} is not depth-fit or depth-fit-pooled (its returns are fixed by its training)");
    }
    let opened = Registry::builtin().open(&name, &a.settings(&name)?, &a.device.device()?)?;
    let sensor = match (opened.sensor, &a.codes) {
        (Some(_), Some(_)) => bail!("--codes: {name} brings its own sensor (the codes it was trained for); drop --codes"),
        (Some(own), None) => {
            if let Some(flag) = a.response.given() {
                bail!(
                    "{flag}: {name} brings its own sensor (the codes, time grid and instrument response it was trained for); drop {flag} (a measured sensor: --calibration DIR)"
                );
            }
            match &a.calibration {
                Some(dir) => own.calibrated_from(dir)?,
                None => own,
            }
        }
        (None, Some(codes)) => {
            SensorArgs { codes: codes.clone(), response: a.response.clone(), calibration: a.calibration.clone() }.sensor()?
        }
        (None, None) => bail!("--codes: {name} decodes any sensor; give the codes the tap images were taken with"),
    };
    if depth_fit {
        if let Some(w) = tcsense_infer::fitted::alias_warning(sensor.nominal(), sensor.codes().length()) {
            eprintln!("{w}");
        }
    }
    let mut decoder = opened.decoder;
    // the clip level: given, else the one a simulation recorded beside the measurements
    let clip_level = match a.clip_level {
        Some(v) => Some(v as f32),
        None => tcsense_sensor::sidecar::Sidecar::read_for(&a.measurements)?.and_then(|s| s.clip_level),
    };
    decode_file(decoder.as_mut(), &sensor, &a.measurements, &a.output, &a.products, clip_level)
}

/// Decode the tap images in `measurements` (`[M, H, W]` or a batch `[B, M, H, W]`) with any
/// decoder on `sensor` ([`tcsense_infer::decode::decode_file`]) with a progress bar, print what
/// was written and draw the products asked for.
fn decode_file(
    decoder: &mut dyn Decoder,
    sensor: &tcsense_sensor::Sensor,
    measurements: &Path,
    output: &Path,
    products: &DepthProductArgs,
    clip_level: Option<f32>,
) -> Result<ExitCode> {
    // every output checked before any work: distinct, not a directory, writable; all of them
    // appear together once the last is written
    let [confidence, intensity, depth] = tcsense_infer::decode::companions(output);
    let mut planned: Vec<(&str, &Path)> =
        vec![("-o", output), ("-o's confidence", &confidence), ("-o's intensity", &intensity), ("-o's depth", &depth)];
    if let Some(p) = &products.ply {
        planned.push(("--ply", p));
    }
    if let Some(p) = &products.png {
        planned.push(("--png", p));
    }
    let mut outputs = Outputs::plan(&planned)?;
    let cancel = interrupt_flag();
    let pb = ProgressBar::new(1);
    pb.set_style(
        ProgressStyle::with_template("{msg} [{bar:30}] {pos}/{len} eta {eta}")
            .unwrap_or_else(|_| ProgressStyle::default_bar())
            .progress_chars("=> "),
    );
    pb.set_message(decoder.name().to_string());
    let progress = |s: Step| {
        pb.set_length((s.frames * s.total.max(1)) as u64);
        pb.set_position((s.frame * s.total.max(1) + s.done) as u64);
    };
    let out = tcsense_infer::decode::decode_file(
        decoder,
        sensor,
        measurements,
        output,
        &Control { cancel: &cancel, progress: &progress },
        &mut outputs,
        clip_level,
    );
    pb.finish_and_clear();
    let out = match out {
        Err(tcsense_infer::InferError::Cancelled) => bail!("interrupted; {} was not written", output.display()),
        r => r?,
    };
    let name = decoder.name();
    let time = human_time(out.seconds_per_frame);
    let shape = |a: &Array4<f32>| -> Vec<usize> {
        if out.batched {
            a.shape().to_vec()
        } else {
            a.shape()[1..].to_vec()
        }
    };
    let d = &out.decoded;
    let mut lines = Vec::new();
    if out.clipped > 0 {
        lines.push(format!("{} pixels with a tap clipped at the full well: no range or lifetime there", out.clipped));
    }
    if let Some(cube) = &d.cube {
        lines.push(format!("wrote {}: x̂ {:?} ({time} per frame, {name})", output.display(), shape(cube)));
    } else if let Some(lifetime) = &d.lifetime {
        let first = lifetime.index_axis(Axis(0), 0);
        let tau_m: Vec<f64> = first.index_axis(Axis(0), 0).iter().filter(|v| v.is_finite()).map(|&v| v as f64).collect();
        let found = match tau_m.len() {
            0 => "no pixel with a fluorophore".to_string(),
            n => format!("{n} pixels with a fluorophore, mean τ_m {:.3} ns", tau_m.iter().sum::<f64>() / n as f64 * 1e9),
        };
        lines.push(format!(
            "wrote {}, {} and {}: lifetimes {:?}, {found} (first frame) ({time} per frame, {name})",
            out.written[0].display(),
            out.written[1].display(),
            out.written[2].display(),
            shape(lifetime),
        ));
        if let Some(p) = &products.png {
            figures::map(
                &outputs.stage(p)?,
                &format!("Fluorescence lifetime ({name})"),
                &first.index_axis(Axis(0), 0).mapv(|t| t * 1e9).view(),
                "lifetime τ_m (ns)",
            )?;
            lines.push(format!("wrote {}", p.display()));
        }
    }
    // ranges, from a decoder of depth or beside a cube (`NAME+fit`), and their products
    match (&d.depth, &d.confidence, &d.lifetime) {
        (Some(depth), Some(confidence), None) => {
            // the depth file and its confidence follow the cube where there is one
            let at = usize::from(d.cube.is_some());
            let (first_d, first_c) = (depth.index_axis(Axis(0), 0), confidence.index_axis(Axis(0), 0));
            let found: Vec<usize> = first_d.outer_iter().map(|d| d.iter().filter(|v| v.is_finite()).count()).collect();
            lines.push(format!(
                "wrote {} and {}: depth {:?}, returns per bounce {found:?} (first frame) ({time} per frame, {name})",
                out.written[at].display(),
                out.written[at + 1].display(),
                shape(depth)
            ));
            if let Some(p) = &products.ply {
                let n = write_ply(&outputs.stage(p)?, &first_d, &first_c, products.fov)?;
                lines.push(format!("wrote {}: {n} points", p.display()));
            }
            if let Some(p) = &products.png {
                figures::map(
                    &outputs.stage(p)?,
                    &format!("Range of the first return ({name})"),
                    &first_d.index_axis(Axis(0), 0),
                    "range (m)",
                )?;
                lines.push(format!("wrote {}", p.display()));
            }
        }
        // a product asked for that this decoder does not give: refused, nothing written
        _ if products.ply.is_some() || (products.png.is_some() && d.lifetime.is_none()) => {
            bail!("--ply/--png: {name} gives no ranges (a cube only); name it {name}+fit for the ranges of its peaks")
        }
        _ => {}
    }
    outputs.commit()?;
    for l in lines {
        println!("{l}");
    }
    Ok(ExitCode::SUCCESS)
}

/// `12.3 ms` or `1.23 s`.
fn human_time(seconds: f64) -> String {
    if seconds < 1.0 {
        format!("{:.1} ms", seconds * 1e3)
    } else {
        format!("{seconds:.2} s")
    }
}

/// Time-grid flags for products: Δt = T_c / K with K = T / L.
#[derive(Args, Clone)]
pub struct BinArgs {
    /// Masks per cycle L (the oversampling/heterodyne factor is K = T / L).
    #[arg(long, default_value_t = 32)]
    pub length: usize,
    /// Code clock in MHz (1 to 10 000).
    #[arg(long, default_value_t = 607.0, value_parser = super::number_in(1.0, 10_000.0))]
    pub clock_mhz: f64,
    /// Bin width in ps (overrides --length/--clock-mhz; 0.01 to 1 000 000).
    #[arg(long, value_parser = super::number_in(0.01, 1e6))]
    pub bin_width_ps: Option<f64>,
}

impl BinArgs {
    fn bin_width(&self, t: usize, file: &Path) -> Result<f64> {
        // (--bin-width-ps and --clock-mhz are bounded by their parsers)
        if let Some(ps) = self.bin_width_ps {
            return Ok(ps * 1e-12);
        }
        if self.length == 0 || t % self.length != 0 {
            bail!(
                "{}: {t} time bins are not a multiple of L = {} (--length); pass --length or --bin-width-ps",
                file.display(),
                self.length
            );
        }
        Ok(1.0 / (self.clock_mhz * 1e6) / (t / self.length) as f64)
    }
}

/// A cube `[T, H, W]`, or the first of a batch `[B, T, H, W]`.
fn read_cube3(path: &Path) -> Result<ndarray::Array3<f32>> {
    let (_, mut cubes) = read_cubes(path)?;
    Ok(cubes.swap_remove(0))
}

/// A cube `[T, H, W]`, or a batch `[B, T, H, W]` as `B` cubes (`batched` = true).
fn read_cubes(path: &Path) -> Result<(bool, Vec<ndarray::Array3<f32>>)> {
    let a = tcsense_sensor::npy::read_cube(path, true)?;
    if a.ndim() == 3 {
        return Ok((false, vec![a.into_dimensionality::<Ix3>()?]));
    }
    let cubes = a.axis_iter(Axis(0)).map(|c| c.to_owned().into_dimensionality::<Ix3>()).collect::<std::result::Result<_, _>>()?;
    Ok((true, cubes))
}

/// Stack per-item outputs back into a batch when the input was one.
fn stack_out<D: ndarray::Dimension>(batched: bool, items: Vec<ndarray::Array<f32, D>>) -> Result<ArrayD<f32>> {
    let views: Vec<_> = items.iter().map(|a| a.view()).collect();
    Ok(if batched { ndarray::stack(Axis(0), &views)?.into_dyn() } else { items.into_iter().next().context("no cube")?.into_dyn() })
}

#[derive(Args)]
pub struct DepthArgs {
    /// Reconstructed cube .npy [T, H, W] (or a batch [B, T, H, W]).
    cube: PathBuf,
    #[command(flatten)]
    bins: BinArgs,
    /// Returns per pixel (multipath bounces, 1 to 16).
    #[arg(long, default_value_t = 2, value_parser = super::count_in(1, 16))]
    peaks: usize,
    /// Ignore peaks below this fraction of the pixel's maximum (0 to 1).
    #[arg(long, default_value_t = 0.1, value_parser = super::number_in(0.0, 1.0))]
    min_rel: f64,
    /// Minimal separation of two returns (bins).
    #[arg(long, default_value_t = 2)]
    min_sep: usize,
    /// Output range map .npy [K, H, W] (m, NaN where no return).
    #[arg(short, long)]
    output: PathBuf,
    #[command(flatten)]
    products: DepthProductArgs,
}

/// Pictures of a range map beside it.
#[derive(Args, Clone)]
pub struct DepthProductArgs {
    /// Also write a point cloud of the (first) frame (PLY).
    #[arg(long)]
    ply: Option<PathBuf>,
    /// Horizontal field of view of the camera for the point cloud (degrees, 1 to 179).
    #[arg(long, default_value_t = 40.0, value_parser = super::number_in(1.0, 179.0))]
    fov: f64,
    /// Also write a PNG of the (first) frame's first return.
    #[arg(long)]
    png: Option<PathBuf>,
}

impl Default for DepthProductArgs {
    fn default() -> Self {
        DepthProductArgs { ply: None, fov: 40.0, png: None }
    }
}

pub fn depth(a: DepthArgs) -> Result<ExitCode> {
    if a.peaks == 0 {
        bail!("--peaks 0: at least one return per pixel");
    }
    let mut planned: Vec<(&str, &Path)> = vec![("-o", &a.output)];
    planned.extend(a.products.ply.as_deref().map(|p| ("--ply", p)));
    planned.extend(a.products.png.as_deref().map(|p| ("--png", p)));
    let mut outputs = Outputs::plan(&planned)?;
    let (batched, cubes) = read_cubes(&a.cube)?;
    let dt = a.bins.bin_width(cubes[0].dim().0, &a.cube)?;
    let opts = PeakOptions { max_peaks: a.peaks, min_rel: a.min_rel as f32, min_sep: a.min_sep };
    let maps: Vec<_> = cubes.iter().map(|x| depth_map(&x.view(), dt, &opts)).collect();
    if batched && maps.len() > 1 && (a.products.ply.is_some() || a.products.png.is_some()) {
        bail!("{}: --ply and --png take a single cube; this batch holds {}", a.cube.display(), maps.len());
    }
    let out = stack_out(batched, maps.iter().map(|m| m.0.clone()).collect())?;
    write_npy(&outputs.stage(&a.output)?, &out.view())?;
    let (d, amp) = &maps[0];
    let found: Vec<usize> = (0..a.peaks).map(|b| d.index_axis(Axis(0), b).iter().filter(|v| v.is_finite()).count()).collect();
    let mut lines = vec![format!(
        "wrote {}: range map {:?}, returns per bounce {found:?} (first cube), bin width {:.1} ps",
        a.output.display(),
        out.shape(),
        dt * 1e12
    )];
    if let Some(p) = &a.products.ply {
        let n = write_ply(&outputs.stage(p)?, &d.view(), &amp.view(), a.products.fov)?;
        lines.push(format!("wrote {}: {n} points", p.display()));
    }
    if let Some(p) = &a.products.png {
        figures::map(&outputs.stage(p)?, "Range of the first return (peak detection)", &d.index_axis(Axis(0), 0), "range (m)")?;
        lines.push(format!("wrote {}", p.display()));
    }
    outputs.commit()?;
    lines.iter().for_each(|l| println!("{l}"));
    Ok(ExitCode::SUCCESS)
}

#[derive(Args)]
pub struct LifetimeArgs {
    /// Reconstructed cube .npy [T, H, W] (or a batch [B, T, H, W]), one code cycle.
    cube: PathBuf,
    #[command(flatten)]
    bins: BinArgs,
    /// FWHM of the Gaussian instrument response in ns (default: fitted to the frame).
    #[arg(long, conflicts_with = "irf")]
    irf_fwhm_ns: Option<f64>,
    /// A measured instrument response .npy [T] (one value per bin; its position is fitted).
    #[arg(long)]
    irf: Option<PathBuf>,
    /// Exponentials per pixel: 1, 2, or auto (two where the Akaike criterion asks for them).
    #[arg(long, default_value = "auto")]
    components: String,
    /// Skip pixels whose total signal is below this fraction of the brightest pixel's.
    #[arg(long, default_value_t = 0.02)]
    min_intensity: f32,
    /// Output mean-lifetime map .npy [H, W] (s, amplitude-weighted; NaN where no fit).
    #[arg(short, long)]
    output: PathBuf,
    /// Also write the components .npy [4, H, W]: τ_m, τ₁ ≤ τ₂ (s) and the fraction α₁ of τ₁.
    #[arg(long)]
    components_out: Option<PathBuf>,
    /// Also write the IRF-referenced phasor .npy [2, H, W] (g, s).
    #[arg(long)]
    phasor: Option<PathBuf>,
    /// Also write a PNG of the lifetime map.
    #[arg(long)]
    png: Option<PathBuf>,
}

pub fn lifetime(a: LifetimeArgs) -> Result<ExitCode> {
    use tcsense_fits::lifetime_cube::{fit_cube, Components, FitOptions, IrfModel};
    let mut planned: Vec<(&str, &Path)> = vec![("-o", &a.output)];
    planned.extend(a.components_out.as_deref().map(|p| ("--components-out", p)));
    planned.extend(a.phasor.as_deref().map(|p| ("--phasor", p)));
    planned.extend(a.png.as_deref().map(|p| ("--png", p)));
    let mut outputs = Outputs::plan(&planned)?;
    let (batched, cubes) = read_cubes(&a.cube)?;
    let t = cubes[0].dim().0;
    let dt = a.bins.bin_width(t, &a.cube)?;
    if batched && cubes.len() > 1 && a.png.is_some() {
        bail!("{}: --png takes a single cube; this batch holds {}", a.cube.display(), cubes.len());
    }
    let components = match a.components.as_str() {
        "1" => Components::One,
        "2" => Components::Two,
        "auto" => Components::Auto,
        other => bail!("--components {other:?}: expected 1, 2 or auto"),
    };
    if !(0.0..1.0).contains(&a.min_intensity) {
        bail!("--min-intensity {}: expected a fraction in [0, 1)", a.min_intensity);
    }
    let irf = match (&a.irf, a.irf_fwhm_ns) {
        (Some(p), _) => {
            let v = tcsense_sensor::npy::read_npy(p)?;
            if v.shape() != [t] || v.iter().any(|x| !x.is_finite() || *x < 0.0) || v.iter().all(|&x| x == 0.0) {
                bail!(
                    "{}: the IRF has shape {:?}; expected [{t}] non-negative finite values, not all zero (one per bin of the cube)",
                    p.display(),
                    v.shape()
                );
            }
            IrfModel::Measured(v.iter().map(|&x| x as f64).collect())
        }
        (None, Some(w)) if w.is_finite() && w >= 0.0 && w * 1e-9 <= tcsense_sensor::params::MAX_RESPONSE_S => {
            IrfModel::Gaussian(Some(w * 1e-9))
        }
        (None, Some(w)) => bail!("--irf-fwhm-ns {w}: expected a width ≥ 0 and at most 1000 ns"),
        (None, None) => IrfModel::Gaussian(None),
    };
    let opts = FitOptions { irf, components, min_intensity: a.min_intensity, ..Default::default() };
    let fits: Vec<_> = cubes.iter().map(|x| fit_cube(&x.view(), dt, &opts)).collect();
    let taus: Vec<_> = fits.iter().map(|f| f.lifetimes.index_axis(Axis(0), 0).to_owned()).collect();
    write_npy(&outputs.stage(&a.output)?, &stack_out(batched, taus.clone())?.view())?;
    let tau = &taus[0];
    let fit: Vec<f32> = tau.iter().copied().filter(|v| v.is_finite()).collect();
    let mean = fit.iter().map(|&v| v as f64).sum::<f64>() / fit.len().max(1) as f64;
    let mut lines = vec![format!(
        "wrote {}: {} pixels fitted, mean lifetime {:.3} ns (onset {:.3} ns, IRF FWHM {:.3} ns)",
        a.output.display(),
        fit.len(),
        mean * 1e9,
        fits[0].onset_s * 1e9,
        fits[0].irf_fwhm_s * 1e9
    )];
    if let Some(p) = &a.components_out {
        write_npy(&outputs.stage(p)?, &stack_out(batched, fits.iter().map(|f| f.lifetimes.clone()).collect())?.view())?;
        lines.push(format!("wrote {}", p.display()));
    }
    if let Some(p) = &a.phasor {
        write_npy(&outputs.stage(p)?, &stack_out(batched, fits.iter().map(|f| f.phasor.clone()).collect())?.view())?;
        lines.push(format!("wrote {}", p.display()));
    }
    if let Some(p) = &a.png {
        figures::map(
            &outputs.stage(p)?,
            "Fluorescence lifetime (reconvolution fit, amplitude-weighted mean)",
            &tau.mapv(|t| t * 1e9).view(),
            "lifetime τ (ns)",
        )?;
        lines.push(format!("wrote {}", p.display()));
    }
    outputs.commit()?;
    lines.iter().for_each(|l| println!("{l}"));
    Ok(ExitCode::SUCCESS)
}

#[derive(Subcommand)]
pub enum PlotCmd {
    /// Training curves of one or more runs (RUN/metrics.csv): the training loss and the first
    /// validation metric (MSE for cube networks, range RMSE for depth networks) against the
    /// epoch; a learned-codes run's relaxed phase is the run RUN/relaxed.
    Training {
        /// Run directories (from `tcsense train`) or zoo entries, `zoo:NAME`.
        #[arg(long, num_args = 1.., required = true, value_parser = super::parse_run)]
        run: Vec<PathBuf>,
        /// Output PNG.
        #[arg(short, long)]
        output: PathBuf,
    },
    /// Waveforms at chosen pixels for one or more cubes (like the paper's Figs. 18 and 20);
    /// writes the PNG and a CSV of the values next to it.
    Waveforms {
        /// Cubes .npy [T, H, W] or the first of a batch [B, T, H, W] (e.g. truth, TVAL3, ADMM-Net), drawn black, blue, red, …
        #[arg(long, num_args = 1.., required = true)]
        cube: Vec<PathBuf>,
        /// Pixels as ROW,COL.
        #[arg(long, num_args = 1.., required = true)]
        pixel: Vec<String>,
        /// Output PNG.
        #[arg(short, long)]
        output: PathBuf,
    },
}

pub fn plot(cmd: PlotCmd) -> Result<ExitCode> {
    match cmd {
        PlotCmd::Training { run, output } => {
            let (mut loss, mut val) = (Vec::new(), Vec::new());
            let mut val_name = String::new();
            for r in &run {
                let path = r.join(tcsense_train::run_dir::METRICS_FILE);
                if !path.exists() {
                    bail!("{}: no metrics; train the run for at least one epoch", path.display());
                }
                let rows = tcsense_train::run_dir::read_rows(&path, usize::MAX)?;
                let first = rows
                    .first()
                    .and_then(|m| m.val.first())
                    .map(|(n, _)| n.clone())
                    .with_context(|| format!("{}: no epoch logged yet", path.display()))?;
                if !val_name.is_empty() && first != val_name {
                    bail!(
                        "{}: validates {first}, but {} validates {val_name}; plot runs of one kind together",
                        path.display(),
                        run[0].display()
                    );
                }
                val_name = first;
                let label = r.display().to_string();
                loss.push(figures::Series { label: label.clone(), points: rows.iter().map(|m| (m.epoch as f64, m.train_loss)).collect() });
                val.push(figures::Series { label, points: rows.iter().map(|m| (m.epoch as f64, m.get(&val_name))).collect() });
            }
            let label = match val_name.as_str() {
                "val_mse" => "validation MSE".to_string(),
                "val_psnr_db" => "validation PSNR (dB)".to_string(),
                "val_depth_rmse_m" => "validation range RMSE of the returns (m)".to_string(),
                n => n.replace('_', " "),
            };
            figures::training_curves(&output, &loss, &val, &label)?;
            println!("wrote {}", output.display());
        }
        PlotCmd::Waveforms { cube, pixel, output } => {
            let cubes: Vec<ndarray::Array3<f32>> = cube.iter().map(|p| read_cube3(p)).collect::<Result<_>>()?;
            let (_, h, w) = cubes[0].dim();
            for (p, c) in cube.iter().zip(&cubes) {
                if (c.dim().1, c.dim().2) != (h, w) {
                    bail!("{}: frame {}x{} differs from {}x{} of {}", p.display(), c.dim().1, c.dim().2, h, w, cube[0].display());
                }
            }
            let pixels: Vec<(usize, usize)> = pixel
                .iter()
                .map(|s| {
                    let (r, c) = s.split_once(',').with_context(|| format!("--pixel {s:?}: expected ROW,COL"))?;
                    let (r, c): (usize, usize) = (
                        r.trim().parse().with_context(|| format!("--pixel {s:?}: expected ROW,COL"))?,
                        c.trim().parse().with_context(|| format!("--pixel {s:?}: expected ROW,COL"))?,
                    );
                    if r >= h || c >= w {
                        bail!("--pixel {s}: outside the {h}x{w} frame");
                    }
                    Ok((r, c))
                })
                .collect::<Result<_>>()?;
            let names: Vec<String> =
                cube.iter().map(|p| p.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default()).collect();
            let views: Vec<(&str, ndarray::ArrayView3<f32>)> = names.iter().zip(&cubes).map(|(n, c)| (n.as_str(), c.view())).collect();
            let csv = plot_waveforms(&output, &views, &pixels)?;
            let csv_path = output.with_extension("csv");
            write_bytes(&csv_path, csv.as_bytes())?;
            println!("wrote {} and {}", output.display(), csv_path.display());
        }
    }
    Ok(ExitCode::SUCCESS)
}
