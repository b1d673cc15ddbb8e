//! The demo's identifiability section: every code set it uses analysed on the LiDAR grid
//! (range alias, range Cramér–Rao bound against delay) and the FLIm grid (heterodyne `K = 8`:
//! range alias, lifetime bound against `τ`), written to `results/identifiability.json`, drawn
//! in two figures and tabulated in the report.

use crate::error::Result;
use serde_json::{json, Value};
use std::path::Path;
use tcsense_infer::figures::{self, Series};
use tcsense_infer::report::{Cell, Format, Table};
use tcsense_sensor::identify::{self, AnalyzeOptions, Light};
use tcsense_sensor::params::C;
use tcsense_sensor::{Codes, Irf, Sampling, Sensor};

/// The heterodyne steps of the demo's FLIm grid.
const FLIM_K: usize = 8;

/// The measures of `sets` (name, codes) under the physical IRF `irf`, as JSON: per set, the
/// LiDAR grid's alias and bound over the cycle and the FLIm grid's alias and lifetime bounds.
pub fn analyse(sets: &[(&str, &Codes)], irf: Irf) -> Result<Value> {
    let light = Light::default();
    let mut out = Vec::new();
    for (name, codes) in sets {
        let lidar = identify::analyze(
            Sensor::ideal((*codes).clone(), Sampling::Oversample(1), irf)?.matrix(),
            1,
            &light,
            &AnalyzeOptions::default(),
        );
        let flim = identify::analyze(
            Sensor::ideal((*codes).clone(), Sampling::Heterodyne(FLIM_K), irf)?.matrix(),
            FLIM_K,
            &light,
            &AnalyzeOptions { lifetime: true, ..Default::default() },
        );
        let mm = |bins: f64, r: &identify::Report| bins * r.bin_width_s * C / 2.0 * 1e3;
        let lifetime = flim.lifetime.clone().unwrap_or_default();
        let worst_rel = lifetime.iter().map(|p| p.known_worst_s / p.tau_s).fold(0.0, f64::max);
        out.push(json!({
            "codes": name,
            "lidar": {
                "range_alias": lidar.range_alias.distance,
                "alias_bins": [lidar.range_alias.bin, lidar.range_alias.other],
                "worst_range_bound_mm": mm(lidar.range.worst_bins, &lidar),
                "mean_range_bound_mm": mm(lidar.range.mean_bins, &lidar),
                "delay_ns": lidar.range.delays_bins.iter().map(|d| d * lidar.bin_width_s * 1e9).collect::<Vec<_>>(),
                "range_bound_mm": lidar.range.sigma_bins.iter().map(|s| mm(*s, &lidar)).collect::<Vec<_>>(),
            },
            "flim": {
                "range_alias": flim.range_alias.distance,
                "lifetime_alias": flim.lifetime_alias.map(|a| a.distance),
                "worst_relative_lifetime_bound": worst_rel,
                "tau_ns": lifetime.iter().map(|p| p.tau_s * 1e9).collect::<Vec<_>>(),
                "lifetime_bound_worst_ns": lifetime.iter().map(|p| p.known_worst_s * 1e9).collect::<Vec<_>>(),
            },
            "light": light,
        }));
    }
    Ok(json!({ "irf": "physical", "sets": out }))
}

/// One line per code set for the demo's log.
pub fn lines(v: &Value) -> Vec<String> {
    v["sets"]
        .as_array()
        .map(|a| {
            a.iter()
                .map(|s| {
                    format!(
                        "  {:<10} LiDAR: alias {:.3}, range bound worst {:.1} mm, mean {:.1} mm; FLIm (K = 8): alias {:.3}, worst σ(τ)/τ {:.1} %",
                        s["codes"].as_str().unwrap_or(""),
                        s["lidar"]["range_alias"].as_f64().unwrap_or(f64::NAN),
                        s["lidar"]["worst_range_bound_mm"].as_f64().unwrap_or(f64::NAN),
                        s["lidar"]["mean_range_bound_mm"].as_f64().unwrap_or(f64::NAN),
                        s["flim"]["range_alias"].as_f64().unwrap_or(f64::NAN),
                        100.0 * s["flim"]["worst_relative_lifetime_bound"].as_f64().unwrap_or(f64::NAN),
                    )
                })
                .collect()
        })
        .unwrap_or_default()
}

/// The two figures: the range bound against delay and the lifetime bound against `τ`, one
/// line per code set.
pub fn draw(v: &Value, range_png: &Path, lifetime_png: &Path) -> Result<()> {
    let sets = v["sets"].as_array().cloned().unwrap_or_default();
    let pairs = |a: &Value, x: &str, y: &str| -> Vec<(f64, f64)> {
        let xs = a[x].as_array().cloned().unwrap_or_default();
        let ys = a[y].as_array().cloned().unwrap_or_default();
        let mut p: Vec<(f64, f64)> = xs.iter().zip(&ys).filter_map(|(x, y)| Some((x.as_f64()?, y.as_f64()?))).collect();
        p.sort_by(|u, w| u.0.total_cmp(&w.0));
        p
    };
    let label =
        |s: &Value, alias: &Value| format!("{} (alias {:.2})", s["codes"].as_str().unwrap_or(""), alias.as_f64().unwrap_or(f64::NAN));
    let range: Vec<Series> = sets
        .iter()
        .map(|s| Series { label: label(s, &s["lidar"]["range_alias"]), points: pairs(&s["lidar"], "delay_ns", "range_bound_mm") })
        .collect();
    figures::line_chart(
        range_png,
        "Range Cramér–Rao bound over the cycle (LiDAR grid, 1000 e⁻ signal, 100 e⁻ ambient)",
        "delay of the return (ns)",
        "σ of the range (mm)",
        &range,
    )?;
    let life: Vec<Series> = sets
        .iter()
        .map(|s| Series { label: label(s, &s["flim"]["range_alias"]), points: pairs(&s["flim"], "tau_ns", "lifetime_bound_worst_ns") })
        .collect();
    figures::log_chart(
        lifetime_png,
        "Lifetime Cramér–Rao bound, worst over the onsets (FLIm grid, onset known)",
        "lifetime τ (ns)",
        "σ of τ (ns)",
        &life,
    )?;
    Ok(())
}

/// The report's table of the measures (`src`: the JSON file the numbers come from).
pub fn table(v: &Value, src: &str, mse: &dyn Fn(&str) -> Option<f64>) -> Table {
    let sets = v["sets"].as_array().cloned().unwrap_or_default();
    let rows = sets
        .iter()
        .enumerate()
        .map(|(i, s)| {
            let name = s["codes"].as_str().unwrap_or("").to_string();
            let f = |path: &str, fmt: Format| Cell::from_json(src, v, &format!("/sets/{i}/{path}"), fmt);
            vec![
                Cell::text(name.clone()),
                mse(&name).map_or_else(|| Cell::text("–"), |m| Cell::text(format!("{m:.3e}"))),
                f("lidar/range_alias", Format::Fixed(3)),
                f("lidar/worst_range_bound_mm", Format::Fixed(1)),
                f("lidar/mean_range_bound_mm", Format::Fixed(1)),
                f("flim/range_alias", Format::Fixed(3)),
                f("flim/worst_relative_lifetime_bound", Format::Fixed(3)),
            ]
        })
        .collect();
    Table {
        caption: "What each code set lets the taps tell apart (results/identifiability.json; physical IRF, 1000 e⁻ signal, 100 e⁻ ambient, 40 e⁻ read noise per block). Range alias: the distance between the unit tap signatures of the two returns at least two masks apart that the codes tell apart least (0: the same taps, 1.414: orthogonal); below 0.5 a surface at one of the two ranges can be read at the other. Range bound: the Cramér–Rao bound of one return's range over the cycle. FLIm: the same alias on the heterodyne grid, and the worst relative lifetime bound σ(τ)/τ over 0.2–8 ns and the onsets (onset known).".into(),
        headers: ["code set", "TVAL3 MSE", "range alias", "worst range bound (mm)", "mean range bound (mm)", "FLIm range alias", "worst σ(τ)/τ"].map(String::from).to_vec(),
        rows,
    }
}
