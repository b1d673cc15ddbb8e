//! The model zoo: trained decoders shipped with the toolkit, each a complete run directory
//! (see [`crate::runs`]) with its provenance, taken wherever a run is by `zoo:NAME`.
//!
//! ```text
//! zoo/NAME/config.json, codes.json, model.bpk, metrics.csv, checkpoint/   the run (as `train` wrote it)
//! zoo/NAME/PROVENANCE.md   commands, commit, seeds, data, wall time, benchmark tables
//! ```
//!
//! The zoo is the directory named by `TCSENSE_ZOO`, else the `zoo/` of the source tree this
//! build came from.

use std::path::{Path, PathBuf};

use crate::runs::{read_config_json, upgrade_config, ModelConfig, CODES_FILE, CONFIG_FILE, WEIGHTS_FILE};
use crate::{ModelError, Result};

/// The prefix that names a zoo entry where a run directory is taken: `zoo:NAME`.
pub const PREFIX: &str = "zoo:";
/// The provenance of an entry, `zoo/NAME/PROVENANCE.md`.
pub const PROVENANCE_FILE: &str = "PROVENANCE.md";
/// The environment variable that points at another zoo directory.
pub const ZOO_ENV: &str = "TCSENSE_ZOO";

/// The zoo directory: `$TCSENSE_ZOO`, else the source tree's `zoo/`.
pub fn root() -> PathBuf {
    match std::env::var_os(ZOO_ENV) {
        Some(dir) if !dir.is_empty() => PathBuf::from(dir),
        _ => {
            let models = Path::new(env!("CARGO_MANIFEST_DIR"));
            models.parent().unwrap_or(models).join("zoo")
        }
    }
}

/// A run directory from what a user typed: `zoo:NAME` is the zoo's entry (an error naming
/// the entries there if it has none of that name), anything else a path, returned as is.
pub fn resolve(spec: &str) -> Result<PathBuf> {
    let Some(name) = spec.strip_prefix(PREFIX) else { return Ok(PathBuf::from(spec)) };
    let root = root();
    let valid = !name.is_empty() && !name.contains(['/', '\\']) && name != "." && name != "..";
    let dir = root.join(name);
    if valid && dir.join(CONFIG_FILE).is_file() {
        return Ok(dir);
    }
    let names = names(&root)?;
    Err(ModelError::InvalidParam {
        field: "zoo entry",
        got: format!("{spec:?} (zoo {})", root.display()),
        expected: if names.is_empty() {
            "an entry, but the zoo has none".into()
        } else {
            format!("one of {}", names.iter().map(|n| format!("{PREFIX}{n}")).collect::<Vec<_>>().join(", "))
        },
    })
}

/// The names of the entries in `root` (directories with a `config.json`), sorted.
fn names(root: &Path) -> Result<Vec<String>> {
    let rd =
        std::fs::read_dir(root).map_err(|e| ModelError::File { path: root.to_path_buf(), msg: format!("cannot list the zoo: {e}") })?;
    let mut out: Vec<String> = rd
        .filter_map(|e| e.ok())
        .filter(|e| e.path().join(CONFIG_FILE).is_file())
        .filter_map(|e| e.file_name().to_str().map(str::to_string))
        .collect();
    out.sort();
    Ok(out)
}

/// What `zoo list` and `zoo show` tell about an entry, read from its files.
#[derive(Debug, Clone)]
pub struct Entry {
    /// `NAME` of `zoo:NAME`.
    pub name: String,
    /// The run directory.
    pub dir: PathBuf,
    /// The network and its hyper-parameters.
    pub model: ModelConfig,
    /// `LiDAR` or `FLIm` (heterodyne sampling or a lifetime decoder).
    pub domain: &'static str,
    /// Whether the codes were learned with the decoder (deep sensing) or given.
    pub learned_codes: bool,
    /// Whether the given codes were designed by identifiability (`codes select --criterion`).
    pub designed_codes: bool,
    /// `M taps, block HxW, L = …` of the run's codes.
    pub codes: String,
    /// Epochs logged in `metrics.csv` (plus `relaxed/metrics.csv`, deep sensing's joint phase,
    /// for learned codes), and the last row's validation metrics by column name.
    pub epochs: usize,
    pub validation: Vec<(String, f64)>,
    /// The first heading of PROVENANCE.md (empty when it has none).
    pub title: String,
    /// Bytes of the weights file.
    pub weights_bytes: u64,
    /// The range alias of its codes on its sensor (sampling and IRF of the run;
    /// [`tcsense_sensor::identify`]): below 0.5 two ranges (or two onsets) two masks or more
    /// apart give nearly the same taps. `None` where the config names no sensor.
    pub range_alias: Option<f64>,
    /// The light it was trained in: the brightest tap's share of the full well (a range where
    /// the photon ladder was drawn per item), and the ambient light (`1/SBR`) where there was
    /// some; `noise-free` for runs without noise.
    pub light: String,
}

/// The light of a run config: `0.05–0.9`, `0.002–0.9, ambient 0–2`, `0.8` or `noise-free`.
fn light_of(json: &serde_json::Value) -> String {
    let num = |p: &str| json.pointer(p).and_then(|v| v.as_f64());
    let g = |v: f64| format!("{v}");
    if json.get("noise").is_none_or(|n| n.is_null()) {
        return "noise-free".into();
    }
    let signal = match (num("/augment/signal_fraction/0"), num("/augment/signal_fraction/1"), num("/noise/signal_fraction")) {
        (Some(lo), Some(hi), _) if lo < hi => format!("{}–{}", g(lo), g(hi)),
        (Some(v), Some(_), _) | (None, _, Some(v)) => g(v),
        _ => "?".into(),
    };
    match (num("/augment/ambient/0"), num("/augment/ambient/1")) {
        (Some(lo), Some(hi)) if hi > 0.0 => format!("{signal}, ambient {}–{}", g(lo), g(hi)),
        _ => signal,
    }
}

/// Every entry of the zoo, by name.
pub fn list() -> Result<Vec<Entry>> {
    let root = root();
    names(&root)?.iter().map(|n| read_entry(n, &root.join(n))).collect()
}

/// The zoo's entry `name` (with or without the `zoo:` prefix).
pub fn entry(name: &str) -> Result<Entry> {
    let name = name.strip_prefix(PREFIX).unwrap_or(name);
    let dir = resolve(&format!("{PREFIX}{name}"))?;
    read_entry(name, &dir)
}

fn read_entry(name: &str, dir: &Path) -> Result<Entry> {
    let file = |f: &str| dir.join(f);
    let json = upgrade_config(read_config_json(&file(CONFIG_FILE))?);
    let bad = |msg: String| ModelError::File { path: file(CONFIG_FILE), msg };
    let model: ModelConfig = serde_json::from_value(json.clone()).map_err(|e| bad(format!("not a run config: {e}")))?;
    let heterodyne = json.pointer("/sampling/mode").and_then(|m| m.as_str()) == Some("heterodyne");
    let domain = if heterodyne || matches!(model, ModelConfig::Lifetime(_)) { "FLIm" } else { "LiDAR" };
    let learned_codes = json.get("learn_codes").is_some_and(|v| !v.is_null());
    let codes = tcsense_sensor::Codes::load(&file(CODES_FILE))?;
    let range_alias = alias_of(&codes, &json);
    let designed_codes = codes.provenance.get("method").and_then(|m| m.as_str()) == Some("design");
    let (bh, bw) = codes.block();
    let codes = format!("{} taps, block {bh}x{bw}, L = {}", codes.taps(), codes.length());
    let (epochs, validation) = last_metrics(&file("metrics.csv"));
    // learned codes: the relaxed phase's epochs come first, in a run of their own
    let epochs = epochs + if learned_codes { last_metrics(&file("relaxed/metrics.csv")).0 } else { 0 };
    let title = std::fs::read_to_string(file(PROVENANCE_FILE))
        .ok()
        .and_then(|t| t.lines().find_map(|l| l.strip_prefix("# ").map(str::to_string)))
        .unwrap_or_default();
    let weights_bytes =
        std::fs::metadata(file(WEIGHTS_FILE)).map_err(|e| ModelError::File { path: file(WEIGHTS_FILE), msg: e.to_string() })?.len();
    let light = light_of(&json);
    Ok(Entry {
        name: name.to_string(),
        dir: dir.to_path_buf(),
        model,
        domain,
        learned_codes,
        designed_codes,
        codes,
        epochs,
        validation,
        title,
        weights_bytes,
        range_alias,
        light,
    })
}

/// The range alias of `codes` on the sensor of a run config (its `sampling` and `irf`).
fn alias_of(codes: &tcsense_sensor::Codes, json: &serde_json::Value) -> Option<f64> {
    let sampling: tcsense_sensor::Sampling = serde_json::from_value(json.get("sampling")?.clone()).ok()?;
    let irf: tcsense_sensor::Irf = serde_json::from_value(json.get("irf")?.clone()).ok()?;
    let sensor = tcsense_sensor::Sensor::ideal(codes.clone(), sampling, irf).ok()?;
    Some(tcsense_sensor::identify::range_alias(&tcsense_sensor::identify::Columns::new(sensor.matrix(), sampling.k())).distance)
}

/// The number of rows of a `metrics.csv` and its last row's validation columns (none when
/// the file is missing or malformed: the listing does not depend on it).
fn last_metrics(path: &Path) -> (usize, Vec<(String, f64)>) {
    let Ok(text) = std::fs::read_to_string(path) else { return (0, Vec::new()) };
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().unwrap_or_default().split(',').collect();
    let rows: Vec<&str> = lines.filter(|l| !l.is_empty()).collect();
    let Some(last) = rows.last() else { return (0, Vec::new()) };
    let vals = header
        .iter()
        .zip(last.split(','))
        .filter(|(h, _)| h.starts_with("val_"))
        .filter_map(|(h, v)| Some((h.to_string(), v.parse().ok()?)))
        .collect();
    (rows.len(), vals)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn paths_pass_through_and_unknown_names_list_the_zoo() {
        assert_eq!(resolve("runs/a").unwrap(), PathBuf::from("runs/a"));
        let root = std::env::temp_dir().join(format!("tcsense-zoo-{}", std::process::id()));
        std::fs::create_dir_all(root.join("one")).unwrap();
        std::fs::write(root.join("one").join(CONFIG_FILE), "{}").unwrap();
        assert_eq!(names(&root).unwrap(), vec!["one".to_string()]);
        let e = match names(&root.join("missing")) {
            Err(e) => e.to_string(),
            Ok(_) => panic!("a missing zoo lists"),
        };
        assert!(e.contains("missing") && e.contains("cannot list the zoo"), "{e}");
        std::fs::remove_dir_all(&root).unwrap();
    }

    #[test]
    fn last_metrics_reads_the_validation_columns_of_the_last_row() {
        let p = std::env::temp_dir().join(format!("tcsense-zoo-metrics-{}.csv", std::process::id()));
        std::fs::write(&p, "epoch,step,train_loss,val_mse,val_psnr_db\n1,2,0.5,1e-3,30.0\n2,4,0.4,5e-4,33.0\n").unwrap();
        let (n, v) = last_metrics(&p);
        assert_eq!(n, 2);
        assert_eq!(v, vec![("val_mse".to_string(), 5e-4), ("val_psnr_db".to_string(), 33.0)]);
        std::fs::remove_file(&p).unwrap();
        assert_eq!(last_metrics(&p).0, 0);
    }
}
