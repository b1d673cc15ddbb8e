//! The report page of a calibration (`tcsense calibrate`): the fitted responses against the
//! sweep data and the nominal model, the gain, dark and residual maps, and the numbers of
//! `calibration.json` (each table cell carries its JSON pointer).

use ndarray::Axis;
use std::path::{Path, PathBuf};
use tcsense_sensor::calibration::{Calibration, DESCRIPTION};
use tcsense_sensor::waveform::subpixel;
use tcsense_sensor::MeasurementMatrix;

use crate::figures::{self, Series};
use crate::report::{Block, Cell, Format, Report, Section, Table};
use crate::{InferError, Result};

/// Write `dir/report.html` and its figures for `cal` (calibrated against `nominal`); `cal`
/// must still hold the sweep's mean responses (a fresh calibration, not a loaded one).
pub fn write_calibration_report(cal: &Calibration, nominal: &MeasurementMatrix, dir: &Path) -> Result<PathBuf> {
    let r = cal.response.as_ref().ok_or_else(|| InferError::InvalidParam {
        field: "calibration",
        got: "a loaded calibration".into(),
        expected: "a fresh calibration with the sweep's responses".into(),
    })?;
    let meta_json: serde_json::Value =
        serde_json::to_value(&cal.meta).map_err(|e| InferError::File { path: dir.join(DESCRIPTION), msg: e.to_string() })?;
    let (n, m, t) = cal.matrix.a().dim();
    let (bh, bw) = cal.matrix.block();
    let dt_ns = cal.matrix.bin_width_s() * 1e9;
    let time = |j: usize| (j as f64 + 0.5) * dt_ns;
    let mut figs = Vec::new();
    // responses per subpixel type: calibrated against nominal
    for q in 0..n {
        let file = format!("responses_{q}.png");
        let mut series = Vec::new();
        for c in 0..m {
            series.push(Series {
                label: format!("tap {c} calibrated"),
                points: (0..t).map(|j| (time(j), cal.matrix.a()[(q, c, j)] as f64)).collect(),
            });
        }
        for c in 0..m {
            series.push(Series {
                label: format!("tap {c} nominal"),
                points: (0..t).map(|j| (time(j), nominal.a()[(q, c, j)] as f64)).collect(),
            });
        }
        figures::line_chart(
            &dir.join(&file),
            &format!("Response of subpixel type {q} (row {}, column {} of the block)", q / bw, q % bw),
            "laser delay (ns)",
            "share of the light in the tap, A[n, m, t]",
            &series,
        )?;
        figs.push(Block::Figure { src: file, caption: format!("Subpixel type {q}: the calibrated matrix A (one line per tap) against the nominal model. Differences are the sensor's tap gains, crosstalk, tail and drift.") });
    }
    // one pixel's sweep data against the fit
    let (_, _, h, w) = r.dim();
    let (pi, pj) = (h / 2 / bh * bh, w / 2 / bw * bw);
    let q = subpixel(pi, pj, (bh, bw));
    let model: Vec<Vec<f64>> =
        (0..m).map(|c| (0..t).map(|j| cal.gain[(c, pi, pj)] as f64 * cal.matrix.a()[(q, c, j)] as f64).collect()).collect();
    let data: Vec<Vec<f64>> = (0..m).map(|c| (0..t).map(|j| r[(j, c, pi, pj)] as f64).collect()).collect();
    let num: f64 = model.iter().flatten().zip(data.iter().flatten()).map(|(a, b)| a * b).sum();
    let den: f64 = model.iter().flatten().map(|a| a * a).sum();
    let kappa = if den > 0.0 { num / den } else { 1.0 };
    let mut series = Vec::new();
    for c in 0..m {
        series.push(Series { label: format!("tap {c} sweep"), points: (0..t).map(|j| (time(j), data[c][j] / kappa)).collect() });
        series.push(Series { label: format!("tap {c} fit"), points: (0..t).map(|j| (time(j), model[c][j])).collect() });
    }
    figures::line_chart(
        &dir.join("fit.png"),
        &format!("Sweep of pixel ({pi}, {pj}) against the fitted model"),
        "laser delay (ns)",
        "response (dark subtracted, / brightness)",
        &series,
    )?;
    // maps
    let taps: Vec<String> = (0..m).map(|c| format!("tap {c}")).collect();
    let gain_panels: Vec<(&str, ndarray::ArrayView2<'_, f32>)> =
        taps.iter().enumerate().map(|(c, l)| (l.as_str(), cal.gain.index_axis(Axis(0), c))).collect();
    figures::maps(&dir.join("gain.png"), "Gain per pixel and tap (1 = mean of its subpixel type)", &gain_panels, "relative gain", None)?;
    let dark_panels: Vec<(&str, ndarray::ArrayView2<'_, f32>)> =
        taps.iter().enumerate().map(|(c, l)| (l.as_str(), cal.dark.index_axis(Axis(0), c))).collect();
    figures::maps(
        &dir.join("dark.png"),
        "Dark offset per pixel and tap",
        &dark_panels,
        &format!("dark offset ({})", cal.meta.units),
        None,
    )?;
    figures::map(&dir.join("residual.png"), "RMS residual of the fit per pixel", &cal.residual.view(), "RMS residual / peak response")?;
    let summary = Table {
        caption: "The calibration (calibration.json)".into(),
        headers: vec!["quantity".into(), "value".into()],
        rows: vec![
            vec![Cell::text("delays in the sweep"), Cell::from_json(DESCRIPTION, &meta_json, "/delays", Format::Fixed(0))],
            vec![Cell::text("dark frames"), Cell::from_json(DESCRIPTION, &meta_json, "/dark_frames", Format::Fixed(0))],
            vec![Cell::text("flat frames"), Cell::from_json(DESCRIPTION, &meta_json, "/flat_frames", Format::Fixed(0))],
            vec![Cell::text("bin width (s)"), Cell::from_json(DESCRIPTION, &meta_json, "/bin_width_s", Format::Sci(3))],
            vec![
                Cell::text(format!("full scale ({})", cal.meta.units)),
                Cell::from_json(DESCRIPTION, &meta_json, "/full_scale", Format::Fixed(0)),
            ],
            vec![
                Cell::text("RMS residual of the fit / peak response"),
                Cell::from_json(DESCRIPTION, &meta_json, "/residual_rms", Format::Sci(2)),
            ],
            vec![
                Cell::text("RMS noise of one dark frame / peak response"),
                Cell::from_json(DESCRIPTION, &meta_json, "/dark_noise_rms", Format::Sci(2)),
            ],
        ],
    };
    let gains = Table {
        caption: "Tap gains relative to the nominal model (mean 1)".into(),
        headers: vec!["tap".into(), "gain".into()],
        rows: (0..m)
            .map(|c| {
                vec![Cell::text(c.to_string()), Cell::from_json(DESCRIPTION, &meta_json, &format!("/tap_gains/{c}"), Format::Fixed(4))]
            })
            .collect(),
    };
    let report = Report {
        title: "Sensor calibration".into(),
        subtitle: format!("{} taps, {bh}x{bw} block, T = {t} bins of {:.1} ps, {}x{} pixels, from {}", m, dt_ns * 1e3, h, w, cal.meta.sweep),
        sections: vec![
            Section {
                id: "summary".into(),
                title: "Summary".into(),
                blocks: vec![
                    Block::Text("The matrix A [N, M, T] was measured from a laser-delay sweep of a flat target: dark frames subtracted, each pixel divided by its gain, averaged per subpixel type, and scaled to the nominal model's total. Decoders given this directory with --calibration correct raw tap images to (y − dark) / gain and decode them with this A.".into()),
                    Block::Table(summary),
                    Block::Table(gains),
                ],
            },
            Section { id: "responses".into(), title: "Responses".into(), blocks: figs },
            Section {
                id: "fit".into(),
                title: "Fit against the sweep".into(),
                blocks: vec![Block::Figure { src: "fit.png".into(), caption: format!("Pixel ({pi}, {pj}): the sweep's frames (dark subtracted, divided by the fitted brightness) and the model gain · A.") }],
            },
            Section {
                id: "maps".into(),
                title: "Gain, dark and residual maps".into(),
                blocks: vec![
                    Block::Figure { src: "gain.png".into(), caption: "Per-pixel gain of each tap (photo-response non-uniformity), relative to the mean of its subpixel type.".into() },
                    Block::Figure { src: "dark.png".into(), caption: format!("Mean dark frame per tap, in {}.", cal.meta.units) },
                    Block::Figure { src: "residual.png".into(), caption: "RMS over taps and delays of the sweep minus the fitted model, relative to the sweep's peak response: structure here is what the model misses.".into() },
                ],
            },
        ],
    };
    let path = dir.join("report.html");
    report.write(&path)?;
    Ok(path)
}
