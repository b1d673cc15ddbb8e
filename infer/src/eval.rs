//! Evaluation of decoders against a dataset's ground truth through the decoder contract:
//! every decoder gets the same (optionally noisy) measurements of the same items, and one
//! row per decoder holds the mean MSE and PSNR, depth errors per bounce (LiDAR), lifetime MAE
//! (FLIm) and the time per frame.

use ndarray::{Array3, Array4, ArrayD, ArrayView2, ArrayView3, Axis, Ix3, Ix4};
use serde::Serialize;
use std::path::Path;
use std::sync::atomic::AtomicBool;
use std::time::Instant;
use tcsense_datasets::Dataset;
use tcsense_models::decoder::{Control, Decoded};
use tcsense_models::ModelError;
use tcsense_sensor::measure::{clipped_pixels, measure, signal_exposure};
use tcsense_sensor::noise::derive_seed;
use tcsense_sensor::noise::Exposure;
use tcsense_sensor::nonideal::NonIdeal;
use tcsense_sensor::{NoiseParams, Sensor};

use crate::metrics::{depth_errors, mse, psnr, DepthErrors, LifetimeErrors};
use crate::products::{depth_map, PeakOptions};
use crate::registry::NamedDecoder;
use crate::{InferError, Result};

/// Accumulates metrics over items.
#[derive(Debug, Clone, Default, Serialize)]
pub struct EvalRow {
    pub decoder: String,
    pub items: usize,
    pub mse: f64,
    pub psnr_db: f64,
    /// Per bounce (LiDAR).
    pub depth: Vec<DepthErrors>,
    /// Mean absolute error of the mean lifetime `τ_m` (s), FLIm: over the pixels that hold a
    /// fluorophore ([`tcsense_datasets::flim::SIGNAL_REL`] of the brightest or more) and got a
    /// lifetime ([`LifetimeErrors`]).
    pub lifetime_mae_s: Option<f64>,
    /// The same weighted by the true intensity.
    pub lifetime_mae_weighted_s: Option<f64>,
    /// Share of the fluorophore pixels whose lifetime is within 0.2 ns (no lifetime: a miss).
    pub lifetime_within_02ns: Option<f64>,
    /// Share of the fluorophore pixels that got a lifetime.
    pub lifetime_coverage: Option<f64>,
    /// Share of the pixels without any fluorophore that got a lifetime (a confidence that says
    /// "fluorophore" everywhere covers every fluorophore).
    pub lifetime_false_share: Option<f64>,
    /// With two lifetime decoders or more in one call: the MAE (s) over the fluorophore pixels
    /// that every one of them gave a lifetime, so that a decoder that leaves the hard pixels
    /// out is compared with one that does not on the same pixels ([`evaluate`]).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub lifetime_mae_common_s: Option<f64>,
    /// The share of the fluorophore pixels that every lifetime decoder of the call gave a
    /// lifetime (the pixels of [`Self::lifetime_mae_common_s`]).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub lifetime_common_share: Option<f64>,
    pub seconds_per_frame: f64,
    /// Per bounce: the median absolute range error (m) over the detected returns of every item.
    pub depth_median_m: Vec<f64>,
    /// Per bounce: the share of the true returns estimated within half a bin (`c·Δt/4`) of
    /// the truth (a missed return counts against it).
    pub depth_within_half_bin: Vec<f64>,
    /// The light the measurements were simulated at, on a photon ladder ([`evaluate_ladder`]).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub light: Option<Light>,
    /// The decays' onset (s) given to the decoders that fit one (`eval --onset-ns`); absent:
    /// fitted to each item.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub onset_given_s: Option<f64>,
    /// The share of the items' pixels with a tap clipped at the full well, where no decoder
    /// gives a range or a lifetime (absent: none clipped).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub clipped_share: Option<f64>,
    #[serde(skip)]
    /// Per bounce: the counts summed over items, Σ squared and Σ absolute errors.
    depth_sums: Vec<(DepthErrors, f64, f64)>,
    #[serde(skip)]
    /// Per bounce: every detected return's absolute error (m).
    depth_abs: Vec<Vec<f32>>,
    #[serde(skip)]
    lt_sum: LifetimeErrors,
    #[serde(skip)]
    time_sum: f64,
}

impl EvalRow {
    pub fn new(decoder: &str) -> Self {
        EvalRow { decoder: decoder.to_string(), ..Default::default() }
    }

    /// Add one item: reconstruction `x̂` (if the decoder gives one), truth `x` (both
    /// `[T, H, W]`), optional true range `[K, H, W]` and lifetime `[H, W]`, bin width and the
    /// decoder's time for it. Depth comes from `depth_est` `[K, H, W]` where the decoder
    /// estimated it, else from peaks of `x̂`; MSE, PSNR and lifetimes need `x̂` (NaN without).
    #[allow(clippy::too_many_arguments)]
    pub fn add(
        &mut self,
        xh: Option<&ArrayView3<'_, f32>>,
        x: &ArrayView3<'_, f32>,
        depth_est: Option<&ArrayView3<'_, f32>>,
        depth: Option<&ArrayView3<'_, f32>>,
        lifetime: Option<&ArrayView2<'_, f32>>,
        bin_width_s: f64,
        seconds: f64,
    ) {
        self.add_with(xh, x, depth_est, depth, lifetime.map(|l| (l, None, None)), bin_width_s, seconds)
    }

    /// [`Self::add`] with the lifetime truth as `(τ_m [H, W], intensity [H, W], estimate)`: a
    /// lifetime decoder's own `τ_m` estimate `[H, W]` (s), else the fit of `x̂`
    /// ([`tcsense_fits::lifetime_cube::fit_cube`], IRF fitted); without the intensity every pixel with a
    /// true lifetime counts.
    #[allow(clippy::too_many_arguments, clippy::type_complexity)]
    pub fn add_with(
        &mut self,
        xh: Option<&ArrayView3<'_, f32>>,
        x: &ArrayView3<'_, f32>,
        depth_est: Option<&ArrayView3<'_, f32>>,
        depth: Option<&ArrayView3<'_, f32>>,
        lifetime: Option<(&ArrayView2<'_, f32>, Option<&ArrayView2<'_, f32>>, Option<&ArrayView2<'_, f32>>)>,
        bin_width_s: f64,
        seconds: f64,
    ) {
        let n = self.items as f64;
        let (m, p) = match xh {
            Some(xh) => {
                let (a, b) = (xh.as_standard_layout(), x.as_standard_layout());
                let (a, b) = (a.as_slice().unwrap_or(&[]), b.as_slice().unwrap_or(&[]));
                (mse(a, b), psnr(a, b))
            }
            None => (f64::NAN, f64::NAN),
        };
        self.mse = (self.mse * n + m) / (n + 1.0);
        self.psnr_db = (self.psnr_db * n + p) / (n + 1.0);
        self.time_sum += seconds;
        self.items += 1;
        self.seconds_per_frame = self.time_sum / self.items as f64;
        if let Some(d) = depth {
            let peaks;
            let est = match (depth_est, xh) {
                (Some(est), _) => Some(est.view()),
                (None, Some(xh)) => {
                    peaks = depth_map(xh, bin_width_s, &PeakOptions { max_peaks: d.dim().0, ..Default::default() }).0;
                    Some(peaks.view())
                }
                (None, None) => None,
            };
            let errs = est.map_or_else(Vec::new, |est| depth_errors(&est, d));
            if let Some(est) = est {
                let k = d.dim().0.min(est.dim().0);
                if self.depth_abs.len() < k {
                    self.depth_abs.resize(k, Vec::new());
                }
                for (b, abs) in self.depth_abs.iter_mut().enumerate().take(k) {
                    abs.extend(
                        d.index_axis(Axis(0), b)
                            .iter()
                            .zip(est.index_axis(Axis(0), b).iter())
                            .filter(|(t, e)| t.is_finite() && e.is_finite())
                            .map(|(t, e)| (e - t).abs()),
                    );
                }
                self.depth_median_m = self.depth_abs.iter_mut().map(|v| median(v)).collect();
            }
            if self.depth_sums.len() < errs.len() {
                self.depth_sums.resize(errs.len(), (DepthErrors::default(), 0.0, 0.0));
            }
            for ((sum, se, ae), e) in self.depth_sums.iter_mut().zip(&errs) {
                sum.truth += e.truth;
                sum.detected += e.detected;
                sum.empty += e.empty;
                sum.false_alarms += e.false_alarms;
                *se += e.rmse_m * e.rmse_m * e.detected as f64;
                *ae += e.mae_m * e.detected as f64;
            }
            let half_bin_m = SPEED_OF_LIGHT * bin_width_s / 4.0;
            self.depth_within_half_bin = self
                .depth_sums
                .iter()
                .enumerate()
                .map(|(b, (sum, _, _))| {
                    let within = self.depth_abs.get(b).map_or(0, |abs| abs.iter().filter(|&&e| (e as f64) <= half_bin_m).count());
                    if sum.truth > 0 {
                        within as f64 / sum.truth as f64
                    } else {
                        f64::NAN
                    }
                })
                .collect();
            self.depth = self
                .depth_sums
                .iter()
                .map(|&(sum, se, ae)| {
                    let d = sum.detected as f64;
                    DepthErrors {
                        rmse_m: if d > 0.0 { (se / d).sqrt() } else { f64::NAN },
                        mae_m: if d > 0.0 { ae / d } else { f64::NAN },
                        ..sum
                    }
                })
                .collect();
        }
        if let Some((truth, intensity, est)) = lifetime {
            let fitted;
            let est = match (est, xh) {
                (Some(e), _) => Some(e.to_owned()),
                (None, Some(xh)) => {
                    fitted = tcsense_fits::lifetime_cube::fit_cube(xh, bin_width_s, &tcsense_fits::lifetime_cube::FitOptions::default());
                    Some(fitted.lifetimes.index_axis(Axis(0), 0).to_owned())
                }
                (None, None) => None,
            };
            if let Some(est) = est {
                self.lt_sum.add(&est.view(), truth, intensity);
                if self.lt_sum.truth > 0 {
                    self.lifetime_mae_s = self.lt_sum.mae();
                    self.lifetime_mae_weighted_s = self.lt_sum.weighted_mae();
                    self.lifetime_within_02ns = self.lt_sum.within_share();
                    self.lifetime_coverage = self.lt_sum.coverage();
                    self.lifetime_false_share = self.lt_sum.false_share();
                }
            }
        }
    }

    /// One line of a table.
    pub fn line(&self) -> String {
        let mut s = format!("{:<24} {:>5} {:>11.4e} {:>8.2}", self.decoder, self.items, self.mse, self.psnr_db);
        for (b, d) in self.depth.iter().enumerate() {
            if d.truth > 0 {
                s.push_str(&format!(
                    "  b{}: rmse {:.3} m mae {:.3} m median {:.3} m det {:.0}%",
                    b + 1,
                    d.rmse_m,
                    d.mae_m,
                    self.depth_median_m.get(b).copied().unwrap_or(f64::NAN),
                    100.0 * d.detection_rate()
                ));
            }
            if d.false_alarms > 0 {
                let lead = if d.truth > 0 { " ".to_string() } else { format!("  b{}: ", b + 1) };
                s.push_str(&format!("{lead}false {:.0}%", 100.0 * d.false_alarm_rate()));
            }
        }
        if let Some(l) = self.lifetime_mae_s {
            s.push_str(&format!("  lifetime MAE {:.3} ns", l * 1e9));
        }
        if let (Some(w), Some(f), Some(c)) = (self.lifetime_mae_weighted_s, self.lifetime_within_02ns, self.lifetime_coverage) {
            s.push_str(&format!(
                " (intensity-weighted {:.3} ns, {:.1} % within 0.2 ns, {:.1} % with a lifetime{})",
                w * 1e9,
                f * 100.0,
                c * 100.0,
                self.lifetime_false_share.map(|v| format!(", {:.1} % of the background with one", v * 100.0)).unwrap_or_default()
            ));
        }
        if let (Some(l), Some(c)) = (self.lifetime_mae_common_s, self.lifetime_common_share) {
            s.push_str(&format!(", {:.3} ns on the {:.1} % every decoder covers", l * 1e9, c * 100.0));
        }
        s.push_str(&format!("  {:.1} ms/frame", self.seconds_per_frame * 1e3));
        s
    }

    /// The rows as CSV, one line per decoder after a header.
    pub fn csv(rows: &[EvalRow]) -> String {
        let mut csv = String::from("decoder,items,mse,psnr_db,bounce1_rmse_m,bounce1_mae_m,bounce1_detection,bounce2_rmse_m,bounce2_mae_m,bounce2_detection,lifetime_mae_s,seconds_per_frame,lifetime_mae_weighted_s,lifetime_within_02ns,lifetime_coverage,bounce1_false_alarm,bounce2_false_alarm,bounce1_median_m,bounce2_median_m,bounce1_within_half_bin,bounce2_within_half_bin,signal_fraction,signal_electrons,sbr,lifetime_false_share,lifetime_mae_common_s,lifetime_common_share\n");
        for r in rows {
            let b = |k: usize| r.depth.get(k).map_or(",,".to_string(), |d| format!("{},{},{}", d.rmse_m, d.mae_m, d.detection_rate()));
            let o = |v: Option<f64>| v.map_or(String::new(), |v| v.to_string());
            let fa = |k: usize| o(r.depth.get(k).map(|d| d.false_alarm_rate()));
            let med = |k: usize| o(r.depth_median_m.get(k).copied());
            let half = |k: usize| o(r.depth_within_half_bin.get(k).copied());
            let light = r.light.map_or(",,".to_string(), |l| format!("{},{},{}", l.signal_fraction, l.signal_electrons, o(l.sbr)));
            csv.push_str(&format!(
                "{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{}\n",
                r.decoder,
                r.items,
                r.mse,
                r.psnr_db,
                b(0),
                b(1),
                o(r.lifetime_mae_s),
                r.seconds_per_frame,
                o(r.lifetime_mae_weighted_s),
                o(r.lifetime_within_02ns),
                o(r.lifetime_coverage),
                fa(0),
                fa(1),
                med(0),
                med(1),
                half(0),
                half(1),
                light,
                o(r.lifetime_false_share),
                o(r.lifetime_mae_common_s),
                o(r.lifetime_common_share)
            ));
        }
        csv
    }
}

/// The median of `v` (NaN when empty), reordering `v` in place.
fn median(v: &mut [f32]) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    let k = v.len() / 2;
    let (_, m, _) = v.select_nth_unstable_by(k, f32::total_cmp);
    *m as f64
}

/// What to evaluate on.
#[derive(Debug, Clone)]
pub struct EvalSettings {
    /// Dataset split.
    pub split: String,
    /// At most this many items.
    pub items: Option<usize>,
    /// Noise on the simulated measurements (`None`: noise-free).
    pub noise: Option<NoiseParams>,
    /// Item `i`'s noise is seeded by `(seed, i)`.
    pub seed: u64,
    /// The sensor the measurements come from, when it is not the ideal model: its
    /// non-idealities (gains, dark offset, crosstalk, tail, drift), realised at the items' size.
    pub sensor: Option<NonIdeal>,
    /// Ambient light as a signal-to-background ratio: constant light added to every item, the
    /// frame's mean signal photons per pixel over `sbr` (`None`: no ambient). The exposure is
    /// set by the signal alone, so that `noise.signal_fraction` keeps its meaning.
    pub sbr: Option<f64>,
}

/// The speed of light (m/s).
const SPEED_OF_LIGHT: f64 = 299_792_458.0;

/// One rung of a photon ladder: the light the measurements were simulated at.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Light {
    /// The brightest tap's signal as a share of the full well.
    pub signal_fraction: f64,
    /// The brightest tap's signal electrons (`signal_fraction` × full well).
    pub signal_electrons: f64,
    /// Signal-to-background ratio of the ambient light (`None`: none).
    pub sbr: Option<f64>,
}

/// Evaluate `decoders` at every light level of `ladder` (the brightest tap's share of the full
/// well, noise on, ambient light at `settings.sbr`): the photon-efficiency curve. The same
/// items and noise seeds at every level; the rows carry their [`Light`].
pub fn evaluate_ladder(
    ds: &Dataset,
    sensor: &Sensor,
    decoders: &mut [NamedDecoder],
    settings: &EvalSettings,
    ladder: &[f64],
    on_item: &dyn Fn(&str, usize, usize),
    cancel: &AtomicBool,
) -> Result<Vec<EvalRow>> {
    let base = settings.noise.unwrap_or_default();
    let mut rows = Vec::new();
    for &level in ladder {
        let noise = NoiseParams { signal_fraction: level, ..base }.validate().map_err(|e| InferError::InvalidParam {
            field: "light level",
            got: level.to_string(),
            expected: format!("a share of the full well the noise model takes ({e})"),
        })?;
        let at = EvalSettings { noise: Some(noise), ..settings.clone() };
        let light = Light { signal_fraction: level, signal_electrons: level * noise.full_well_e, sbr: settings.sbr };
        for mut row in evaluate(ds, sensor, decoders, &at, on_item, cancel)? {
            row.light = Some(light);
            rows.push(row);
        }
    }
    Ok(rows)
}

/// Evaluate `decoders` on a dataset split with `sensor`, what the decoders know of the sensor
/// (its nominal `A` measures the items; a calibration's dark and gain maps correct the tap
/// images and its matrix decodes them): the same measurements of each item (`measure`, noise
/// seeded per item) go to every decoder. `on_item(decoder, done, of)` is called after each item.
pub fn evaluate(
    ds: &Dataset,
    sensor: &Sensor,
    decoders: &mut [NamedDecoder],
    settings: &EvalSettings,
    on_item: &dyn Fn(&str, usize, usize),
    cancel: &AtomicBool,
) -> Result<Vec<EvalRow>> {
    let x = ds
        .load(&settings.split, "x")?
        .into_dimensionality::<Ix4>()
        .map_err(|e| file_err(&ds.dir, format!("field x of split {}: {e}", settings.split)))?;
    let n = settings.items.unwrap_or(x.dim().0).min(x.dim().0);
    if n == 0 {
        return Err(file_err(&ds.dir, format!("no items in split {:?}", settings.split)));
    }
    let field = |name: &str| -> Result<Option<ndarray::ArrayD<f32>>> {
        Ok(if ds.manifest.fields.contains_key(name) { Some(ds.load(&settings.split, name)?) } else { None })
    };
    let depth =
        field("depth")?.map(|d| d.into_dimensionality::<Ix4>()).transpose().map_err(|e| file_err(&ds.dir, format!("field depth: {e}")))?;
    let lifetime = field("lifetime")?
        .map(|d| d.into_dimensionality::<Ix3>())
        .transpose()
        .map_err(|e| file_err(&ds.dir, format!("field lifetime: {e}")))?;
    let intensity = field("intensity")?
        .map(|d| d.into_dimensionality::<Ix3>())
        .transpose()
        .map_err(|e| file_err(&ds.dir, format!("field intensity: {e}")))?;
    let (_, _, h, w) = x.dim();
    let a = sensor.nominal();
    let plan = a.plan(h, w)?;
    // a non-ideal sensor, or any sensor whose raw tap images a calibration corrects (its dark
    // offsets are in electrons), is measured in electrons
    let real = match (&settings.sensor, sensor.calibration()) {
        (Some(s), _) if !s.is_ideal() => Some(s.realise(a, h, w)?),
        (_, Some(_)) => Some(NonIdeal::default().realise(a, h, w)?),
        _ => None,
    };
    let noise_model = settings.noise.unwrap_or_default();
    if let Some(sbr) = settings.sbr.filter(|s| !(s.is_finite() && *s > 0.0)) {
        return Err(InferError::InvalidParam {
            field: "sbr",
            got: sbr.to_string(),
            expected: "a positive signal-to-background ratio (e.g. 1: as much ambient light as signal)".into(),
        });
    }
    // the measurements every decoder sees, [1, M, H, W] per item, with their clipped pixels
    let measured: Vec<(Array4<f32>, Option<Array3<bool>>)> = (0..n)
        .map(|i| -> Result<(Array4<f32>, Option<Array3<bool>>)> {
            let xi = x.slice_axis(Axis(0), ndarray::Slice::from(i..i + 1));
            let seed = derive_seed(settings.seed, i as u64);
            // ambient light: a constant added to every bin; the exposure is the signal's own
            let (lit, exposure) = match settings.sbr {
                Some(sbr) => {
                    let t = xi.dim().1 as f32;
                    let b = xi.sum() / (xi.dim().2 * xi.dim().3) as f32 / (t * sbr as f32);
                    (Some(xi.mapv(|v| v + b)), signal_exposure(&plan, &xi, &noise_model)?)
                }
                None => (None, Exposure::Auto),
            };
            let xi = lit.as_ref().map_or(xi, |l| l.view());
            let as_batch = |a: ArrayD<f32>| a.into_dimensionality::<Ix4>().map_err(|e| file_err(&ds.dir, e.to_string()));
            // the pixels with a tap clipped at the full well, [1, H, W] (noise on)
            let as_masks = |a: ArrayD<bool>| a.into_dimensionality::<Ix3>().map_err(|e| file_err(&ds.dir, e.to_string()));
            let Some(real) = &real else {
                let exposure = match (&lit, &settings.noise) {
                    (Some(_), Some(_)) => exposure,
                    _ => Exposure::Auto,
                };
                let m = measure(&plan, &xi.view().into_dyn(), settings.noise.as_ref(), exposure, seed)?;
                let clipped = settings.noise.and_then(|n| m.clipped(n.full_well_e)).map(as_masks).transpose()?;
                return Ok((as_batch(m.into_input_units())?, clipped));
            };
            // a real sensor: raw electrons, corrected with the calibration's maps when there is one
            let m = real.measure(&xi, &noise_model, settings.noise.is_some(), exposure, seed)?;
            let clipped = settings.noise.map(|n| as_masks(clipped_pixels(&m.electrons.view().into_dyn(), n.full_well_e))).transpose()?;
            let s = m.electrons_per_unit as f32;
            let e: Array4<f32> = m.electrons.into_dimensionality().map_err(|e| file_err(&ds.dir, e.to_string()))?;
            Ok((sensor.correct(e.view())?.mapv(|v| v / s), clipped))
        })
        .collect::<Result<_>>()?;
    let (ys, clipped): (Vec<Array4<f32>>, Vec<Option<Array3<bool>>>) = measured.into_iter().unzip();
    let clipped: Vec<Option<Array3<bool>>> = clipped.into_iter().map(|c| c.filter(|c| c.iter().any(|&v| v))).collect();
    let clipped_share = clipped.iter().any(Option::is_some).then(|| {
        let count: usize = clipped.iter().flatten().map(|c| c.iter().filter(|&&v| v).count()).sum();
        count as f64 / (n * h * w) as f64
    });
    let ctl = Control::quiet(cancel);
    let mut rows = Vec::new();
    // each lifetime decoder's τ_m estimate of each item `[H, W]`, for the common pixels
    let mut estimates: Vec<(usize, Vec<ndarray::Array2<f32>>)> = Vec::new();
    for d in decoders.iter_mut() {
        let mut row = EvalRow { clipped_share, ..EvalRow::new(&d.label) };
        for (i, y) in ys.iter().enumerate() {
            let t0 = Instant::now();
            let mut out: Decoded = d.decoder.decode(y.view(), sensor, &ctl).map_err(|e| match e {
                ModelError::Cancelled => InferError::Cancelled,
                e => e.into(),
            })?;
            let secs = t0.elapsed().as_secs_f64();
            // no range and no lifetime where a tap is clipped: nothing there can be read (a
            // decoder of cubes too: its ranges, the cube's peaks as the row finds them, masked)
            if let Some(c) = &clipped[i] {
                if let (None, Some(cube), Some(truth)) = (&out.depth, &out.cube, &depth) {
                    let opts = PeakOptions { max_peaks: truth.dim().1, ..Default::default() };
                    out.depth = Some(depth_map(&cube.index_axis(Axis(0), 0), a.bin_width_s(), &opts).0.insert_axis(Axis(0)));
                }
                out.without_pixels(&c.view());
            }
            if out.cube.is_none() && out.depth.is_none() && out.lifetime.is_none() {
                return Err(InferError::InvalidParam {
                    field: "decoder",
                    got: d.label.clone(),
                    expected: "a decoder that gives a cube, depth or lifetimes".into(),
                });
            }
            if out.lifetime.is_some() && lifetime.is_none() {
                return Err(file_err(
                    &ds.dir,
                    format!("{} estimates lifetimes; this dataset has no lifetime field (a FLIm dataset has)", d.label),
                ));
            }
            let est = out.depth.as_ref().map(|e| e.index_axis(Axis(0), 0));
            let truth_d = depth.as_ref().map(|t| t.index_axis(Axis(0), i));
            let truth_l = lifetime.as_ref().map(|t| t.index_axis(Axis(0), i));
            let cube = out.cube.as_ref().map(|c| c.index_axis(Axis(0), 0));
            let truth_i = intensity.as_ref().map(|t| t.index_axis(Axis(0), i));
            let est_l = out.lifetime.as_ref().map(|l| l.index_axis(Axis(0), 0).index_axis(Axis(0), 0).to_owned());
            let lt = truth_l.as_ref().map(|t| (t, truth_i.as_ref(), est_l.as_ref().map(|e| e.view())));
            let lt = lt.as_ref().map(|(t, i, e)| (*t, *i, e.as_ref()));
            row.add_with(cube.as_ref(), &x.index_axis(Axis(0), i), est.as_ref(), truth_d.as_ref(), lt, a.bin_width_s(), secs);
            // kept for the pixels every lifetime decoder covers (moved: the row is done with it)
            if let (Some(e), true) = (est_l, lifetime.is_some()) {
                if i == 0 {
                    estimates.push((rows.len(), Vec::with_capacity(n)));
                }
                if let Some((_, v)) = estimates.last_mut() {
                    v.push(e);
                }
            }
            on_item(&d.label, i + 1, n);
        }
        rows.push(row);
    }
    if let (Some(truth), true) = (&lifetime, estimates.len() > 1) {
        common_pixels(&mut rows, &estimates, truth, intensity.as_ref());
    }
    Ok(rows)
}

/// Each lifetime decoder's MAE over the fluorophore pixels that every one of them estimated
/// (`estimates`: a decoder's row in `rows` and its estimate of each item `[H, W]`), and the
/// share of the fluorophore pixels they are.
fn common_pixels(
    rows: &mut [EvalRow],
    estimates: &[(usize, Vec<ndarray::Array2<f32>>)],
    truth: &ndarray::Array3<f32>,
    intensity: Option<&ndarray::Array3<f32>>,
) {
    let items = estimates.iter().map(|(_, e)| e.len()).min().unwrap_or(0);
    let common: Vec<ndarray::Array2<bool>> = (0..items)
        .map(|i| {
            let mut m = estimates[0].1[i].mapv(f32::is_finite);
            for (_, e) in &estimates[1..] {
                m.zip_mut_with(&e[i], |c, v| *c &= v.is_finite());
            }
            m
        })
        .collect();
    for (r, est) in estimates {
        let Some(row) = rows.get_mut(*r) else { continue };
        let mut sum = LifetimeErrors::default();
        for (i, mask) in common.iter().enumerate() {
            let masked = ndarray::Zip::from(&est[i]).and(mask).map_collect(|&v, &c| if c { v } else { f32::NAN });
            let i_map = intensity.map(|a| a.index_axis(Axis(0), i));
            sum.add(&masked.view(), &truth.index_axis(Axis(0), i), i_map.as_ref());
        }
        row.lifetime_mae_common_s = sum.mae();
        row.lifetime_common_share = sum.coverage();
    }
}

fn file_err(path: &Path, msg: String) -> InferError {
    InferError::File { path: path.to_path_buf(), msg }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array3;

    /// The median range error is over every detected return of every item, per bounce (not a
    /// mean of the items' medians), and a missed return does not count.
    #[test]
    fn the_median_range_error_pools_the_items() {
        let mut row = EvalRow::new("d");
        let x = Array3::<f32>::zeros((4, 1, 3));
        let truth = Array3::from_shape_vec((2, 1, 3), vec![1.0, 2.0, 3.0, f32::NAN, 5.0, 5.0]).unwrap();
        // item 1: first-return errors 0.1, 0.2, 0.3; second 0.5 and a miss
        let est1 = Array3::from_shape_vec((2, 1, 3), vec![1.1, 2.2, 3.3, f32::NAN, 5.5, f32::NAN]).unwrap();
        // item 2: first-return errors 1.0, 2.0, 3.0; second 1.5 and 2.5
        let est2 = Array3::from_shape_vec((2, 1, 3), vec![2.0, 4.0, 6.0, f32::NAN, 6.5, 7.5]).unwrap();
        row.add(None, &x.view(), Some(&est1.view()), Some(&truth.view()), None, 1e-9, 0.0);
        row.add(None, &x.view(), Some(&est2.view()), Some(&truth.view()), None, 1e-9, 0.0);
        // first: {0.1, 0.2, 0.3, 1, 2, 3} → the upper middle, 1; second: {0.5, 1.5, 2.5} → 1.5
        assert!((row.depth_median_m[0] - 1.0).abs() < 1e-6, "{:?}", row.depth_median_m);
        assert!((row.depth_median_m[1] - 1.5).abs() < 1e-6, "{:?}", row.depth_median_m);
        // within half a bin (1 ns: 3.75 cm): 0 of 6 first returns, 0 of 3 second (truth counts
        // the missed one)
        assert_eq!(row.depth_within_half_bin, vec![0.0, 0.0]);
        assert!(EvalRow::csv(&[row]).lines().nth(1).unwrap().ends_with(",1,1.5,0,0,,,,,,"));
    }

    /// On the pixels every lifetime decoder covers: a decoder that leaves a pixel out takes it
    /// out of the others' common MAE too; the share counts the fluorophore pixels.
    #[test]
    fn the_common_pixels_are_those_every_decoder_estimated() {
        let ns = 1e-9f32;
        // two items of 1×3 pixels; the third pixel of item 1 holds no fluorophore
        let truth = ndarray::Array3::from_shape_vec((2, 1, 3), vec![1.0 * ns, 2.0 * ns, f32::NAN, 3.0 * ns, 4.0 * ns, 5.0 * ns]).unwrap();
        let est = |v: [f32; 3]| ndarray::Array2::from_shape_vec((1, 3), v.to_vec()).unwrap();
        // decoder a: every pixel, errors 0.1, 0.2 | 0.3, 0.4, 0.5 ns
        let a = vec![est([1.1 * ns, 2.2 * ns, 9.0 * ns]), est([3.3 * ns, 4.4 * ns, 5.5 * ns])];
        // decoder b: leaves out the first pixel of each item; errors 1 | 1, 1 ns
        let b = vec![est([f32::NAN, 3.0 * ns, f32::NAN]), est([f32::NAN, 5.0 * ns, 6.0 * ns])];
        let mut rows = vec![EvalRow::new("cube"), EvalRow::new("a"), EvalRow::new("b")];
        common_pixels(&mut rows, &[(1, a), (2, b)], &truth, None);
        assert_eq!(rows[0].lifetime_mae_common_s, None, "a row without lifetimes of its own");
        // common: (item 0, pixel 1), (item 1, pixels 1 and 2): 3 of the 5 fluorophore pixels
        let (ma, mb) = (rows[1].lifetime_mae_common_s.unwrap(), rows[2].lifetime_mae_common_s.unwrap());
        assert!((ma - (0.2 + 0.4 + 0.5) / 3.0 * 1e-9).abs() < 1e-15, "{ma:e}");
        assert!((mb - 1e-9).abs() < 1e-15, "{mb:e}");
        assert_eq!(rows[1].lifetime_common_share, Some(0.6));
        assert_eq!(rows[2].lifetime_common_share, Some(0.6));
    }
}
