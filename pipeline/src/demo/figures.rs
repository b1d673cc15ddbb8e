//! The demo's figures: codes, waveforms, depth and lifetime maps, point clouds and the
//! training curves, drawn from what the steps wrote.

use super::*;

pub(super) fn read3(path: &Path) -> Result<Array3<f32>> {
    read_npy(path)?.into_dimensionality::<Ix3>().with_context(|| format!("{}: expected a rank-3 array", path.display()))
}

/// Three distinct pixels worth looking at: `first` where it exists, the centre, `last`, and
/// the quarter points where those coincide.
pub(super) fn pick_pixels(h: usize, w: usize, first: Option<(usize, usize)>, last: Option<(usize, usize)>) -> Vec<(usize, usize)> {
    let mut v: Vec<(usize, usize)> = Vec::new();
    for p in [first, Some((h / 2, w / 2)), last, Some((h / 4, w / 4)), Some((3 * h / 4, 3 * w / 4))].into_iter().flatten() {
        if !v.contains(&p) && v.len() < 3 {
            v.push(p);
        }
    }
    v
}

/// Which figures were drawn (file names under `figures/`).
pub(super) struct Figures {
    pub(super) files: Vec<&'static str>,
}

pub(super) fn draw_figures(dir: &Path, lidar: &Dataset, flim: &Dataset, selected: &Codes, learned: &Codes) -> Result<Figures> {
    let f = dir.join("figures");
    let fr = dir.join("frames");
    let mut files = Vec::new();
    let mut out = |name: &'static str| {
        files.push(name);
        f.join(name)
    };
    // the photon-efficiency curves, drawn by their step beside their numbers
    for name in ["photon-lidar.png", "photon-flim.png"] {
        if !out(name).exists() {
            bail!("{}: missing (the photon-efficiency step draws it)", f.join(name).display());
        }
    }
    if !out("speed-accuracy-lidar.png").exists() {
        bail!("{}: missing (the deployed speed step draws it)", f.join("speed-accuracy-lidar.png").display());
    }
    // codes
    plot::codes(&out("codes-random.png"), "random codes", &Codes::load(&dir.join("codes/random.json"))?)?;
    plot::codes(&out("codes-selected.png"), "selected codes (designed for range identifiability)", selected)?;
    plot::codes(&out("codes-best-mse.png"), "the best random codes by TVAL3 MSE", &Codes::load(&dir.join("codes/best-mse.json"))?)?;
    let ident = read_json(&dir.join("results/identifiability.json"))?;
    crate::identifiability::draw(&ident, &out("identifiability-range.png"), &out("identifiability-lifetime.png"))?;
    plot::codes(&out("codes-learned.png"), "learned codes (deep sensing, projected)", learned)?;
    let sel = read_json(&dir.join("results/selection.json"))?;
    let pts: Vec<(f64, f64)> = sel["candidates"]
        .as_array()
        .map(|a| a.iter().filter_map(|c| Some((c["seed"].as_f64()?, c["mse"].as_f64()?))).collect())
        .unwrap_or_default();
    plot::log_chart(
        &out("selection.png"),
        "Code selection: TVAL3 MSE of each random candidate (noise-free)",
        "candidate seed",
        "MSE of the reconstruction",
        &[Series { label: "candidate".into(), points: pts }],
    )?;

    // tap images of the LiDAR frame
    let y = read3(&fr.join("lidar-y.npy"))?;
    let taps: Vec<(String, Array2<f32>)> = (0..y.dim().0).map(|m| (format!("tap {m}"), y.index_axis(Axis(0), m).to_owned())).collect();
    let panels: Vec<(&str, ndarray::ArrayView2<f32>)> = taps.iter().map(|(n, a)| (n.as_str(), a.view())).collect();
    plot::maps(&out("taps.png"), "Tap images of the LiDAR test frame (noisy, selected codes)", &panels, "tap signal (units of A·x)", None)?;

    // LiDAR: waveforms, depth maps, errors, point clouds
    let bin_w = lidar.manifest.bin_width_s;
    let range_m = C * bin_w * lidar.manifest.bins as f64 / 2.0;
    let x = read3(&fr.join("lidar-x.npy"))?;
    let (_, h, w) = x.dim();
    let index = read_json(&fr.join("frames.json"))?["lidar_test_index"].as_u64().unwrap_or(0) as usize;
    let truth_d = lidar.load("test", "depth")?.into_dimensionality::<Ix4>()?.index_axis(Axis(0), index).to_owned();
    let tv = read3(&fr.join("lidar-tval3.npy"))?;
    let admm = read3(&fr.join("lidar-admm.npy"))?;
    let admm_l = read3(&fr.join("lidar-learned-admm.npy"))?;
    let unet_d = read3(&fr.join("lidar-unet-depth.npy"))?;
    let two = truth_d.dim().0 > 1;
    let second = if two {
        truth_d
            .index_axis(Axis(0), 1)
            .indexed_iter()
            .filter(|(_, v)| v.is_finite())
            .min_by_key(|((r, c), _)| r.abs_diff(h / 2) + c.abs_diff(w / 2))
            .map(|(p, _)| p)
    } else {
        None
    };
    let far =
        truth_d.index_axis(Axis(0), 0).indexed_iter().filter(|(_, v)| v.is_finite()).max_by(|a, b| a.1.total_cmp(b.1)).map(|(p, _)| p);
    let pixels = pick_pixels(h, w, second, far);
    plot::waveforms(
        &out("waveforms-lidar.png"),
        &[("truth", x.view()), ("TVAL3", tv.view()), ("ADMM-Net", admm.view()), ("ADMM-Net, learned codes", admm_l.view())],
        &pixels,
        Some(bin_w * 1e9),
    )?;
    let peaks = PeakOptions { max_peaks: 2, ..Default::default() };
    let d_tv = depth_map(&tv.view(), bin_w, &peaks).0;
    let d_admm = depth_map(&admm.view(), bin_w, &peaks).0;
    let k = truth_d.dim().0.min(2);
    let mut panels: Vec<(String, Array2<f32>)> = Vec::new();
    let mut errors: Vec<(String, Array2<f32>)> = Vec::new();
    for b in 0..k {
        let t = truth_d.index_axis(Axis(0), b).to_owned();
        panels.push((format!("truth, return {}", b + 1), t.clone()));
        for (name, d) in [("TVAL3", &d_tv), ("ADMM-Net", &d_admm), ("Aᵀ + U-Net", &unet_d)] {
            let est = if b < d.dim().0 { d.index_axis(Axis(0), b).to_owned() } else { Array2::from_elem((h, w), f32::NAN) };
            let err = ndarray::Zip::from(&est)
                .and(&t)
                .map_collect(|&e, &t| if e.is_finite() && t.is_finite() { (e - t).abs() } else { f32::NAN });
            panels.push((format!("{name}, return {}", b + 1), est));
            errors.push((format!("{name}, return {}", b + 1), err));
        }
    }
    let pv: Vec<(&str, ndarray::ArrayView2<f32>)> = panels.iter().map(|(n, a)| (n.as_str(), a.view())).collect();
    plot::maps(
        &out("depth.png"),
        "Range of the two returns: truth and each decoder (grey: no return)",
        &pv,
        "range (m)",
        Some((0.0, range_m)),
    )?;
    let ev: Vec<(&str, ndarray::ArrayView2<f32>)> = errors.iter().map(|(n, a)| (n.as_str(), a.view())).collect();
    let emax = errors.iter().flat_map(|(_, a)| a.iter().copied()).filter(|v| v.is_finite()).fold(0f32, f32::max).max(1e-3) as f64;
    plot::maps(
        &out("depth-error.png"),
        "Absolute range error where truth and estimate have a return",
        &ev,
        "|range error| (m)",
        Some((0.0, emax.min(range_m / 4.0))),
    )?;
    let clouds = [
        ("truth", point_cloud(&truth_d.view(), FOV_DEG)),
        ("ADMM-Net (peaks of the cube)", point_cloud(&d_admm.view(), FOV_DEG)),
        ("Aᵀ + U-Net (direct depth)", point_cloud(&unet_d.view(), FOV_DEG)),
    ];
    let clouds: Vec<(&str, Vec<[f32; 4]>)> = clouds.into_iter().collect();
    plot::point_clouds(&out("point-cloud.png"), "Point clouds of the test frame (camera coordinates)", &clouds)?;

    // FLIm: waveforms, lifetime maps, phasors
    let fbin = flim.manifest.bin_width_s;
    let fx = read3(&fr.join("flim-x.npy"))?;
    let (_, fh, fw) = fx.dim();
    let ftv = read3(&fr.join("flim-tval3.npy"))?;
    let fadmm = read3(&fr.join("flim-admm.npy"))?;
    let truth_tau = flim.load("test", "lifetime")?.into_dimensionality::<Ix3>()?.index_axis(Axis(0), 0).to_owned();
    let short = truth_tau.indexed_iter().filter(|(_, v)| v.is_finite() && **v > 0.0).min_by(|a, b| a.1.total_cmp(b.1)).map(|(p, _)| p);
    let long = truth_tau.indexed_iter().filter(|(_, v)| v.is_finite() && **v > 0.0).max_by(|a, b| a.1.total_cmp(b.1)).map(|(p, _)| p);
    let pixels = pick_pixels(fh, fw, short, long);
    plot::waveforms(
        &out("waveforms-flim.png"),
        &[("truth", fx.view()), ("TVAL3", ftv.view()), ("ADMM-Net", fadmm.view())],
        &pixels,
        Some(fbin * 1e9),
    )?;
    // the reconvolution fit (IRF fitted) of each cube, the fit to the taps as it was decoded
    let lt = |c: &Array3<f32>| {
        tcsense_fits::lifetime_cube::fit_cube(&c.view(), fbin, &tcsense_fits::lifetime_cube::FitOptions::default())
            .lifetimes
            .index_axis(Axis(0), 0)
            .to_owned()
    };
    let (tau_x, tau_tv, tau_admm) = (lt(&fx), lt(&ftv), lt(&fadmm));
    let tau_fit = read3(&fr.join("flim-fit-lifetime.npy"))?.index_axis(Axis(0), 0).to_owned();
    let ns = |a: &Array2<f32>| a.mapv(|v| v * 1e9);
    let truth_ns = truth_tau.mapv(|v| if v > 0.0 { v * 1e9 } else { f32::NAN });
    let maps = [
        ("truth (generator)", truth_ns),
        ("fit to the true cube", ns(&tau_x)),
        ("TVAL3 + fit", ns(&tau_tv)),
        ("ADMM-Net + fit", ns(&tau_admm)),
        ("fit to the taps", ns(&tau_fit)),
    ];
    let hi = maps[0].1.iter().copied().filter(|v| v.is_finite()).fold(0f32, f32::max).max(0.5) as f64 * 1.2;
    let mv: Vec<(&str, ndarray::ArrayView2<f32>)> = maps.iter().map(|(n, a)| (*n, a.view())).collect();
    plot::maps(
        &out("lifetime.png"),
        "Fluorescence lifetime map of one test frame (grey: no fit)",
        &mv,
        "lifetime τ (ns)",
        Some((0.0, hi)),
    )?;
    let phasors = |x: &Array3<f32>| -> Vec<(f64, f64)> {
        let p = referenced_phasors(&x.view(), 0.02);
        (0..fh * fw).map(|i| (p[(0, i / fw, i % fw)] as f64, p[(1, i / fw, i % fw)] as f64)).collect()
    };
    let period = fbin * flim.manifest.bins as f64;
    plot::phasor(
        &out("phasor.png"),
        &format!("Phasors of the test frame (first harmonic, period {:.2} ns)", period * 1e9),
        &[("truth", phasors(&fx)), ("TVAL3", phasors(&ftv)), ("ADMM-Net", phasors(&fadmm))],
        period,
    )?;

    // training curves
    let runs_dir = dir.join("runs");
    let mut lidar_runs =
        vec![("ADMM-Net, selected codes", runs_dir.join("admm-lidar")), ("ADMM-Net, learned codes", runs_dir.join("learned-lidar"))];
    if runs_dir.join("zoo-lidar").join(tcsense_train::run_dir::METRICS_FILE).exists() {
        lidar_runs.push(("ADMM-Net from the zoo, fine-tuned", runs_dir.join("zoo-lidar")));
    }
    training_figure(&out("training-lidar.png"), &lidar_runs)?;
    training_figure(&out("training-unet.png"), &[("Aᵀ + U-Net", runs_dir.join("unet-lidar"))])?;
    training_figure(&out("training-flim.png"), &[("ADMM-Net, FLIm", runs_dir.join("admm-flim"))])?;
    Ok(Figures { files })
}

/// The epochs of a run, a learned-codes run's relaxed phase (`RUN/relaxed/`) first, its
/// fine-tuning on the projected codes continuing the epoch, step and time count.
pub(super) fn run_rows(run: &Path) -> Result<Vec<tcsense_train::EpochMetrics>> {
    use tcsense_train::run_dir::{read_rows, METRICS_FILE};
    let relaxed = run.join("relaxed").join(METRICS_FILE);
    let mut rows = if relaxed.exists() { read_rows(&relaxed, usize::MAX)? } else { Vec::new() };
    let (e0, s0, t0) = rows.last().map_or((0, 0, 0.0), |m| (m.epoch, m.step, m.seconds));
    for mut m in read_rows(&run.join(METRICS_FILE), usize::MAX)? {
        m.epoch += e0;
        m.step += s0;
        m.seconds += t0;
        rows.push(m);
    }
    Ok(rows)
}

pub(super) fn training_figure(path: &Path, runs: &[(&str, PathBuf)]) -> Result<()> {
    let (mut loss, mut val) = (Vec::new(), Vec::new());
    let mut val_name = String::new();
    for (label, r) in runs {
        let rows = run_rows(r)?;
        val_name = rows.first().and_then(|m| m.val.first()).map(|(n, _)| n.clone()).unwrap_or_default();
        loss.push(Series { label: label.to_string(), points: rows.iter().map(|m| (m.epoch as f64, m.train_loss)).collect() });
        val.push(Series { label: label.to_string(), points: rows.iter().map(|m| (m.epoch as f64, m.get(&val_name))).collect() });
    }
    let label = match val_name.as_str() {
        "val_mse" => "validation MSE of the cube",
        "val_depth_rmse_m" => "validation range RMSE of the returns (m)",
        _ => "validation metric",
    };
    plot::training_curves(path, &loss, &val, label)?;
    Ok(())
}
