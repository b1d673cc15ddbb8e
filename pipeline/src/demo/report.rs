//! The demo's report page: the metric tables, the findings read off them and the figures.

use super::*;

/// A table row per entry of `results["rows"]` (the parsed `file`): the `text` fields as they
/// are, then each `(pointer into the row, format)` as a sourced number.
pub(super) fn result_rows(file: &str, results: &Value, text: &[&str], numbers: &[(&str, Format)]) -> Vec<Vec<Cell>> {
    let rows = results["rows"].as_array().map_or(0, |r| r.len());
    (0..rows)
        .map(|i| {
            let row = &results["rows"][i];
            let mut cells: Vec<Cell> = text.iter().map(|k| Cell::text(row[*k].as_str().unwrap_or(""))).collect();
            cells.extend(numbers.iter().map(|&(k, f)| Cell::from_json(file, results, &format!("/rows/{i}/{k}"), f)));
            cells
        })
        .collect()
}

/// One sentence per metric (JSON pointer into a row, label, format, unit): which row of
/// `results` has the lowest value and what TVAL3 gets, read from the results themselves so
/// the text follows whatever the run measured.
pub(super) fn findings(results: &Value, metrics: &[(&str, &str, Format, &str)]) -> String {
    let rows = results["rows"].as_array().cloned().unwrap_or_default();
    let name = |r: &Value| {
        format!(
            "{} ({} codes, {})",
            r["decoder"].as_str().unwrap_or(""),
            r["codes"].as_str().unwrap_or("selected"),
            r["engine"].as_str().unwrap_or("")
        )
    };
    let mut out = Vec::new();
    for &(ptr, label, format, unit) in metrics {
        let val = |r: &Value| r.pointer(&format!("/{ptr}")).and_then(Value::as_f64).filter(|v| v.is_finite());
        let show = |v: f64| format!("{}{unit}", format.show(Some(v)));
        let best = rows.iter().filter_map(|r| val(r).map(|v| (r, v))).min_by(|a, b| a.1.total_cmp(&b.1));
        let tval3 = rows.iter().find(|r| r["decoder"] == "TVAL3").and_then(val);
        if let Some((r, v)) = best {
            let vs = match tval3 {
                Some(t) if r["decoder"] != "TVAL3" => format!(" against TVAL3's {}", show(t)),
                _ => String::new(),
            };
            out.push(format!("Lowest {label}: {}, {}{vs}.", name(r), show(v)));
        }
    }
    out.join(" ")
}

pub(super) fn read_json(path: &Path) -> Result<Value> {
    serde_json::from_slice(&std::fs::read(path).with_context(|| format!("cannot read {}", path.display()))?)
        .with_context(|| format!("{}: not JSON", path.display()))
}

/// The code memory's settings (`registers.json`'s fields but the channel map) as a table.
fn registers_table(r: &Value, src: &str) -> Table {
    let text = |v: &Value| match v {
        Value::String(s) => s.clone(),
        Value::Null => "–".into(),
        other => other.to_string(),
    };
    let c = &r["constraints"];
    let mut constraints = Vec::new();
    if c["tap"].as_bool() == Some(true) {
        constraints.push("tap".to_string());
    }
    if let Some(h) = c["hamming"].as_u64() {
        constraints.push(format!("Hamming ≤ {h}"));
    }
    if let Some(w) = c["window"].as_u64() {
        constraints.push(format!("runs ≥ {w} masks"));
    }
    let block = match (r["block"][0].as_u64(), r["block"][1].as_u64()) {
        (Some(h), Some(w)) => format!("{h}×{w}"),
        _ => "–".into(),
    };
    let row = |name: &str, value: String| vec![Cell::text(name), Cell::text(value)];
    Table {
        caption: format!("Code-memory registers of the learned set ({src})"),
        headers: vec!["register".into(), "value".into()],
        rows: vec![
            row("ECLEN (L/8 − 1)", text(&r["ECLEN"])),
            row("masks per cycle L", text(&r["length"])),
            row(
                "channels",
                match (r["channel_count"].as_u64(), r["taps"].as_u64().filter(|&t| t > 0)) {
                    (Some(c), Some(t)) => format!("{c} ({} subpixels × {t} taps)", c / t),
                    _ => text(&r["channel_count"]),
                },
            ),
            row("pixel block", block),
            row("bytes per channel", text(&r["bytes_per_channel"])),
            row("modulation clock", r["clock_hz"].as_f64().map_or("–".into(), |hz| format!("{} MHz", hz / 1e6))),
            row("drain tap", text(&r["drain"])),
            row("constraints", if constraints.is_empty() { "none".into() } else { constraints.join(", ") }),
            row("bit order", text(&r["bit_order"])),
            row("combined image", format!("{}: {}", text(&r["combined_file"]), text(&r["combined_layout"]))),
        ],
    }
}

/// Where each code channel lives in the code memory (`registers.json`'s `channels`).
fn channels_table(r: &Value, src: &str) -> Table {
    let rows = r["channels"]
        .as_array()
        .map(|chs| {
            chs.iter()
                .map(|c| {
                    let n = |k: &str| c[k].as_u64().map_or("–".into(), |v| v.to_string());
                    vec![
                        Cell::text(n("channel")),
                        Cell::text(format!("{} (row {}, column {})", n("subpixel"), n("row"), n("col"))),
                        Cell::text(n("tap")),
                        Cell::text(c["file"].as_str().unwrap_or("–")),
                        Cell::text(n("offset")),
                    ]
                })
                .collect()
        })
        .unwrap_or_default();
    Table {
        caption: format!("Code channels of the learned set ({src}: channels)"),
        headers: ["channel", "subpixel", "tap", "file", "offset in the combined image (bytes)"].map(String::from).to_vec(),
        rows,
    }
}

pub(super) fn build_report(dir: &Path, plan: &Plan, figs: &Figures, times: &[Value], total_s: f64) -> Result<Report> {
    let fig = |name: &str, caption: &str| -> Block {
        debug_assert!(figs.files.contains(&name), "figure {name} not drawn");
        Block::Figure { src: format!("figures/{name}"), caption: caption.into() }
    };
    let r = &plan.request;
    let mut sections = Vec::new();

    // overview
    let mut training_rows = Vec::new();
    for t in &plan.trainings {
        let rows = run_rows(&dir.join("runs").join(&t.name))?;
        let last = rows.last();
        training_rows.push(vec![
            Cell::text(&t.title),
            Cell::text(format!("runs/{}", t.name)),
            Cell::text(last.map_or("0".into(), |m| m.epoch.to_string())),
            Cell::text(last.map_or("0".into(), |m| m.step.to_string())),
            Cell::text(format!("{:.1}", t.step_ms)),
            Cell::text(format!("{:.0}", last.map_or(0.0, |m| m.seconds))),
            Cell::text(last.and_then(|m| m.val.first()).map_or("–".into(), |(n, v)| {
                format!(
                    "{} {}",
                    n.trim_start_matches("val_").replace('_', " "),
                    if n.ends_with("_m") { format!("{v:.3} m") } else { format!("{v:.3e}") }
                )
            })),
        ]);
    }
    let mut step_rows: Vec<Vec<Cell>> = times
        .iter()
        .map(|t| {
            vec![Cell::text(t["step"].as_str().unwrap_or("")), Cell::text(format!("{:.1}", t["seconds"].as_f64().unwrap_or(f64::NAN)))]
        })
        .collect();
    step_rows.push(vec![Cell::text("this run of tcsense demo, in all"), Cell::text(format!("{total_s:.1}"))]);
    sections.push(Section {
        id: "overview".into(),
        title: "What was done".into(),
        blocks: vec![
            Block::Text(format!(
                "The prototype sensor of the paper (4 taps, 2×2 pixel blocks, L = 32 masks at 607 MHz, constraints tap + Hamming H = 2 + window W = 2, physical IRF) was simulated on two synthetic datasets with randomised scenes: LiDAR with multipath ({} scenes of {}×{} pixels, T = 32 bins of 51.5 ps) and fluorescence lifetime imaging ({} scenes, heterodyne K = 8, T = 256). Codes were drawn at random under the constraints, the best of {} by TVAL3 was kept for comparison (the paper's selection), the selected codes were designed for range identifiability (no alias, the smallest worst-case range bound; see Exposure codes), and codes were also learned jointly with an ADMM-Net (deep sensing, with a hinge on the range alias in the loss) and projected exactly onto the constraints; both sets are exported to the sensor's code memory. TVAL3, ADMM-Net and the Aᵀ + U-Net depth decoder reconstruct the same noisy tap images (shot and read noise, full well 20 000 e⁻, σ 40 e⁻); the trained decoders are exported to ONNX and run again through ONNX Runtime. Budget: {} minutes{}.",
                r.lidar_scenes, r.size[0], r.size[1], r.flim_scenes, plan.candidates, r.budget_minutes, if r.quick { " (--quick)" } else { "" }
            )),
            Block::Table(Table { caption: "Trainings (epochs sized to the budget from a measured step time; batch 2, Adam, lr 10⁻³, augmentation on)".into(), headers: vec!["network".into(), "run directory".into(), "epochs".into(), "steps".into(), "ms per step (planned)".into(), "training time (s)".into(), "last validation".into()], rows: training_rows }),
        ],
    });
    let run_log = Section {
        id: "run".into(),
        title: "This run".into(),
        blocks: vec![
            Block::Table(Table { caption: "Steps of this run of the demo and their wall time (a resumed run times only what it did)".into(), headers: vec!["step".into(), "seconds".into()], rows: step_rows }),
            Block::Text(format!("Everything this report shows is in {}: plan.json (the settings and the epochs sized to the budget), results/*.json (every number of the tables), runs/ (the training runs: config.json, metrics.csv, checkpoints, model.bpk, codes.json), onnx/, code-memory/, codes/, the datasets lidar/ and flim/, frames/ (the tap images and reconstructions of the frames shown, .npy) and figures/.", dir.display())),
        ],
    };

    sections.push(codes_section(dir, &fig)?);
    sections.push(taps_section(&fig));
    sections.push(lidar_section(dir, plan, &fig)?);
    sections.push(flim_section(dir, plan, &fig)?);
    sections.push(training_section(&fig));
    sections.push(bringup_section(dir)?);
    sections.push(deployment_section(dir, plan, &fig)?);
    sections.push(run_log);
    // results first: what was done, the two applications, then how (codes, tap images,
    // training), deployment and the run's log
    let order = ["overview", "lidar", "flim", "codes", "taps", "training", "deployment", "run"];
    sections.sort_by_key(|s| order.iter().position(|o| *o == s.id).unwrap_or(order.len()));
    let version = env!("CARGO_PKG_VERSION");
    Ok(Report {
        title: "tcsense demo report".into(),
        subtitle: format!("tcsense {version}; prototype sensor 4 taps, 2×2, L = 32, 607 MHz; {}×{} frames; budget {} min; seed {}; written by `tcsense demo{}`", r.size[0], r.size[1], r.budget_minutes, r.seed, if r.quick { " --quick" } else { "" }),
        sections,
    })
}

/// The exposure codes: the sets, the selection by TVAL3, identifiability, the projection and the code memory.
fn codes_section(dir: &Path, fig: &dyn Fn(&str, &str) -> Block) -> Result<Section> {
    // codes
    let sel = read_json(&dir.join("results/selection.json"))?;
    let ident = read_json(&dir.join("results/identifiability.json"))?;
    let n_cand = sel["candidates"].as_array().map_or(0, |a| a.len());
    let mut cand_rows = Vec::new();
    for i in 0..n_cand {
        cand_rows.push(vec![
            Cell::from_json("results/selection.json", &sel, &format!("/candidates/{i}/seed"), Format::Fixed(0)),
            Cell::from_json("results/selection.json", &sel, &format!("/candidates/{i}/mse"), Format::Sci(3)),
        ]);
    }
    let regs_src = "code-memory/learned/registers.json";
    let regs = read_json(&dir.join(regs_src)).unwrap_or(Value::Null);
    let proj = read_json(&dir.join("runs/learned-lidar/relaxed/projection.json"))?;
    let psrc = "runs/learned-lidar/relaxed/projection.json";
    let projection = Table {
        caption: "Projection of the learned codes onto the constraints (the relaxed codes' hard version, and the bits the exact projection changed)".into(),
        headers: ["solver", "violations before (tap / Hamming / window)", "bits changed", "of bits"].map(String::from).to_vec(),
        rows: vec![vec![
            Cell::text(proj["solver"].as_str().unwrap_or("")),
            Cell::text(format!("{} / {} / {}", proj["relaxed_violations"]["tap"], proj["relaxed_violations"]["hamming"], proj["relaxed_violations"]["window"])),
            Cell::from_json(psrc, &proj, "/bits_changed", Format::Fixed(0)),
            Cell::from_json(psrc, &proj, "/bits", Format::Fixed(0)),
        ]],
    };
    Ok(Section {
        id: "codes".into(),
        title: "Exposure codes".into(),
        blocks: vec![
            Block::Text("Each row is one code channel: subpixel n of the 2×2 block and tap m; a coloured cell means the tap collects light during that mask. The strip below counts the bits that change between adjacent masks against the Hamming limit; red marks on top would flag violated masks (there are none: every exported set passes the checker).".into()),
            fig("codes-random.png", "One random code set under the constraints (seed of the demo)."),
            fig("codes-selected.png", "The selected code set: designed for range identifiability (tcsense codes select --criterion range: the best of 20 000 random sets by alias and worst-case range bound, then a local search that keeps every constraint exact)."),
            fig("codes-best-mse.png", "The paper's selection: the random candidate with the lowest TVAL3 MSE."),
            fig("codes-learned.png", "Codes learned jointly with ADMM-Net (relaxed, straight-through training, then the exact projection onto tap + H 2 + W 2, then fine-tuning)."),
            fig("selection.png", "TVAL3 MSE of every random candidate on the validation scenes (noise-free, as in the paper's selection)."),
            Block::Table(Table { caption: "Code selection by TVAL3 MSE (results/selection.json)".into(), headers: vec!["candidate seed".into(), "TVAL3 MSE".into()], rows: cand_rows }),
            Block::Text("Selection by TVAL3 MSE over typical scenes does not see a range the codes erase: two returns whose tap signatures are nearly equal cost little MSE on average, but a surface at one of them is placed at the other by every decoder. The table and figures below measure what each code set lets the taps tell apart; the selected set was designed for it.".into()),
            Block::Table(crate::identifiability::table(&ident, "results/identifiability.json", &|name| match name {
                "best MSE" => sel["candidates"].as_array().and_then(|a| a.iter().filter_map(|c| c["mse"].as_f64()).reduce(f64::min)),
                "selected" => sel["designed"]["mse"].as_f64(),
                _ => None,
            })),
            fig("identifiability-range.png", "Cramér–Rao bound of a single return's range at every delay of the cycle, per code set (LiDAR grid): where two ranges alias the bound peaks."),
            fig("identifiability-lifetime.png", "Cramér–Rao bound of the lifetime (onset known), worst over the onsets, per code set (FLIm grid, heterodyne K = 8)."),
            Block::Table(projection),
            Block::Text("Both sets are written to the sensor's code memory: code-memory/selected/ and code-memory/learned/ hold one binary per channel (chNN.bin), the combined image codes.bin and the registers (ECLEN = L/8 − 1). Write them to the sensor with your acquisition software, or read them back with tcsense codes import. The learned set's registers, and where each channel's bits are:".into()),
            Block::Table(registers_table(&regs, regs_src)),
            Block::Table(channels_table(&regs, regs_src)),
        ],
    })
}

/// The tap images of one LiDAR test frame.
fn taps_section(fig: &dyn Fn(&str, &str) -> Block) -> Section {
    // tap images
    Section {
        id: "taps".into(),
        title: "Tap images".into(),
        blocks: vec![
            Block::Text("What the sensor reads out for one LiDAR test frame: one image per tap, each pixel the light of its 2×2 subpixel's code channel integrated over the frame, with shot and read noise (as in the paper's Fig. 15b). These are the decoders' only input.".into()),
            fig("taps.png", "The four tap images of the LiDAR test frame shown below (selected codes)."),
        ],
    }
}

/// The LiDAR results: the metric table and the frames.
fn lidar_section(dir: &Path, plan: &Plan, fig: &dyn Fn(&str, &str) -> Block) -> Result<Section> {
    // LiDAR
    let lj = read_json(&dir.join("results/lidar.json"))?;
    let src = "results/lidar.json";
    let rows = result_rows(
        src,
        &lj,
        &["decoder", "codes", "engine"],
        &[
            ("mse", Format::Sci(3)),
            ("psnr_db", Format::Fixed(2)),
            ("range_rmse_m/0", Format::Fixed(3)),
            ("range_rmse_m/1", Format::Fixed(3)),
            ("detection_pct/0", Format::Fixed(1)),
            ("detection_pct/1", Format::Fixed(1)),
            ("ms_per_frame", Format::Fixed(1)),
        ],
    );
    let findings_lidar = findings(
        &lj,
        &[
            ("mse", "MSE", Format::Sci(3), ""),
            ("range_rmse_m/0", "range RMSE of return 1", Format::Fixed(3), " m"),
            ("range_rmse_m/1", "range RMSE of return 2", Format::Fixed(3), " m"),
        ],
    );
    Ok(Section {
        id: "lidar".into(),
        title: "LiDAR with multipath".into(),
        blocks: vec![
            Block::Table(Table {
                caption: format!("LiDAR test split, {} items, noisy (in the style of the paper's Table 4). Every decoder of a code set sees the same measurements; the learned-codes rows measure the same scenes with the same noise seeds through their own codes, as does the zoo's decoder as shipped (zoo:admm-lidar-delay, trained for hours on the prototype's codes); the zoo's decoder fine-tuned to the selected codes had the training time of ADMM-Net from scratch. Range errors over the pixels where the truth and the decoder both have that return; the U-Net estimates range directly and has no cube (no MSE).", plan.lidar_eval_items),
                headers: ["decoder", "codes", "engine", "MSE", "PSNR (dB)", "range RMSE return 1 (m)", "range RMSE return 2 (m)", "detected return 1 (%)", "detected return 2 (%)", "time per frame (ms)"].map(String::from).to_vec(),
                rows,
            }),
            Block::Text(findings_lidar),
            Block::Table(photon_table(dir, "lidar")?),
            Block::Text(codes_on_the_ladder(dir)?),
            fig("photon-lidar.png", "Photon efficiency: each decoder's median first-return error (bins, left) and its share of the true first returns within half a bin (right) against the signal electrons of the brightest tap, on the test split at signal 0.8, 0.1, 0.02 and 0.005 of the full well (noise on, no ambient light; the same scenes and noise seeds at every level), beside the Cramér–Rao bound of one return seen by a whole block through each code set. Rows not marked are on the selected codes; the learned-codes rows are the same ADMM-Net architecture trained with its codes by deep sensing, and the fit, through the learned codes. The zoo's U-Net on the fit's evidence is measured through its own codes."),
            fig("waveforms-lidar.png", "Waveforms at three pixels of one test frame (the first with a diffusive sheet) against the truth (as in the paper's Fig. 18): the pixel nearest the centre with a return behind the sheet, the centre, the farthest first return (quarter points where these coincide)."),
            fig("depth.png", "Range of the first and second return, truth and each decoder (TVAL3 and ADMM-Net by peak detection in the cube, the U-Net directly); one colour scale over the unambiguous range."),
            fig("depth-error.png", "Absolute range error of each decoder and return."),
            fig("point-cloud.png", "The same frame as point clouds (pinhole camera, 40° field of view; as in the paper's Fig. 17)."),
        ],
    })
}

/// The FLIm results: the metric table and the lifetime maps.
fn flim_section(dir: &Path, plan: &Plan, fig: &dyn Fn(&str, &str) -> Block) -> Result<Section> {
    // FLIm
    let fj = read_json(&dir.join("results/flim.json"))?;
    let src = "results/flim.json";
    let rows = result_rows(
        src,
        &fj,
        &["decoder", "engine"],
        &[
            ("mse", Format::Sci(3)),
            ("psnr_db", Format::Fixed(2)),
            ("lifetime_mae_ns", Format::Fixed(3)),
            ("lifetime_within_02ns_pct", Format::Fixed(1)),
            ("ms_per_frame", Format::Fixed(1)),
        ],
    );
    let findings_flim = findings(&fj, &[("mse", "MSE", Format::Sci(3), ""), ("lifetime_mae_ns", "lifetime MAE", Format::Fixed(3), " ns")]);
    Ok(Section {
        id: "flim".into(),
        title: "Fluorescence lifetime imaging".into(),
        blocks: vec![
            Block::Table(Table {
                caption: format!("FLIm test split, {} items, noisy, selected codes (in the style of the paper's Table 5). Lifetime error: mean absolute error of the amplitude-weighted mean lifetime over the pixels holding a fluorophore (a cube's by the reconvolution fit with the IRF fitted; the fit to the taps and the lifetime decoder have no cube, so no MSE). The zoo's decoders as shipped (zoo:admm-flim-delay, trained for 3.8 hours, and zoo:lifetime-flim, 39 minutes, on the prototype's codes) measure the same scenes with the same noise seeds through their own codes.", plan.flim_eval_items),
                headers: ["decoder", "engine", "MSE", "PSNR (dB)", "lifetime MAE (ns)", "within 0.2 ns (%)", "time per frame (ms)"].map(String::from).to_vec(),
                rows,
            }),
            Block::Text(findings_flim),
            Block::Table(photon_table(dir, "flim")?),
            Block::Text(flim_codes_on_the_ladder(dir)?),
            fig("photon-flim.png", "Photon efficiency: each decoder's lifetime MAE (ns, left) and the share of the fluorophore pixels given a lifetime (right) against the signal electrons of the brightest tap, at signal 0.8, 0.1, 0.02 and 0.005 of the full well (noise on), beside the Cramér–Rao bound of a 2 ns lifetime seen by a whole block with its onset known, through each code set. The zoo's networks are measured through their own codes: the lifetime network on the fit's evidence pooled by likeness, and one lifetime network architecture on designed codes and on codes learned with it."),
            fig("waveforms-flim.png", "Decays at three pixels of FLIm test frame 0 (shortest and longest true lifetime, centre) against the truth (as in the paper's Fig. 20)."),
            fig("lifetime.png", "Lifetime map: the generator's amplitude-weighted mean lifetimes, the reconvolution fit to the true cube (the fit's own error), the fits to each decoder's cube, and the lifetimes fitted to the tap images directly."),
            fig("phasor.png", "Phasor plot of every pixel (first harmonic, background removed, phase referenced to the frame's decay onset at the peak of its summed decay): single exponentials lie on the semicircle, mixtures of lifetimes inside it."),
        ],
    })
}

/// The two LiDAR code sets on the photon ladder (`results/photon-lidar.json`) with one decoder
/// architecture: the ADMM-Net's median first-return error on the selected codes against deep
/// sensing's on the learned codes at every level, and the levels where the learned codes do at
/// least as well.
fn codes_on_the_ladder(dir: &Path) -> Result<String> {
    let pj = read_json(&dir.join("results/photon-lidar.json"))?;
    let rows = pj["rows"].as_array().cloned().unwrap_or_default();
    let bin_m = pj["bin_m"].as_f64().unwrap_or(f64::NAN);
    let median = |decoder: &str, level: f64| {
        ladder_row(&rows, decoder, level).and_then(|r| r["depth_median_m"][0].as_f64()).map(|m| m / bin_m).filter(|v| v.is_finite())
    };
    let mut cells = Vec::new();
    let mut at_least = Vec::new();
    let mut compared = 0;
    for level in LADDER {
        match (median(SELECTED_ADMM, level), median(LEARNED_ADMM, level)) {
            (Some(s), Some(l)) => {
                compared += 1;
                cells.push(format!("{:.2} → {:.2} at signal {level} ({:.2}×)", s, l, l / s));
                if l <= s {
                    at_least.push(level.to_string());
                }
            }
            _ => cells.push(format!("no first returns to compare at signal {level}")),
        }
    }
    if compared == 0 && !rows.iter().any(|r| r["decoder"].as_str() == Some(LEARNED_ADMM)) {
        return Ok("results/photon-lidar.json has no rows on the learned codes (it was written by an earlier version of the demo: delete it and rerun the demo into this directory to add them).".into());
    }
    let verdict = verdict_on_the_ladder(&at_least, "the selected codes' first-return error");
    Ok(format!(
        "The two code sets with one decoder architecture (ADMM-Net + peaks, median first-return error in bins, selected codes → learned codes, same scenes and noise seeds): {}. {verdict} The learned codes were trained for the cube's error at the training's light levels; the fit's rows show what each code set gives without a learned prior.",
        cells.join("; ")
    ))
}

/// The row of `decoder` at light `level` (the brightest tap's share of the full well) among a
/// photon ladder's rows.
fn ladder_row<'a>(rows: &'a [Value], decoder: &str, level: f64) -> Option<&'a Value> {
    rows.iter().find(|r| r["decoder"].as_str() == Some(decoder) && r["light"]["signal_fraction"].as_f64() == Some(level))
}

/// Where learned codes are at least as good as `reference` on the ladder, for people.
fn verdict_on_the_ladder(at_least: &[String], reference: &str) -> String {
    if at_least.is_empty() {
        format!("The learned codes do not reach {reference} at any level.")
    } else {
        format!("The learned codes are at least as good at signal {} of the full well.", at_least.join(", "))
    }
}

/// The two FLIm code sets on the photon ladder (`results/photon-flim.json`) with one decoder
/// architecture: the zoo's lifetime network on designed codes against the same network on codes
/// learned with it, lifetime MAE and coverage at every level.
fn flim_codes_on_the_ladder(dir: &Path) -> Result<String> {
    let pj = read_json(&dir.join("results/photon-flim.json"))?;
    let rows = pj["rows"].as_array().cloned().unwrap_or_default();
    let value =
        |decoder: &str, level: f64, key: &str| ladder_row(&rows, decoder, level).and_then(|r| r[key].as_f64()).filter(|v| v.is_finite());
    if !rows.iter().any(|r| r["decoder"].as_str() == Some(FLIM_LEARNED_NET)) {
        return Ok("The FLIm ladder has no rows on learned codes: the zoo's lifetime networks on designed and learned codes were not found for these bins (see TCSENSE_ZOO), or results/photon-flim.json was written by an earlier version of the demo (delete it and rerun the demo into this directory).".into());
    }
    let mut cells = Vec::new();
    let mut at_least = Vec::new();
    for level in LADDER {
        let mae = |d| value(d, level, "lifetime_mae_s").map(|v| v * 1e9);
        let cov = |d| value(d, level, "lifetime_coverage").map(|v| 100.0 * v);
        match (mae(FLIM_DESIGNED_NET), mae(FLIM_LEARNED_NET)) {
            (Some(d), Some(l)) => {
                let coverage = match (cov(FLIM_DESIGNED_NET), cov(FLIM_LEARNED_NET)) {
                    (Some(a), Some(b)) => format!(", coverage {a:.0} → {b:.0} %"),
                    _ => String::new(),
                };
                cells.push(format!("{d:.3} → {l:.3} ns at signal {level} ({:.2}×{coverage})", l / d));
                if l <= d {
                    at_least.push(level.to_string());
                }
            }
            _ => cells.push(format!("no lifetimes to compare at signal {level}")),
        }
    }
    let verdict = verdict_on_the_ladder(&at_least, "the designed codes' lifetime error");
    Ok(format!(
        "The two FLIm code sets with one decoder architecture (the zoo's lifetime network, lifetime MAE, designed codes → codes learned with it, each through its own codes, the same scenes and noise seeds): {}. {verdict} `tcsense zoo show lifetime-flim-learned` has the same comparison on test sets unlike the training data.",
        cells.join("; ")
    ))
}

/// The photon ladder of one application (`results/photon-{app}.json`) as a table: a row per
/// decoder, a column per light level; LiDAR cells are the median first-return error (bins) and
/// the share within half a bin, FLIm cells the lifetime MAE (ns) and the coverage.
fn photon_table(dir: &Path, app: &str) -> Result<Table> {
    let src = format!("results/photon-{app}.json");
    let pj = read_json(&dir.join(&src))?;
    let rows = pj["rows"].as_array().cloned().unwrap_or_default();
    let mut levels: Vec<(f64, f64)> = Vec::new();
    let mut decoders: Vec<String> = Vec::new();
    for r in &rows {
        let l = (r["light"]["signal_fraction"].as_f64().unwrap_or(f64::NAN), r["light"]["signal_electrons"].as_f64().unwrap_or(f64::NAN));
        if !levels.iter().any(|v| v.0 == l.0) {
            levels.push(l);
        }
        let d = r["decoder"].as_str().unwrap_or("").to_string();
        if !decoders.contains(&d) {
            decoders.push(d);
        }
    }
    let bin_m = pj["bin_m"].as_f64();
    let cell = |r: &Value| -> String {
        let num = |v: &Value| v.as_f64().filter(|v| v.is_finite());
        if app == "lidar" {
            match (num(&r["depth_median_m"][0]), num(&r["depth_within_half_bin"][0]), bin_m) {
                (Some(m), Some(s), Some(b)) => format!("{:.2} · {:.0} %", m / b, 100.0 * s),
                (None, Some(s), _) => format!("– · {:.0} %", 100.0 * s),
                _ => "–".into(),
            }
        } else {
            match (num(&r["lifetime_mae_s"]), num(&r["lifetime_coverage"])) {
                (Some(m), Some(c)) => format!("{:.3} · {:.0} %", m * 1e9, 100.0 * c),
                (None, Some(c)) => format!("– · {:.0} %", 100.0 * c),
                _ => "–".into(),
            }
        }
    };
    let table_rows = decoders
        .iter()
        .map(|d| {
            let mut row = vec![Cell::text(d)];
            for l in &levels {
                let r = rows.iter().find(|r| r["decoder"].as_str() == Some(d) && r["light"]["signal_fraction"].as_f64() == Some(l.0));
                row.push(Cell::text(r.map_or("–".into(), cell)));
            }
            row
        })
        .collect();
    let mut headers = vec!["decoder".to_string()];
    headers.extend(levels.iter().map(|(f, e)| format!("signal {f} ({e:.0} e⁻)")));
    let what = if app == "lidar" {
        "median first-return error (bins) · first returns within half a bin"
    } else {
        "lifetime MAE (ns) · fluorophore pixels with a lifetime"
    };
    Ok(Table {
        caption: format!("The light axis ({src}): {what}, at each signal level (the brightest tap's share of the 20 000 e⁻ full well; noise on, no ambient light), {} test items.", pj["items"]),
        headers,
        rows: table_rows,
    })
}

/// The training curves.
fn training_section(fig: &dyn Fn(&str, &str) -> Block) -> Section {
    // training
    Section {
        id: "training".into(),
        title: "Training curves".into(),
        blocks: vec![
            fig("training-lidar.png", "ADMM-Net on LiDAR with the selected codes and with codes learned jointly (metrics.csv of each run; the learned run's relaxed epochs, then its fine-tuning on the projected codes), and the zoo's ADMM-Net fine-tuned to the selected codes in the same time as the run from scratch: what starting from the zoo buys."),
            fig("training-unet.png", "Aᵀ + U-Net: depth loss and validation range RMSE."),
            fig("training-flim.png", "ADMM-Net on FLIm."),
        ],
    }
}

/// The bring-up of a non-ideal sensor: its check table.
fn bringup_section(dir: &Path) -> Result<Section> {
    // the bring-up of a non-ideal sensor
    let bj = read_json(&dir.join("bringup/results/check.json"))?;
    let src = "bringup/results/check.json";
    let rows: Vec<Vec<Cell>> = bj["rows"]
        .as_array()
        .cloned()
        .unwrap_or_default()
        .iter()
        .enumerate()
        .map(|(i, row)| {
            vec![
                Cell::text(row["decoder"].as_str().unwrap_or("")),
                Cell::text(row["condition"].as_str().unwrap_or("")),
                Cell::from_json(src, &bj, &format!("/rows/{i}/first_return_median_m"), Format::Fixed(3)),
                Cell::from_json(src, &bj, &format!("/rows/{i}/psnr_db"), Format::Fixed(2)),
            ]
        })
        .collect();
    Ok(Section {
        id: "bringup".into(),
        title: "Bring-up of a non-ideal sensor".into(),
        blocks: vec![
            Block::Text(format!(
                "The demo's sensor on the bench is not the model: {}. A laser-delay sweep of it (bench-sweep/) is calibrated, the LiDAR decoders above are fine-tuned to the calibrated sensor and exported to ONNX models that take its raw tap images (bringup/onnx/), and each decoder is checked on held-back scenes through that sensor: on the ideal sensor, through the nominal model, with the calibration alone and calibrated + fine-tuned, beside TVAL3. bringup/report.html has the calibration, the steps and their times; `tcsense bringup` runs the same path on any sweep.",
                bj["truth"]
            )),
            Block::Table(Table {
                caption: "First-return median range error (m) and cube PSNR (dB) of each decoder, per condition".into(),
                headers: ["decoder", "condition", "first-return median error (m)", "PSNR (dB)"].map(String::from).to_vec(),
                rows,
            }),
        ],
    })
}

/// Deployment: the timing table and the commands that run the exported models.
fn deployment_section(dir: &Path, plan: &Plan, fig: &dyn Fn(&str, &str) -> Block) -> Result<Section> {
    let r = &plan.request;
    // deployment timing
    let tj = read_json(&dir.join("results/timing.json"))?;
    let src = "results/timing.json";
    let mut rows = Vec::new();
    for (i, d) in tj["decoders"].as_array().cloned().unwrap_or_default().iter().enumerate() {
        for (j, e) in d["timing"]["engines"].as_array().cloned().unwrap_or_default().iter().enumerate() {
            let p = |k: &str| format!("/decoders/{i}/timing/engines/{j}/{k}");
            let fps = e["frames_per_s"].as_f64().unwrap_or(0.0);
            rows.push(vec![
                Cell::text(format!("runs/{}", d["run"].as_str().unwrap_or(""))),
                Cell::text(e["engine"].as_str().unwrap_or("")),
                Cell::from_json(src, &tj, &p("ms_per_frame"), Format::Fixed(1)),
                Cell::from_json(src, &tj, &p("frames_per_s"), Format::Fixed(1)),
                Cell::text(if fps >= SENSOR_FPS { "yes" } else { "no" }),
            ]);
        }
    }
    let (th, tw) = (r.timing_size[0], r.timing_size[1]);
    // the decoders as deployed, beside their errors on the photon ladder
    let sj = read_json(&dir.join("results/speed-lidar.json"))?;
    let ssrc = "results/speed-lidar.json";
    let ladder: Vec<f64> = sj["ladder"].as_array().map(|a| a.iter().filter_map(Value::as_f64).collect()).unwrap_or_default();
    let speed_rows: Vec<Vec<Cell>> = (0..sj["speeds"].as_array().map_or(0, Vec::len))
        .map(|i| {
            let mut row = vec![
                Cell::text(sj["speeds"][i]["decoder"].as_str().unwrap_or("")),
                Cell::from_json(ssrc, &sj, &format!("/speeds/{i}/frames_per_s"), Format::Fixed(1)),
                Cell::from_json(ssrc, &sj, &format!("/speeds/{i}/ms_per_frame"), Format::Fixed(1)),
                Cell::text(if sj["speeds"][i]["frames_per_s"].as_f64().unwrap_or(0.0) >= SENSOR_FPS { "yes" } else { "no" }),
            ];
            row.extend((0..ladder.len()).map(|k| Cell::from_json(ssrc, &sj, &format!("/error_bins/{i}/{k}"), Format::Fixed(2))));
            row
        })
        .collect();
    let mut speed_headers: Vec<String> =
        ["decoder (as deployed)", "frames/s", "ms per frame", "keeps up with the sensor"].map(String::from).to_vec();
    speed_headers.extend(ladder.iter().map(|l| format!("error (bins) at {l}")));
    Ok(Section {
        id: "deployment".into(),
        title: "Deployment: ONNX and timing".into(),
        blocks: vec![
            Block::Table(Table {
                caption: format!("Time per {th}×{tw} frame, batch 1, median of {} interleaved rounds on this machine ({} threads available); the sensor delivers {SENSOR_FPS} frames/s.", plan.timing_rounds, rayon::current_num_threads()),
                headers: ["decoder", "engine", "ms per frame", "frames/s", "keeps up with the sensor"].map(String::from).to_vec(),
                rows,
            }),
            Block::Table(Table {
                caption: format!(
                    "The LiDAR decoders as deployed: each timed whole (ONNX Runtime and the fits `tcsense infer` runs around it, one frame per call) on {} noisy {th}×{tw} frames of the test scenes at signal {} of the full well, the median of {} interleaved rounds; beside each, its median first-return error on the photon ladder (the same network in burn gives the same product). The zoo's U-Net on the fit's evidence runs on its own codes.",
                    sj["frames"], sj["signal_fraction"], sj["rounds"]
                ),
                headers: speed_headers,
                rows: speed_rows,
            }),
            fig("speed-accuracy-lidar.png", "Deployed speed against accuracy: each LiDAR decoder as a run of dots at its frames/s (whole decoder at the frame size above), one dot per signal level of the photon ladder (labelled with the brightest tap's share of the full well), its median first-return error in bins. Up and to the left is slower and worse."),
            Block::Text("Each trained decoder is exported to onnx/NAME.onnx (opset 17; input measurements [B, 4, H, W], the raw tap images; output cube [B, T, H, W] or depth and confidence [B, 2, H, W]; codes, clock and sensor model in the metadata). Run them on recorded tap images with:".into()),
            Block::Code(format!(
                "tcsense infer --model {0}/onnx/unet-lidar.onnx --measurements {0}/frames/lidar-y.npy --products depth,ply -o out/\ntcsense infer --model {0}/onnx/admm-flim.onnx --measurements {0}/frames/flim-y.npy --products cube,lifetime -o out/\ntcsense eval --dataset {0}/lidar --codes {0}/codes/selected.json --irf physical --decoder tval3 --decoder onnx:{0}/onnx/admm-lidar.onnx --noise",
                dir.display()
            )),
        ],
    })
}
