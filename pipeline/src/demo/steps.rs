//! The demo's steps: the sensor of a dataset, numbered steps with their wall times, one
//! training, the metric rows, and the frames every decoder decodes for the figures.

use super::*;

pub(super) fn physical_irf() -> Irf {
    Irf::Physical { laser_fwhm_s: DEFAULT_LASER_FWHM_S, tap_tau_s: DEFAULT_TAP_TAU_S }
}

/// The sensor of a dataset's grid with these codes (physical IRF).
pub(super) fn sensor(codes: &Codes, ds: &Dataset) -> Result<Sensor> {
    Ok(Sensor::ideal(codes.clone(), ds.manifest.grid.sampling, physical_irf())?)
}

/// Numbered steps with their wall times.
pub(super) struct Steps<'a> {
    pub(super) obs: &'a dyn Observer,
    pub(super) n: usize,
    pub(super) of: usize,
    pub(super) times: Vec<(String, f64)>,
}

impl Steps<'_> {
    pub(super) fn run<T>(&mut self, what: &str, f: impl FnOnce() -> Result<T>) -> Result<T> {
        self.n += 1;
        self.obs.line(&format!("[{}/{}] {what}", self.n, self.of));
        let t0 = Instant::now();
        let v = f()?;
        self.times.push((what.to_string(), t0.elapsed().as_secs_f64()));
        Ok(v)
    }
}

pub(super) fn cancelled(cancel: &AtomicBool) -> Result<()> {
    if cancel.load(Ordering::SeqCst) {
        bail!("interrupted; rerun the same command to resume");
    }
    Ok(())
}

/// Train (or resume) one run of the plan.
#[allow(clippy::too_many_arguments)]
pub(super) fn train_one(
    t: &TrainPlan,
    plan: &Plan,
    ds: &Dataset,
    ds_dir: &Path,
    codes: &Codes,
    run: &Path,
    obs: &dyn Observer,
    cancel: &AtomicBool,
) -> Result<()> {
    let resume = run.join(CONFIG_FILE).exists();
    let cfg = if resume {
        TrainConfig::load(&run.join(CONFIG_FILE))?
    } else {
        let mut cfg = TrainConfig::for_dataset(model_of(&t.name, ds), ds_dir, ds);
        cfg.run.irf = physical_irf();
        cfg.epochs = t.epochs;
        cfg.seed = plan.request.seed;
        cfg.max_val_items = Some(plan.val_items);
        if let Some(c) = plan.crop {
            cfg.augment = cfg.augment.map(|g| tcsense_train::Augmentation { crop: Some(c), ..g });
        }
        if t.name.starts_with("learned") {
            cfg.learn_codes = Some(LearnCodes::new(codes.constraints, t.epochs));
        }
        if t.name.starts_with("zoo") {
            let Some((zoo_dir, _)) = zoo_entry(ds) else {
                bail!("the plan fine-tunes zoo:{ZOO_ENTRY}, but the zoo no longer holds it (see TCSENSE_ZOO)")
            };
            cfg.init_from = Some(zoo_dir.display().to_string());
        }
        cfg
    };
    // the codes it trains with, as every front end finds them (a resumed learned-codes run
    // stopped before its projection starts from its start codes)
    let start = if resume { tcsense_train::setup::run_codes(run, None, true)? } else { codes.clone() };
    let res = train(&cfg, &start, run, resume, obs.training(), cancel);
    match res {
        Ok(_) => Ok(()),
        Err(TrainError::Cancelled) => {
            bail!("interrupted; the last checkpoint in {} is kept: rerun the same command to resume", run.display())
        }
        Err(e) => Err(e.into()),
    }
}

/// The engine that runs a decoder given by its spec (`tval3`, `KIND:RUN`, `onnx:MODEL`).
pub(super) fn engine(spec: &str) -> &'static str {
    if spec.starts_with("onnx:") {
        "ONNX Runtime"
    } else if spec == names::TVAL3 {
        "Rust (TVAL3)"
    } else if [names::LIFETIME_FIT, names::LIFETIME_FIT_POOLED, names::DEPTH_FIT, names::DEPTH_FIT_POOLED].contains(&spec) {
        "Rust (fit to the taps)"
    } else {
        "burn (flex)"
    }
}

/// A row of a metric table: what every decoder has, and the domain's own metrics `own`.
pub(super) fn result_row(r: &EvalRow, codes: &str, decoder: &str, engine: &str, own: Value) -> Value {
    let mut row = json!({
        "decoder": decoder,
        "codes": codes,
        "engine": engine,
        "items": r.items,
        "mse": r.mse,
        "psnr_db": r.psnr_db,
        "ms_per_frame": r.seconds_per_frame * 1e3,
    });
    if let (Some(row), Value::Object(own)) = (row.as_object_mut(), own) {
        row.extend(own);
    }
    row
}

pub(super) fn lidar_row(r: &EvalRow, codes: &str, decoder: &str, engine: &str) -> Value {
    let own = json!({
        "range_rmse_m": r.depth.iter().map(|d| d.rmse_m).collect::<Vec<_>>(),
        "range_mae_m": r.depth.iter().map(|d| d.mae_m).collect::<Vec<_>>(),
        "detection_pct": r.depth.iter().map(|d| 100.0 * d.detection_rate()).collect::<Vec<_>>(),
    });
    result_row(r, codes, decoder, engine, own)
}

pub(super) fn flim_row(r: &EvalRow, codes: &str, decoder: &str, engine: &str) -> Value {
    let own = json!({
        "lifetime_mae_ns": r.lifetime_mae_s.map(|v| v * 1e9),
        "lifetime_within_02ns_pct": r.lifetime_within_02ns.map(|v| v * 100.0),
    });
    result_row(r, codes, decoder, engine, own)
}

/// Decode one test item of each dataset (with the evaluation's noise for that item) with every
/// decoder and keep the inputs and outputs in `DIR/frames/` as `.npy`; which items, in
/// `DIR/frames/frames.json`.
#[allow(clippy::too_many_arguments)]
pub(super) fn decode_frames(
    dir: &Path,
    lidar: &Dataset,
    flim: &Dataset,
    selected: &Codes,
    learned: &Codes,
    noise: &NoiseParams,
    seed: u64,
    cancel: &AtomicBool,
) -> Result<()> {
    let frames = dir.join("frames");
    let runs_dir = dir.join("runs");
    let ctl = Control::quiet(cancel);
    // the LiDAR frame: the first test item with a return behind a sheet in ≥ 5 % of its pixels
    let depth = lidar.load("test", "depth")?.into_dimensionality::<Ix4>()?;
    let (n, k, fh, fw) = depth.dim();
    let lidar_index = if k > 1 {
        (0..n).find(|&i| depth.slice(ndarray::s![i, 1, .., ..]).iter().filter(|v| v.is_finite()).count() * 20 >= fh * fw).unwrap_or(0)
    } else {
        0
    };
    write_json(&frames.join("frames.json"), &json!({ "lidar_test_index": lidar_index, "flim_test_index": 0 }))?;
    let item = |ds: &Dataset, i: usize| -> Result<Array4<f32>> {
        let x = ds.load("test", "x")?.into_dimensionality::<Ix4>()?;
        Ok(x.slice_axis(Axis(0), ndarray::Slice::from(i..i + 1)).to_owned())
    };
    let jobs: [FrameJob<'_>; 3] = [
        (
            "lidar",
            lidar,
            selected,
            vec![
                ("tval3", names::TVAL3.into()),
                ("admm", format!("{}:{}", names::ADMM_NET, runs_dir.join("admm-lidar").display())),
                ("unet", format!("{}:{}", names::UNET, runs_dir.join("unet-lidar").display())),
            ],
        ),
        ("lidar-learned", lidar, learned, vec![("admm", format!("{}:{}", names::ADMM_NET, runs_dir.join("learned-lidar").display()))]),
        (
            "flim",
            flim,
            selected,
            vec![
                ("tval3", names::TVAL3.into()),
                ("admm", format!("{}:{}", names::ADMM_NET, runs_dir.join("admm-flim").display())),
                ("fit", "lifetime-fit".into()),
            ],
        ),
    ];
    for (tag, ds, codes, decoders) in jobs {
        let a = sensor(codes, ds)?;
        let index = if tag.starts_with("lidar") { lidar_index } else { 0 };
        let x = item(ds, index)?;
        let (_, _, fh, fw) = x.dim();
        let y_path = frames.join(format!("{tag}-y.npy"));
        // the evaluation's noise for this item
        let y = measure_batch(&a.plan(fh, fw)?, &x.view(), Some(noise), derive_seed(seed, index as u64))?;
        write_npy(&y_path, &y.index_axis(Axis(0), 0).to_owned().view())?;
        // the truth, once per dataset (`lidar-learned` shares `lidar`'s)
        let x_path = frames.join(format!("{}-x.npy", tag.split('-').next().unwrap_or(tag)));
        if !x_path.exists() {
            write_npy(&x_path, &x.index_axis(Axis(0), 0).to_owned().view())?;
        }
        for (name, spec) in decoders {
            let out_cube = frames.join(format!("{tag}-{name}.npy"));
            let out_depth = frames.join(format!("{tag}-{name}-depth.npy"));
            let out_lifetime = frames.join(format!("{tag}-{name}-lifetime.npy"));
            if out_cube.exists() || out_depth.exists() || out_lifetime.exists() {
                continue;
            }
            let mut d = open_decoder(&spec, &Tval3Options::default(), &Device::flex())?;
            let out = d.decoder.decode(y.view(), &a, &ctl).map_err(|e| PipelineError::Invalid(format!("{spec}: {e}")))?;
            if let Some(c) = out.cube {
                write_npy(&out_cube, &c.index_axis(Axis(0), 0).to_owned().view())?;
            }
            if let Some(dp) = out.depth {
                write_npy(&out_depth, &dp.index_axis(Axis(0), 0).to_owned().view())?;
            }
            if let Some(l) = out.lifetime {
                write_npy(&out_lifetime, &l.index_axis(Axis(0), 0).to_owned().view())?;
            }
        }
    }
    Ok(())
}

/// One dataset's test frame through decoders: (file tag, dataset, codes, [(name, decoder spec)]).
pub(super) type FrameJob<'a> = (&'a str, &'a Dataset, &'a Codes, Vec<(&'a str, String)>);

/// The photon ladder's ADMM-Net on the selected LiDAR codes, and its rows on the learned codes
/// (deep sensing's ADMM-Net and the fit): the report compares the two ADMM-Nets.
pub(super) const SELECTED_ADMM: &str = "ADMM-Net + peaks";
pub(super) const LEARNED_ADMM: &str = "ADMM-Net + peaks, learned codes";
pub(super) const LEARNED_FIT: &str = "range fit to the taps, 2 returns, learned codes";
/// The photon ladder's rows of the range fit to the taps with one and two returns.
pub(super) const FIT_ONE: &str = "range fit to the taps, 1 return";
pub(super) const FIT_TWO: &str = "range fit to the taps, 2 returns";
/// The photon ladder's row of the Aᵀ + U-Net on the selected codes.
pub(super) const UNET_FIT: &str = "Aᵀ + U-Net + range fit";
/// The photon ladder's row of the range fit pooled by likeness (`depth-fit-pooled`).
pub(super) const POOLED_FIT: &str = "range fit pooled by likeness, 2 returns";
/// The photon ladder's row of the zoo's U-Net on the fit's evidence.
pub(super) const EVIDENCE_UNET: &str = "U-Net on the fit's evidence (zoo, as shipped, its own codes)";

/// The FLIm photon ladder's two code sets with one architecture: the zoo's lifetime network on
/// designed codes and on codes learned with it, each through its own codes.
pub(super) const FLIM_DESIGNED_NET: &str = "lifetime network (zoo), designed codes";
pub(super) const FLIM_LEARNED_NET: &str = "lifetime network (zoo), codes learned with it";

/// The rungs of the demo's photon ladder: the brightest tap's share of the full well.
pub(super) const LADDER: [f64; 4] = [0.8, 0.1, 0.02, 0.005];

/// The photon-efficiency curves of the demo's decoders on their test splits (noise on, no
/// ambient light): LiDAR — the range fit to the taps with one and two returns and pooled by
/// likeness, the ADMM-Net by
/// peaks, the Aᵀ + U-Net (with its range fit), on the selected codes; the same ADMM-Net
/// architecture trained with its codes by deep sensing, and the two-return fit, on the learned
/// codes (both code sets' curves with one decoder architecture); the zoo's U-Net on the fit's
/// evidence as shipped on its own codes; FLIm — the lifetime fit to the taps and the
/// ADMM-Net's cube by the reconvolution fit on the selected codes, and the zoo's lifetime
/// network on the fit's evidence as shipped. Writes `results/photon-lidar.json`,
/// `results/photon-flim.json` (every [`EvalRow`] with its light) and their figures
/// `figures/photon-lidar.png`, `figures/photon-flim.png`; a resumed demo keeps them.
#[allow(clippy::too_many_arguments)]
pub(super) fn photon_curves(
    dir: &Path,
    lidar: &Dataset,
    flim: &Dataset,
    selected: &Codes,
    learned: &Codes,
    runs_dir: &Path,
    lidar_items: usize,
    flim_items: usize,
    noise: &NoiseParams,
    seed: u64,
    obs: &dyn Observer,
    cancel: &AtomicBool,
) -> Result<()> {
    let settings = |items| EvalSettings { split: "test".into(), items: Some(items), noise: Some(*noise), seed, sensor: None, sbr: None };
    let on_item = |label: &str, done: usize, of: usize| obs.items(label.rsplit('/').next().unwrap_or(label), done, of);
    let run_of = |kind: &str, name: &str| format!("{kind}:{}", runs_dir.join(name).display());
    // (label, decoder) evaluated on `a`, the rows renamed to their labels
    let ladder = |ds: &Dataset, a: &Sensor, decoders: &[(&str, String)], items: usize| -> Result<Vec<EvalRow>> {
        let mut dec = decoders
            .iter()
            .map(|(_, spec)| open_decoder(spec, &Tval3Options::default(), &Device::flex()))
            .collect::<std::result::Result<Vec<_>, _>>()?;
        let mut rows = tcsense_infer::eval::evaluate_ladder(ds, a, &mut dec, &settings(items), &LADDER, &on_item, cancel)?;
        for r in &mut rows {
            if let Some((label, _)) = decoders.iter().find(|(_, spec)| *spec == r.decoder) {
                r.decoder = label.to_string();
            }
        }
        Ok(rows)
    };
    let figures = dir.join("figures");
    std::fs::create_dir_all(&figures).with_context(|| figures.display().to_string())?;
    let lidar_json = dir.join("results/photon-lidar.json");
    if !lidar_json.exists() {
        let a = sensor(selected, lidar)?;
        let decoders = [
            (FIT_ONE, format!("{}:1", names::DEPTH_FIT)),
            (FIT_TWO, names::DEPTH_FIT.to_string()),
            (POOLED_FIT, names::DEPTH_FIT_POOLED.to_string()),
            (SELECTED_ADMM, run_of(names::ADMM_NET, "admm-lidar")),
            (UNET_FIT, run_of(names::UNET, "unet-lidar")),
        ];
        let mut rows = ladder(lidar, &a, &decoders, lidar_items)?;
        let on_learned = sensor(learned, lidar)?;
        let learned_decoders = [(LEARNED_FIT, names::DEPTH_FIT.to_string()), (LEARNED_ADMM, run_of(names::ADMM_NET, "learned-lidar"))];
        rows.extend(ladder(lidar, &on_learned, &learned_decoders, lidar_items)?);
        if let Some((zoo_dir, _)) = zoo_entry_named(ZOO_EVIDENCE_UNET, lidar) {
            let own = sensor(&Codes::load(&zoo_dir.join(CODES_FILE))?, lidar)?;
            let shipped = [(EVIDENCE_UNET, format!("{}:{}", names::UNET, zoo_dir.display()))];
            rows.extend(ladder(lidar, &own, &shipped, lidar_items)?);
        }
        let codes = [("selected", a.nominal()), ("learned", on_learned.nominal())];
        tcsense_infer::curves::range_curve(&figures.join("photon-lidar.png"), &rows, &codes, noise, None)?;
        let bin_m = C * a.nominal().bin_width_s() / 2.0;
        write_json(
            &lidar_json,
            &json!({ "split": "test", "items": lidar_items, "noise_seed": seed, "ladder": LADDER, "bin_m": bin_m, "rows": rows }),
        )?;
    }
    let flim_json = dir.join("results/photon-flim.json");
    if !flim_json.exists() {
        let a = sensor(selected, flim)?;
        let decoders = [
            ("lifetime fit to the taps", names::LIFETIME_FIT.to_string()),
            ("lifetime fit pooled by likeness", names::LIFETIME_FIT_POOLED.to_string()),
            ("ADMM-Net + reconvolution fit", run_of(names::ADMM_NET, "admm-flim")),
        ];
        let mut rows = ladder(flim, &a, &decoders, flim_items)?;
        if let Some((zoo_dir, _)) = zoo_entry_named(ZOO_EVIDENCE_LIFETIME, flim) {
            let own = sensor(&Codes::load(&zoo_dir.join(CODES_FILE))?, flim)?;
            let shipped = [(
                "lifetime network on the fit's evidence pooled by likeness (zoo, as shipped, its own codes)",
                format!("{}:{}", names::LIFETIME, zoo_dir.display()),
            )];
            rows.extend(ladder(flim, &own, &shipped, flim_items)?);
        }
        // one architecture on both code sets: the zoo's lifetime network on designed codes and
        // on codes learned with it, each through its own codes
        let mut pair = Vec::new();
        if let (Some((designed, _)), Some((learned, _))) =
            (zoo_entry_named(ZOO_FLIM_DESIGNED, flim), zoo_entry_named(ZOO_FLIM_LEARNED, flim))
        {
            for (label, dir, set) in [(FLIM_DESIGNED_NET, designed, "designed"), (FLIM_LEARNED_NET, learned, "learned")] {
                let own = sensor(&Codes::load(&dir.join(CODES_FILE))?, flim)?;
                rows.extend(ladder(flim, &own, &[(label, format!("{}:{}", names::LIFETIME, dir.display()))], flim_items)?);
                pair.push((set, own));
            }
        }
        let mut codes = vec![("selected", a.nominal())];
        codes.extend(pair.iter().map(|(set, s)| (*set, s.nominal())));
        tcsense_infer::curves::lifetime_curve(&figures.join("photon-flim.png"), &rows, &codes, a.spec().sampling().k(), noise, None)?;
        write_json(&flim_json, &json!({ "split": "test", "items": flim_items, "noise_seed": seed, "ladder": LADDER, "rows": rows }))?;
    }
    Ok(())
}

/// Frames of the stream each deployed decoder is timed on (`speed_against_accuracy`).
pub(super) const SPEED_FRAMES: usize = 10;

/// The photon ladder's LiDAR decoders as deployed — the fits, and the exported networks through
/// ONNX Runtime with the fits `tcsense infer` runs around them (`onnx:` decoders) — timed on a
/// stream of [`SPEED_FRAMES`] noisy frames at `size` (the test scenes mirrored to it, signal at
/// the ladder's first rung), `rounds` interleaved rounds, beside their errors on the ladder
/// (`results/photon-lidar.json`, the same networks in burn: the same products). The zoo's U-Net
/// on the fit's evidence is exported (`onnx/zoo-evidence-lidar.onnx`) and timed through its own
/// codes. Writes `results/speed-lidar.json` and `figures/speed-accuracy-lidar.png`; a resumed
/// demo keeps them.
#[allow(clippy::too_many_arguments)]
pub(super) fn speed_against_accuracy(
    dir: &Path,
    lidar: &Dataset,
    selected: &Codes,
    size: (usize, usize),
    rounds: usize,
    noise: &NoiseParams,
    seed: u64,
    cancel: &AtomicBool,
) -> Result<()> {
    let out = dir.join("results/speed-lidar.json");
    if out.exists() {
        return Ok(());
    }
    let photon = read_json(&dir.join("results/photon-lidar.json"))?;
    let bin_m = photon["bin_m"].as_f64().unwrap_or(f64::NAN);
    let rows = photon["rows"].as_array().cloned().unwrap_or_default();
    let onnx = |name: &str| format!("onnx:{}", dir.join("onnx").join(format!("{name}.onnx")).display());
    let first = NoiseParams { signal_fraction: LADDER[0], ..*noise };
    // (label of the photon ladder's row, decoder as deployed) on one sensor, timed together
    let timed = |a: &Sensor, decoders: &[(&str, String)]| -> Result<Vec<tcsense_infer::speed::DecoderSpeed>> {
        let mut dec = decoders
            .iter()
            .map(|(label, spec)| {
                let mut d = open_decoder(spec, &Tval3Options::default(), &Device::flex())?;
                d.label = label.to_string();
                Ok(d)
            })
            .collect::<Result<Vec<_>>>()?;
        let y = tcsense_infer::speed::tiled_frames(lidar, "test", a, size, SPEED_FRAMES, &first, seed)?;
        Ok(tcsense_infer::speed::stream_speed(&mut dec, a, &y.view(), rounds, &|_, _| {}, cancel)?)
    };
    let mut speeds = timed(
        &sensor(selected, lidar)?,
        &[
            (FIT_ONE, format!("{}:1", names::DEPTH_FIT)),
            (FIT_TWO, names::DEPTH_FIT.to_string()),
            (POOLED_FIT, names::DEPTH_FIT_POOLED.to_string()),
            (SELECTED_ADMM, onnx("admm-lidar")),
            (UNET_FIT, onnx("unet-lidar")),
        ],
    )?;
    if let Some((zoo_dir, _)) = zoo_entry_named(ZOO_EVIDENCE_UNET, lidar) {
        let model = dir.join("onnx/zoo-evidence-lidar.onnx");
        if !model.exists() {
            export_to(&runs::load(&zoo_dir, &Device::flex())?, ExportOptions::default(), &model)?;
        }
        let own = sensor(&Codes::load(&zoo_dir.join(CODES_FILE))?, lidar)?;
        speeds.extend(timed(&own, &[(EVIDENCE_UNET, onnx("zoo-evidence-lidar"))])?);
    }
    // each decoder's median first-return error (bins) at every rung, from the ladder's rows
    let error_at = |label: &str, level: f64| -> f64 {
        rows.iter()
            .find(|r| r["decoder"] == label && r["light"]["signal_fraction"].as_f64() == Some(level))
            .and_then(|r| r["depth_median_m"][0].as_f64())
            .map_or(f64::NAN, |m| m / bin_m)
    };
    let errors: Vec<Vec<f64>> = speeds.iter().map(|s| LADDER.iter().map(|&l| error_at(&s.decoder, l)).collect()).collect();
    let series: Vec<Series> = speeds
        .iter()
        .zip(&errors)
        .map(|(s, e)| Series { label: s.decoder.clone(), points: e.iter().map(|&e| (s.frames_per_s, e)).collect() })
        .collect();
    let (h, w) = size;
    let figures = dir.join("figures");
    std::fs::create_dir_all(&figures).with_context(|| figures.display().to_string())?;
    plot::speed_accuracy(
        &figures.join("speed-accuracy-lidar.png"),
        &format!("Deployed speed against accuracy ({h}x{w} frames, no ambient light; dots at each signal level)"),
        &format!("frames per second ({h}x{w}, whole decoder, one frame per call)"),
        "median first-return error (bins)",
        &series,
        &LADDER.iter().map(|l| l.to_string()).collect::<Vec<_>>(),
    )?;
    write_json(
        &out,
        &json!({ "frame": [h, w], "frames": SPEED_FRAMES, "rounds": rounds, "signal_fraction": LADDER[0], "ladder": LADDER, "speeds": speeds, "error_bins": errors }),
    )
}
