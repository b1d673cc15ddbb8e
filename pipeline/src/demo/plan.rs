//! The demo's plan: what the user asked for, the trainings and their shares of the budget,
//! epochs sized from a measured step time, fixed in `plan.json` on the first run.

use super::*;

/// What the user asked for: a rerun into the same directory must ask for the same.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub(super) struct Request {
    pub(super) quick: bool,
    pub(super) budget_minutes: f64,
    pub(super) size: [usize; 2],
    pub(super) lidar_scenes: usize,
    pub(super) flim_scenes: usize,
    pub(super) timing_size: [usize; 2],
    pub(super) seed: u64,
}

/// One training of the demo, sized to its share of the budget.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub(super) struct TrainPlan {
    /// Run directory under `runs/`.
    pub(super) name: String,
    /// What it is, for people.
    pub(super) title: String,
    pub(super) budget_s: f64,
    /// Measured median time of one step (batch 2) at the training crop.
    pub(super) step_ms: f64,
    pub(super) steps_per_epoch: usize,
    pub(super) epochs: usize,
}

/// Everything the demo does, fixed on its first run (`plan.json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub(super) struct Plan {
    pub(super) request: Request,
    /// Training crop (the frames when `None`).
    pub(super) crop: Option<[usize; 2]>,
    /// Random code sets scored by TVAL3 in the selection, and the validation items scored.
    pub(super) candidates: usize,
    pub(super) select_items: usize,
    /// Test items of the metric tables.
    pub(super) lidar_eval_items: usize,
    pub(super) flim_eval_items: usize,
    /// Validation items per epoch.
    pub(super) val_items: usize,
    pub(super) timing_rounds: usize,
    pub(super) trainings: Vec<TrainPlan>,
}

/// The trainings and their shares of the training budget. `zoo-lidar` fine-tunes the zoo's
/// LiDAR decoder ([`ZOO_ENTRY`]) to the selected codes in the time `admm-lidar` trains from
/// scratch; it is left out when the zoo does not hold that entry.
pub(super) const TRAININGS: [(&str, &str, f64); 5] = [
    ("admm-lidar", "ADMM-Net on LiDAR, selected codes", 0.2),
    ("learned-lidar", "ADMM-Net on LiDAR, codes learned with it (deep sensing)", 0.2),
    ("unet-lidar", "Aᵀ + U-Net depth decoder on LiDAR, selected codes", 0.15),
    ("admm-flim", "ADMM-Net with the delay prior on FLIm (heterodyne K = 8), selected codes", 0.25),
    ("zoo-lidar", "ADMM-Net from the zoo (zoo:admm-lidar-delay), fine-tuned to the selected codes in the same time", 0.2),
];

/// The zoo entry the demo evaluates as shipped (on its own codes) and fine-tunes.
pub(super) const ZOO_ENTRY: &str = "admm-lidar-delay";

/// The zoo entry's run directory and network, when the zoo holds it with the dataset's bins
/// (a binary installed without the source tree's `zoo/` and no `TCSENSE_ZOO` has none).
pub(super) fn zoo_entry(ds: &Dataset) -> Option<(PathBuf, ModelConfig)> {
    zoo_entry_named(ZOO_ENTRY, ds)
}

/// The zoo's lifetime decoder, evaluated as shipped (on its own codes) in the FLIm table.
pub(super) const ZOO_LIFETIME: &str = "lifetime-flim";

/// The zoo's FLIm ADMM-Net, evaluated as shipped (on its own codes) in the FLIm table.
pub(super) const ZOO_FLIM_CUBE: &str = "admm-flim-delay";

/// The zoo's lifetime network on designed codes and the same network on codes learned with
/// it: the FLIm photon ladder's two code sets with one decoder architecture.
pub(super) const ZOO_FLIM_DESIGNED: &str = "lifetime-flim-designed";
pub(super) const ZOO_FLIM_LEARNED: &str = "lifetime-flim-learned";

/// The zoo's decoders on the fits' evidence, evaluated as shipped on the photon ladder.
pub(super) const ZOO_EVIDENCE_UNET: &str = "unet-lidar-evidence-8k";
/// For lifetimes the pooled network trained on a flatter prior: the lowest errors at 0.02, at
/// the rate of `-fast`.
pub(super) const ZOO_EVIDENCE_LIFETIME: &str = "lifetime-flim-pooled-wide";

/// Zoo entry `name`'s run directory and network, when the zoo holds it for the dataset's
/// sampling and bins with 4 taps.
pub(super) fn zoo_entry_named(name: &str, ds: &Dataset) -> Option<(PathBuf, ModelConfig)> {
    let dir = tcsense_models::zoo::resolve(&format!("{}{name}", tcsense_models::zoo::PREFIX)).ok()?;
    let spec: runs::RunSpec = serde_json::from_value(runs::read_config_json(&dir.join(CONFIG_FILE)).ok()?).ok()?;
    (spec.sampling == ds.manifest.grid.sampling && spec.model.bins() == ds.manifest.bins && spec.model.taps() == 4)
        .then_some((dir, spec.model))
}

impl Request {
    pub(super) fn from_options(a: &DemoOptions) -> Result<Self> {
        let budget = a.budget_minutes.unwrap_or(if a.quick { 2.0 } else { 10.0 });
        if !(budget.is_finite() && budget > 0.0 && budget <= 10080.0) {
            bail!("--budget-minutes {budget}: expected a positive number of minutes, at most 10080 (a week)");
        }
        let (h, w) = a.size.unwrap_or(if a.quick { (32, 32) } else { (64, 64) });
        if h < 8 || w < 8 || h > 4096 || w > 4096 || h % 8 != 0 || w % 8 != 0 {
            bail!("--size {h}x{w}: expected multiples of 8 (the 2x2 block and the U-Net's 3 levels), from 8x8 to 4096x4096");
        }
        let lidar = a.scenes.unwrap_or(if a.quick { 160 } else { 400 });
        if !(30..=100_000).contains(&lidar) {
            bail!("--scenes {lidar}: expected 30 to 100000 (the paper's splits need 3 test items)");
        }
        let (th, tw) = a.timing_size;
        if th == 0 || tw == 0 || th % 4 != 0 || tw % 4 != 0 {
            bail!("--timing-size {th}x{tw}: expected multiples of 4");
        }
        Ok(Request {
            quick: a.quick,
            budget_minutes: budget,
            size: [h, w],
            lidar_scenes: lidar,
            flim_scenes: (lidar / 2).max(30),
            timing_size: [th, tw],
            seed: a.seed,
        })
    }
}

/// The model of a training.
pub(super) fn model_of(name: &str, ds: &Dataset) -> ModelConfig {
    let (m, t) = (4, ds.manifest.bins);
    if name.starts_with("zoo") {
        if let Some((_, model)) = zoo_entry(ds) {
            return model;
        }
    }
    if name.starts_with("unet") {
        let range_m = C * ds.manifest.bin_width_s * t as f64 / 2.0;
        ModelConfig::Unet(UnetConfig::new(m, t, range_m).with_head(tcsense_models::UnetHead::ScoreVolume))
    } else if name.ends_with("flim") {
        // onsets anywhere in the cycle: the delay-equivariant prior, 4 channels per bin
        ModelConfig::AdmmNet(AdmmNetConfig::cpu(m, t).with_prior(Prior::Delay).with_channels(4).with_normalize(true))
    } else {
        ModelConfig::AdmmNet(AdmmNetConfig::cpu(m, t).with_normalize(true))
    }
}

/// Sizes by mode, and epochs from a measured training step of each network.
pub(super) fn make_plan(r: &Request, lidar: &Dataset, flim: &Dataset, obs: &dyn Observer) -> Result<Plan> {
    let [h, w] = r.size;
    let crop = if h > 32 && w > 32 { Some([32, 32]) } else { None };
    let [ch, cw] = crop.unwrap_or(r.size);
    let codes = generate::prototype_codes(r.seed)?;
    let budget_s = r.budget_minutes * 60.0 * TRAINING_SHARE;
    let mut trainings = Vec::new();
    for (name, title, share) in TRAININGS {
        let ds = if name.ends_with("flim") { flim } else { lidar };
        if name.starts_with("zoo") && zoo_entry(ds).is_none() {
            obs.line(&format!("  {name}: skipped, the zoo has no entry {ZOO_ENTRY} for these bins (see TCSENSE_ZOO)"));
            continue;
        }
        let a = sensor(&codes, ds)?;
        let step = tcsense_train::bench::bench_step(a.matrix(), &model_of(name, ds), ch, cw, 3)?.step_ms;
        // learning the codes adds the operators' rebuild from A(θ) and the logits' step
        let step = if name.starts_with("learned") { step * 1.3 } else { step } + STEP_OVERHEAD_MS;
        let train_items = ds.manifest.splits.iter().find(|s| s.name == "train").map_or(0, |s| s.count);
        let steps_per_epoch = train_items.div_ceil(2).max(1);
        let fit = (share * budget_s / (step / 1e3 * steps_per_epoch as f64)).floor() as usize;
        // deep sensing needs relaxed epochs and at least one on the projected codes
        let epochs = fit.max(if name.starts_with("learned") { 3 } else { 1 });
        obs.line(&format!("  {name}: {step:.1} ms per step at {ch}x{cw}, {steps_per_epoch} steps per epoch → {epochs} epochs"));
        trainings.push(TrainPlan {
            name: name.into(),
            title: title.into(),
            budget_s: share * budget_s,
            step_ms: step,
            steps_per_epoch,
            epochs,
        });
    }
    let q = r.quick;
    Ok(Plan {
        request: r.clone(),
        crop,
        candidates: if q { 4 } else { 8 },
        select_items: if q { 1 } else { 2 },
        lidar_eval_items: if q { 4 } else { 8 },
        flim_eval_items: if q { 2 } else { 4 },
        val_items: if q { 4 } else { 8 },
        timing_rounds: if q { 2 } else { 3 },
        trainings,
    })
}
