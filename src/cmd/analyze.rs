//! `tcsense codes analyze` and the identifiability lines of `codes check` / `codes export`.

use anyhow::{bail, Context, Result};
use clap::Args;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use tcsense_infer::figures::{line_chart, log_chart, Series};
use tcsense_sensor::identify::{self, AnalyzeOptions, Light, Report, DEFAULT_ALIAS_THRESHOLD};
use tcsense_sensor::{Codes, MeasurementMatrix, C};

use super::sensor::{ResponseArgs, SensorArgs};

/// The sensor a code set is analysed on (IRF and sampling) and the light it is stated at.
#[derive(Args, Clone)]
pub struct MeasureArgs {
    #[command(flatten)]
    pub response: ResponseArgs,
    #[command(flatten)]
    pub light: LightArgs,
}

/// The light the bounds are stated at and the alias threshold (`codes analyze`, `check`,
/// `export`, `select`).
#[derive(Args, Clone)]
pub struct LightArgs {
    /// Signal electrons per subpixel from one return (or decay).
    #[arg(long, default_value_t = 1000.0)]
    pub photons: f64,
    /// Ambient electrons per subpixel over the exposure.
    #[arg(long, default_value_t = 100.0)]
    pub ambient: f64,
    /// Read noise σ per tap (electrons).
    #[arg(long, default_value_t = 40.0)]
    pub read_noise: f64,
    /// Aliases below this distance are warned about (check), refused (export) or ranked below
    /// every set above it (select).
    #[arg(long, default_value_t = DEFAULT_ALIAS_THRESHOLD)]
    pub alias_threshold: f64,
}

impl LightArgs {
    /// The checked light (and threshold).
    pub fn light(&self) -> Result<Light> {
        let l = Light { photons: self.photons, ambient: self.ambient, read_noise_e: self.read_noise };
        l.validate().map_err(|e| anyhow::anyhow!("--photons/--ambient/--read-noise: {e}"))?;
        if !(self.alias_threshold >= 0.0 && self.alias_threshold <= std::f64::consts::SQRT_2) {
            bail!("--alias-threshold {}: expected a distance in [0, 1.414] (unit signatures are 0 to 1.414 apart)", self.alias_threshold);
        }
        Ok(l)
    }
}

impl MeasureArgs {
    /// The sensor flags with these codes.
    /// The sensor flags with these codes (IRF `physical` unless named).
    pub fn sensor(&self, codes: &Path) -> SensorArgs {
        let irf = Some(self.response.irf.clone().unwrap_or_else(|| "physical".into()));
        SensorArgs { codes: codes.to_path_buf(), response: ResponseArgs { irf, ..self.response.clone() }, calibration: None }
    }
    fn k(&self) -> usize {
        self.response.k()
    }
}

#[derive(Args)]
pub struct AnalyzeArgs {
    /// Codes JSON file(s); several are compared side by side.
    #[arg(required = true)]
    codes: Vec<PathBuf>,
    #[command(flatten)]
    measure: MeasureArgs,
    /// The lifetime measures too (on by default with --heterodyne).
    #[arg(long)]
    lifetime: bool,
    /// Print the whole report (every delay's bound) as JSON.
    #[arg(long)]
    json: bool,
    /// Write range-bound.png (and lifetime-bound.png) into DIR.
    #[arg(long, value_name = "DIR")]
    plot: Option<PathBuf>,
    /// Check the bounds against the project's estimators on noisy simulated 32×32 frames (the
    /// range fit at 8 delays; the fit to the taps at 6 lifetimes with --heterodyne).
    #[arg(long)]
    validate: bool,
    /// Seed of the validation's noise.
    #[arg(long, default_value_t = 0)]
    seed: u64,
}

/// Frame side of `--validate`.
const VALIDATE_SIZE: usize = 32;

fn print_checks(what: &str, unit: &str, scale: f64, checks: &[tcsense_infer::bounds::Check]) {
    println!("  {what}: bound vs the estimator's spread ({unit}; RMS over {} pixels each)", checks.first().map_or(0, |c| c.pixels));
    println!("      at        bound      spread       bias   spread/bound");
    for c in checks {
        println!(
            "  {:>8.3}   {:>10.5}  {:>10.5}  {:>+9.5}   {:>6.3}",
            c.at * scale,
            c.bound * scale,
            c.spread * scale,
            c.bias * scale,
            c.ratio()
        );
    }
}

/// A code set's analysis with the name it is shown under.
struct Analysed {
    name: String,
    report: Report,
}

/// Analyse one code set on the sensor of `m`.
fn analyse(path: &Path, m: &MeasureArgs, lifetime: bool) -> Result<(Codes, MeasurementMatrix, Report)> {
    let sensor = m.sensor(path).sensor()?;
    let light = m.light.light()?;
    let opts = AnalyzeOptions { lifetime, ..Default::default() };
    let report = identify::analyze(sensor.matrix(), m.k(), &light, &opts);
    Ok((sensor.codes().clone(), sensor.matrix().clone(), report))
}

fn metres(bins: f64, r: &Report) -> f64 {
    bins * r.bin_width_s * C / 2.0
}

/// The identifiability lines printed by `analyze` and `check`.
fn print_report(name: &str, r: &Report, threshold: f64) {
    let al = &r.range_alias;
    let warn = if al.distance < threshold { "  ← ALIAS: below the threshold" } else { "" };
    println!("{name}:");
    println!(
        "  range alias      {:.3} (bins {} and {}; 0: the taps cannot tell them apart, 1.414: orthogonal){warn}",
        al.distance, al.bin, al.other
    );
    let rb = &r.range;
    println!(
        "  range bound      worst {:.3} bins ({:.1} mm, at bin {:.2}), mean {:.3} bins ({:.1} mm) at {} e⁻ signal, {} e⁻ ambient, {} e⁻ read noise",
        rb.worst_bins,
        metres(rb.worst_bins, r) * 1e3,
        rb.worst_at_bins,
        rb.mean_bins,
        metres(rb.mean_bins, r) * 1e3,
        r.light.photons,
        r.light.ambient,
        r.light.read_noise_e
    );
    match r.two_returns.resolved_bins {
        Some(d) => println!("  two returns      resolved from {d:.2} bins apart ({:.2} m; half the signal each)", metres(d, r)),
        None => println!("  two returns      not resolved at any separation up to half the cycle"),
    }
    if let Some(la) = &r.lifetime_alias {
        println!(
            "  lifetime alias   {:.3} (τ {:.2} ns at onset bin {:.1} against τ {:.2} ns at bin {:.1}; a pixel fitting its own onset; the frame's onset is placed by the range alias)",
            la.distance,
            la.tau1_s * 1e9,
            la.onset1_bins,
            la.tau2_s * 1e9,
            la.onset2_bins
        );
    }
    if let Some(pts) = &r.lifetime {
        println!("  lifetime bound   τ (ns)   onset known: mean / worst (ns)   onset fitted: mean / worst (ns)");
        for p in pts {
            println!(
                "                   {:>6.2}   {:>10.4} / {:<10.4}          {:>10.4} / {:<10.4}",
                p.tau_s * 1e9,
                p.known_mean_s * 1e9,
                p.known_worst_s * 1e9,
                p.fitted_mean_s * 1e9,
                p.fitted_worst_s * 1e9
            );
        }
    }
}

/// A short name for a legend: the file with its folder (`unet-lidar/codes.json`).
fn file_name(p: &Path) -> String {
    let parts: Vec<String> = p.components().rev().take(2).map(|c| c.as_os_str().to_string_lossy().into_owned()).collect();
    parts.into_iter().rev().collect::<Vec<_>>().join("/")
}

pub fn analyze_cmd(a: AnalyzeArgs) -> Result<ExitCode> {
    let lifetime = a.lifetime || a.measure.response.heterodyne.is_some();
    let mut all = Vec::new();
    let mut checks = Vec::new();
    for path in &a.codes {
        let (_, matrix, report) = analyse(path, &a.measure, lifetime)?;
        if a.validate {
            let light = a.measure.light.light()?;
            let t = matrix.bins() as f64;
            // delays spread over the cycle, off the bins' centres
            let delays: Vec<f64> = (0..8).map(|i| (i as f64 + 0.37) * t / 8.0).collect();
            let range = tcsense_infer::bounds::validate_range(&matrix, &light, &delays, VALIDATE_SIZE, a.seed)?;
            let life = if lifetime {
                let taus = [0.5e-9, 1e-9, 2e-9, 3e-9, 5e-9, 8e-9];
                let onset = 0.3 * t * matrix.bin_width_s();
                Some(tcsense_infer::bounds::validate_lifetime(&matrix, a.measure.k(), &light, &taus, onset, VALIDATE_SIZE, a.seed)?)
            } else {
                None
            };
            checks.push((range, life));
        }
        all.push(Analysed { name: path.display().to_string(), report });
    }
    if a.json {
        let v: Vec<serde_json::Value> = all.iter().map(|x| serde_json::json!({ "codes": x.name, "report": x.report })).collect();
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        for (i, x) in all.iter().enumerate() {
            print_report(&x.name, &x.report, a.measure.light.alias_threshold);
            if let Some((range, life)) = checks.get(i) {
                print_checks("range fit (3×3 window, started at the truth)", "bins", 1.0, range);
                if let Some(life) = life {
                    print_checks("fit to the taps (3×3 window, onset given), lifetime", "ns", 1e9, life);
                }
            }
        }
    }
    if let Some(dir) = &a.plot {
        std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
        let series: Vec<Series> = a
            .codes
            .iter()
            .zip(&all)
            .map(|(p, x)| {
                let r = &x.report;
                let mut pts: Vec<(f64, f64)> = r
                    .range
                    .delays_bins
                    .iter()
                    .zip(&r.range.sigma_bins)
                    .map(|(&d, &s)| (d * r.bin_width_s * 1e9, metres(s, r) * 1e3))
                    .collect();
                pts.sort_by(|u, v| u.0.total_cmp(&v.0));
                Series { label: format!("{} (alias {:.2})", file_name(p), r.range_alias.distance), points: pts }
            })
            .collect();
        let light = all[0].report.light;
        let title = format!(
            "Range Cramér–Rao bound over the cycle ({} e⁻ signal, {} e⁻ ambient, σ_read {} e⁻)",
            light.photons, light.ambient, light.read_noise_e
        );
        let png = dir.join("range-bound.png");
        line_chart(&png, &title, "delay of the return (ns)", "σ of the range (mm)", &series)?;
        println!("wrote {}", png.display());
        if lifetime {
            let mut series = Vec::new();
            for (p, x) in a.codes.iter().zip(&all) {
                if let Some(pts) = &x.report.lifetime {
                    series.push(Series {
                        label: format!("{}: onset known (worst)", file_name(p)),
                        points: pts.iter().map(|q| (q.tau_s * 1e9, q.known_worst_s * 1e9)).collect(),
                    });
                    series.push(Series {
                        label: format!("{}: onset fitted (worst)", file_name(p)),
                        points: pts.iter().map(|q| (q.tau_s * 1e9, q.fitted_worst_s * 1e9)).collect(),
                    });
                }
            }
            let png = dir.join("lifetime-bound.png");
            let title = format!("Lifetime bound, worst over the onsets ({} e⁻ signal, {} e⁻ ambient)", light.photons, light.ambient);
            log_chart(&png, &title, "lifetime τ (ns)", "σ of τ (ns)", &series)?;
            println!("wrote {}", png.display());
        }
    }
    Ok(ExitCode::SUCCESS)
}

/// `codes check`'s identifiability lines: the report, and a warning on stderr below the
/// threshold. Returns whether the codes alias.
pub fn check_measures(path: &Path, m: &MeasureArgs) -> Result<bool> {
    let (_, _, report) = analyse(path, m, m.response.heterodyne.is_some())?;
    print_report(&path.display().to_string(), &report, m.light.alias_threshold);
    let aliased = aliased(&report, m.light.alias_threshold);
    if let Some(msg) = &aliased {
        eprintln!("warning: {}: {msg}", path.display());
    }
    Ok(aliased.is_some())
}

/// What aliases in a report, in words, or `None`.
fn aliased(r: &Report, threshold: f64) -> Option<String> {
    let al = &r.range_alias;
    if al.distance < threshold {
        return Some(format!(
            "returns in bins {} and {} give taps {:.3} apart (alias threshold {threshold}): a surface at one of these ranges is read at the other",
            al.bin, al.other, al.distance
        ));
    }
    None
}

/// `codes export`'s gate: an error naming the bins where the codes alias (unless forced).
pub fn export_gate(path: &Path, m: &MeasureArgs, force: bool) -> Result<()> {
    if force {
        return Ok(());
    }
    let (_, _, report) = analyse(path, m, m.response.heterodyne.is_some())?;
    if let Some(msg) = aliased(&report, m.light.alias_threshold) {
        bail!("{}: {msg}; refusing to export aliased codes (design better ones with `tcsense codes select --criterion range`, or pass --force)", path.display());
    }
    Ok(())
}
