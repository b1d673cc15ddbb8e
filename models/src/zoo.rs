//! The model zoo: trained decoders shipped with the toolkit, each a complete run directory
//! (see [`crate::runs`]) with its provenance, taken wherever a run is by `zoo:NAME`.
//!
//! ```text
//! zoo/NAME/config.json, codes.json, model.bpk, metrics.csv, checkpoint/   the run (as `train` wrote it)
//! zoo/NAME/PROVENANCE.md   commands, commit, seeds, data, wall time, benchmark tables
//! zoo/NAME/codes_comparison.json   learned codes only: against the same network on designed codes
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
/// How an entry's learned codes compare with the same network on designed codes,
/// `zoo/NAME/codes_comparison.json` (learned-codes entries; `scripts/zoo_codes_compare.sh`).
pub const COMPARISON_FILE: &str = "codes_comparison.json";
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
    /// Learned codes: how they fared against the same network on designed (or given) codes
    /// ([`COMPARISON_FILE`]); `None` where it was not measured.
    pub comparison: Option<CodesComparison>,
}

/// Learned codes against designed codes on the photon ladder of test sets unlike the training
/// data, each entry through its own codes, the same items and noise seeds
/// (`scripts/zoo_codes_compare.sh`).
#[derive(Debug, Clone, PartialEq, serde::Deserialize)]
pub struct CodesComparison {
    /// The entry of the same network on designed (or given) codes.
    pub against: String,
    /// What was compared, with its unit: the first return's median error (m) or the lifetime
    /// MAE (s).
    pub product: String,
    /// The light levels: the brightest tap's share of the full well.
    pub levels: Vec<f64>,
    /// Learned / against per level, the geometric mean over the sets (`None`: not measured).
    pub ratio: Vec<Option<f64>>,
    /// `wins`, `on-par` or `baseline`.
    pub verdict: Verdict,
    /// Per test set, both entries' product at every level.
    pub sets: std::collections::BTreeMap<String, ComparisonRow>,
}

/// One test set of a [`CodesComparison`]: the product per light level.
#[derive(Debug, Clone, PartialEq, serde::Deserialize)]
pub struct ComparisonRow {
    pub learned: Vec<Option<f64>>,
    pub against: Vec<Option<f64>>,
}

/// Whether learned codes beat the designed ones: the ratio learned / designed of the product,
/// the geometric mean over the test sets, at signal 0.02 and 0.8 of the full well.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Verdict {
    /// At most 0.8× at 0.02 and 1.05× at 0.8 (issue 53's goal): the entry to use on its
    /// domain.
    Wins,
    /// At most 1.05× at both: no worse than the designed codes, short of the goal.
    OnPar,
    /// Worse at either: the learned codes lose, and the entry is kept as a baseline for
    /// comparisons, not to deploy.
    Baseline,
}

impl CodesComparison {
    /// `1.31× at 0.02, 1.08× at 0.8` style summary of the ratios at every level.
    pub fn ratios(&self) -> String {
        self.levels
            .iter()
            .zip(&self.ratio)
            .map(|(l, r)| match r {
                Some(r) => format!("{r:.2}× at {l}"),
                None => format!("– at {l}"),
            })
            .collect::<Vec<_>>()
            .join(", ")
    }

    /// Read a comparison file (`None` where there is none).
    pub fn read(path: &Path) -> Result<Option<CodesComparison>> {
        let text = match std::fs::read_to_string(path) {
            Ok(t) => t,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(ModelError::File { path: path.to_path_buf(), msg: e.to_string() }),
        };
        let c: CodesComparison = serde_json::from_str(&text)
            .map_err(|e| ModelError::File { path: path.to_path_buf(), msg: format!("not a codes comparison: {e}") })?;
        if c.ratio.len() != c.levels.len()
            || c.sets.values().any(|r| r.learned.len() != c.levels.len() || r.against.len() != c.levels.len())
        {
            return Err(ModelError::File {
                path: path.to_path_buf(),
                msg: format!("ratio and every set's rows must have one value per level ({} levels)", c.levels.len()),
            });
        }
        Ok(Some(c))
    }
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
    let comparison = CodesComparison::read(&file(COMPARISON_FILE))?;
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
        comparison,
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

    /// A comparison file is read with its verdict and ratios; one whose rows do not match its
    /// levels is refused with the file's name.
    #[test]
    fn a_codes_comparison_reads_and_checks_its_rows() {
        let p = std::env::temp_dir().join(format!("tcsense-zoo-cmp-{}.json", std::process::id()));
        let good = r#"{"entry": "x-learned", "against": "x-designed", "product": "lifetime MAE (s)", "levels": [0.8, 0.02],
            "sets": {"standard": {"learned": [1e-10, 2e-9], "against": [1e-10, 1e-9]}}, "ratio": [1.0, 2.0], "verdict": "baseline"}"#;
        std::fs::write(&p, good).unwrap();
        let c = CodesComparison::read(&p).unwrap().unwrap();
        assert_eq!((c.verdict, c.against.as_str()), (Verdict::Baseline, "x-designed"));
        assert_eq!(c.ratios(), "1.00× at 0.8, 2.00× at 0.02");
        std::fs::write(&p, good.replace("[1.0, 2.0]", "[1.0]")).unwrap();
        let e = CodesComparison::read(&p).unwrap_err().to_string();
        assert!(e.contains("tcsense-zoo-cmp") && e.contains("one value per level"), "{e}");
        std::fs::write(&p, good.replace("baseline", "maybe")).unwrap();
        assert!(CodesComparison::read(&p).unwrap_err().to_string().contains("not a codes comparison"));
        std::fs::remove_file(&p).unwrap();
        assert!(CodesComparison::read(&p).unwrap().is_none());
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
