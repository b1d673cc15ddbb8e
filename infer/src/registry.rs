//! The decoder registry, beside the contract: every decoder the toolkit opens by name, in one
//! table ([`Registry::builtin`]). `tcsense reconstruct`, `eval`, the demo, the bring-up and
//! Python's `open_decoder` open decoders only through it, so a new decoder is its
//! implementation of [`Decoder`] plus one [`Entry`] in the table.
//!
//! A name is `NAME` or `NAME:ARG` (the entry says whether it takes an argument: a run
//! directory, a zoo entry, a model file, a count), optionally followed by `+fit`: a decoder of
//! cubes whose peaks are refined by the fit in the tap domain ([`crate::fitted::PeaksThenFit`]).
//! A caller may extend the table ([`Registry::with`]); the names of the built-in decoders are
//! constants in [`names`].
//!
//! ```
//! use tcsense_infer::registry::{names, DecoderSettings, Registry};
//! use tcsense_models::Device;
//!
//! let registry = Registry::builtin();
//! let fit = registry.open("depth-fit:1", &DecoderSettings::default(), &Device::flex()).unwrap();
//! assert_eq!(fit.decoder.name(), names::DEPTH_FIT);
//! assert!(fit.sensor.is_none()); // a fit decodes any sensor
//! assert!(registry.open("nonsense", &DecoderSettings::default(), &Device::flex()).is_err());
//! ```

use std::path::Path;

use tcsense_fits::depth::DepthFitOptions;
use tcsense_models::decoder::Tval3Decoder;
pub use tcsense_models::decoder::{check_measurements, Control, Decoded, Decoder, Step};
use tcsense_models::{runs, Device, Tval3Options};
use tcsense_sensor::{Codes, Sensor};

use crate::{InferError, Result};
use tcsense_fits::lifetime_taps::TapFitOptions;

/// The names of the built-in decoders.
pub mod names {
    /// TVAL3, the paper's iterative decoder of cubes.
    pub const TVAL3: &str = "tval3";
    /// Ranges fitted to the tap images (`depth-fit:1`, `depth-fit:2` returns).
    pub const DEPTH_FIT: &str = "depth-fit";
    /// Ranges fitted to the tap images, the window's costs pooled with those of its
    /// neighbours of like range (`depth-fit-pooled:N`, N×N neighbourhood).
    pub const DEPTH_FIT_POOLED: &str = "depth-fit-pooled";
    /// Lifetimes fitted to the tap images.
    pub const LIFETIME_FIT: &str = "lifetime-fit";
    /// Lifetimes fitted to the tap images, the window's costs pooled with those of its
    /// neighbours of like lifetime (`lifetime-fit-pooled:N`, N×N neighbourhood).
    pub const LIFETIME_FIT_POOLED: &str = "lifetime-fit-pooled";
    /// An ADMM-Net run (`admm-net:RUN`).
    pub const ADMM_NET: &str = tcsense_models::runs::network_names::ADMM_NET;
    /// An Aᵀ + U-Net run, its ranges refined in the tap domain (`unet:RUN`).
    pub const UNET: &str = tcsense_models::runs::network_names::UNET;
    /// An Aᵀ + U-Net run, its own ranges (`unet-raw:RUN`).
    pub const UNET_RAW: &str = "unet-raw";
    /// A lifetime network run (`lifetime:RUN`).
    pub const LIFETIME: &str = tcsense_models::runs::network_names::LIFETIME;
    /// A zoo entry of any kind (`zoo:NAME`).
    pub const ZOO: &str = "zoo";
    /// An exported model through ONNX Runtime (`onnx:MODEL.onnx`).
    pub const ONNX: &str = "onnx";
    /// An exported depth model through ONNX Runtime, its ranges as the graph gives them
    /// (`onnx-raw:MODEL.onnx`).
    pub const ONNX_RAW: &str = "onnx-raw";
    /// The suffix that refines a cube decoder's peaks in the tap domain.
    pub const PLUS_FIT: &str = "+fit";

    /// Whether the entry `key` may fit an onset, and so take a known one: the lifetime fits,
    /// and the network runs and zoo entries (a lifetime network on the fit's evidence; any
    /// other run refuses it when opened).
    pub fn fits_onset(key: &str) -> bool {
        [LIFETIME_FIT, LIFETIME_FIT_POOLED, LIFETIME, ZOO].contains(&key)
    }
}

/// A decoder opened by name, with the sensor it was trained for (learned decoders and
/// exported models).
pub struct NamedDecoder {
    /// The name as given (`tval3`, `admm-net:RUN`).
    pub label: String,
    pub decoder: Box<dyn Decoder>,
    /// The run's or model's sensor (its codes, sampling, IRF and matrix): a learned decoder is
    /// evaluated with its own codes only. `None` for decoders of any sensor (TVAL3, the fits).
    pub sensor: Option<Sensor>,
}

impl NamedDecoder {
    /// The codes it was trained with (learned decoders).
    pub fn codes(&self) -> Option<&Codes> {
        self.sensor.as_ref().map(Sensor::codes)
    }
}

/// The settings a decoder may take when it is opened; each decoder reads those that apply to
/// it (the defaults are every decoder's own).
#[derive(Debug, Clone, Default)]
pub struct DecoderSettings {
    /// TVAL3's options.
    pub tval3: Tval3Options,
    /// The fit of lifetimes to the taps.
    pub tap_fit: TapFitOptions,
    /// The fit of ranges to the taps (`depth-fit:K` sets its returns).
    pub depth_fit: DepthFitOptions,
    /// A known onset (`tap_fit.onset_s`) goes to the decoders that fit one and not to the
    /// others, instead of being refused by those (an evaluation's onset of its dataset).
    pub onset_where_taken: bool,
}

/// What an entry's `open` is given.
pub struct Opening<'a> {
    /// The whole name as given, for the decoder's label and messages.
    pub label: &'a str,
    /// The part after `NAME:`, for entries that take one.
    pub arg: Option<&'a str>,
    pub settings: &'a DecoderSettings,
    pub device: &'a Device,
}

/// Whether an entry's name takes `:ARG`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ArgUse {
    /// `NAME` only.
    None,
    /// `NAME` or `NAME:ARG`.
    Optional,
    /// `NAME:ARG`.
    Required,
}

/// One decoder of the table.
#[derive(Clone)]
pub struct Entry {
    /// The name before any `:` (one of [`names`] for the built-in decoders).
    pub name: &'static str,
    /// How it is written, e.g. `depth-fit[:K]`, `unet:RUN`.
    pub usage: &'static str,
    /// One line for help and listings.
    pub summary: &'static str,
    pub arg: ArgUse,
    /// Whether it gives cubes, so that `NAME+fit` may refine their peaks.
    pub cubes: bool,
    /// Open it.
    pub open: fn(&Opening<'_>) -> Result<NamedDecoder>,
}

/// The table of decoders.
#[derive(Clone)]
pub struct Registry {
    entries: Vec<Entry>,
}

impl Registry {
    /// Every decoder the toolkit ships.
    pub fn builtin() -> Registry {
        use names::*;
        Registry {
            entries: vec![
                Entry {
                    name: TVAL3,
                    usage: "tval3",
                    summary: "TV-regularised reconstruction of cubes (the paper's iterative decoder)",
                    arg: ArgUse::None,
                    cubes: true,
                    open: open_tval3,
                },
                Entry {
                    name: DEPTH_FIT,
                    usage: "depth-fit[:K]",
                    summary: "ranges fitted to the tap images, K = 1 or 2 returns per pixel (default 2); no network",
                    arg: ArgUse::Optional,
                    cubes: false,
                    open: open_depth_fit,
                },
                Entry {
                    name: DEPTH_FIT_POOLED,
                    usage: "depth-fit-pooled[:N]",
                    summary: "the range fit over 3x3 windows, each pooled with the neighbouring 3x3 windows that tile NxN pixels (N = 9, 15, 21…, default 15), weighted by how much their posteriors overlap: the fit in bright light, a wider window on one surface in dim light; two returns (reconstruct --returns 1 for one); no network",
                    arg: ArgUse::Optional,
                    cubes: false,
                    open: open_depth_fit_pooled,
                },
                Entry {
                    name: LIFETIME_FIT,
                    usage: "lifetime-fit[:N]",
                    summary: "lifetimes fitted to the tap images (a reconvolution fit in the measurement domain) over windows of NxN pixels (odd, default 3); no network",
                    arg: ArgUse::Optional,
                    cubes: false,
                    open: open_lifetime_fit,
                },
                Entry {
                    name: LIFETIME_FIT_POOLED,
                    usage: "lifetime-fit-pooled[:N]",
                    summary: "the fit to the taps over 3x3 windows, each pooled with the neighbouring 3x3 windows that tile NxN pixels (N = 9, 15, 21…, default 15), weighted by how much their posteriors overlap: the 3x3 fit in bright light, a wider window in dim light; no network",
                    arg: ArgUse::Optional,
                    cubes: false,
                    open: open_lifetime_fit_pooled,
                },
                Entry {
                    name: ADMM_NET,
                    usage: "admm-net:RUN",
                    summary: "an ADMM-Net training run (RUN: a directory or zoo:NAME): cubes",
                    arg: ArgUse::Required,
                    cubes: true,
                    open: open_admm_net,
                },
                Entry {
                    name: UNET,
                    usage: "unet:RUN",
                    summary: "an Aᵀ + U-Net run: ranges with a confidence, refined in the tap domain",
                    arg: ArgUse::Required,
                    cubes: false,
                    open: open_unet,
                },
                Entry {
                    name: UNET_RAW,
                    usage: "unet-raw:RUN",
                    summary: "an Aᵀ + U-Net run: the network's own ranges, no fit",
                    arg: ArgUse::Required,
                    cubes: false,
                    open: open_unet_raw,
                },
                Entry {
                    name: LIFETIME,
                    usage: "lifetime:RUN",
                    summary: "a lifetime network run: τ_m, τ₁, τ₂, α₁ with a confidence and the intensity",
                    arg: ArgUse::Required,
                    cubes: false,
                    open: open_lifetime,
                },
                Entry {
                    name: ZOO,
                    usage: "zoo:NAME",
                    summary: "a zoo entry, whatever its kind (`tcsense zoo list`)",
                    arg: ArgUse::Required,
                    cubes: true,
                    open: open_zoo,
                },
                Entry {
                    name: ONNX,
                    usage: "onnx:MODEL.onnx",
                    summary: "an exported model through ONNX Runtime",
                    arg: ArgUse::Required,
                    cubes: true,
                    open: open_onnx,
                },
                Entry {
                    name: ONNX_RAW,
                    usage: "onnx-raw:MODEL.onnx",
                    summary: "an exported depth model through ONNX Runtime, its ranges as the graph gives them (no range fit after it: for a graph from the taps, `export onnx --from-taps`, what any ONNX runtime gives with the file alone)",
                    arg: ArgUse::Required,
                    cubes: false,
                    open: open_onnx_raw,
                },
            ],
        }
    }

    /// This table and `entry` (which replaces an entry of the same name).
    pub fn with(mut self, entry: Entry) -> Registry {
        self.entries.retain(|e| e.name != entry.name);
        self.entries.push(entry);
        self
    }

    /// The entries, in the table's order.
    pub fn entries(&self) -> &[Entry] {
        &self.entries
    }

    /// The entry of `name` (the part before any `:`).
    pub fn entry(&self, name: &str) -> Option<&Entry> {
        self.entries.iter().find(|e| e.name == name)
    }

    /// Every usage, comma-separated, for messages.
    pub fn usages(&self) -> String {
        let mut u: Vec<&str> = self.entries.iter().map(|e| e.usage).collect();
        u.push("NAME+fit");
        u.join(", ")
    }

    /// One line per decoder: usage and summary, for help text.
    pub fn listing(&self) -> String {
        let w = self.entries.iter().map(|e| e.usage.chars().count()).max().unwrap_or(0);
        let mut s: String = self.entries.iter().map(|e| format!("  {:w$}  {}\n", e.usage, e.summary)).collect();
        s.push_str(&format!(
            "  {:w$}  a decoder of cubes (tval3, admm-net:RUN, zoo:NAME, onnx:MODEL.onnx) whose peaks are refined in the tap domain\n",
            "NAME+fit"
        ));
        s
    }

    /// Open the decoder `name` (`NAME`, `NAME:ARG`, either followed by `+fit`).
    pub fn open(&self, name: &str, settings: &DecoderSettings, device: &Device) -> Result<NamedDecoder> {
        if let Some(inner) = name.strip_suffix(names::PLUS_FIT) {
            let entry = self.entry(entry_name(inner));
            if inner.ends_with(names::PLUS_FIT) || !entry.is_some_and(|e| e.cubes) {
                return Err(InferError::InvalidParam {
                    field: "decoder",
                    got: name.into(),
                    expected:
                        "+fit after a decoder of cubes: tval3+fit, admm-net:RUN+fit, zoo:NAME+fit or onnx:MODEL.onnx+fit of an ADMM-Net"
                            .into(),
                });
            }
            let d = self.open(inner, settings, device)?;
            return Ok(NamedDecoder {
                label: name.into(),
                decoder: Box::new(crate::fitted::PeaksThenFit::new(d.decoder)),
                sensor: d.sensor,
            });
        }
        let (key, arg) = match name.split_once(':') {
            Some((k, a)) => (k, Some(a)),
            None => (name, None),
        };
        let entry = self.entry(key).ok_or_else(|| InferError::UnknownDecoder { name: name.into(), known: self.usages() })?;
        // a known onset is for the decoders that fit one (a network run is checked when opened)
        if let (Some(t), false) = (settings.tap_fit.onset_s, settings.onset_where_taken) {
            if !names::fits_onset(key) {
                return Err(InferError::InvalidParam {
                    field: "onset",
                    got: format!("{} ns", (t * 1e15).round() / 1e6),
                    expected: format!(
                        "no onset for {name}, which fits none: a known onset is for the lifetime fits and the lifetime networks on the fit's evidence (lifetime:RUN, zoo:NAME)"
                    ),
                });
            }
        }
        match (entry.arg, arg) {
            (ArgUse::None, Some(_)) | (ArgUse::Required, None) | (_, Some("")) => {
                return Err(InferError::InvalidParam {
                    field: "decoder",
                    got: name.into(),
                    expected: format!("{} ({})", entry.usage, entry.summary),
                })
            }
            _ => {}
        }
        (entry.open)(&Opening { label: name, arg, settings, device })
    }
}

/// The entry a decoder name opens: `NAME` of `NAME` and `NAME:ARG`, either followed by `+fit`
/// (whose settings are the inner decoder's).
pub fn entry_name(name: &str) -> &str {
    let inner = name.strip_suffix(names::PLUS_FIT).unwrap_or(name);
    inner.split_once(':').map_or(inner, |(k, _)| k)
}

/// Open a decoder of the built-in table by name with TVAL3's options `tval3` and every other
/// decoder's defaults ([`Registry::open`]).
pub fn open_decoder(name: &str, tval3: &Tval3Options, device: &Device) -> Result<NamedDecoder> {
    open_decoder_at_onset(name, tval3, None, device)
}

/// [`open_decoder`] with the data's onset (s) when known: the lifetime fits and the lifetime
/// networks on the fit's evidence take it (they fit only the IRF's width), the others decode
/// as they would without it.
pub fn open_decoder_at_onset(name: &str, tval3: &Tval3Options, onset_s: Option<f64>, device: &Device) -> Result<NamedDecoder> {
    let tap_fit = TapFitOptions { onset_s, ..Default::default() };
    tap_fit.validate().map_err(|msg| InferError::InvalidParam { field: "onset", got: format!("{onset_s:?} s"), expected: msg })?;
    Registry::builtin().open(name, &DecoderSettings { tval3: *tval3, tap_fit, onset_where_taken: true, ..Default::default() }, device)
}

fn any_sensor(o: &Opening<'_>, decoder: Box<dyn Decoder>) -> Result<NamedDecoder> {
    Ok(NamedDecoder { label: o.label.into(), decoder, sensor: None })
}

fn open_tval3(o: &Opening<'_>) -> Result<NamedDecoder> {
    any_sensor(o, Box::new(Tval3Decoder::new(o.settings.tval3)?))
}

fn open_depth_fit(o: &Opening<'_>) -> Result<NamedDecoder> {
    let mut opts = o.settings.depth_fit.clone();
    if let Some(r) = o.arg {
        opts.returns = r.parse().ok().filter(|r| (1..=2).contains(r)).ok_or_else(|| InferError::InvalidParam {
            field: "decoder",
            got: o.label.into(),
            expected: "depth-fit:1 or depth-fit:2 (returns per pixel)".into(),
        })?;
    }
    any_sensor(o, Box::new(crate::fitted::DepthFitDecoder::new(opts)?))
}

fn open_depth_fit_pooled(o: &Opening<'_>) -> Result<NamedDecoder> {
    let opts = o.settings.depth_fit.clone();
    let max = tcsense_fits::range::MAX_WINDOW;
    let window = opts.fit.window;
    let side = match o.arg {
        None => POOL_LIKE_SIDE,
        Some(n) => {
            n.parse().ok().filter(|&n: &usize| tcsense_fits::evidence::pooled_side(n, window)).ok_or_else(|| InferError::InvalidParam {
                field: "decoder",
                got: o.label.into(),
                expected: format!(
                    "depth-fit-pooled:N with N an odd multiple of the window's side {window} above it, up to {max} pixels (e.g. 9, 15, 21)"
                ),
            })?
        }
    };
    any_sensor(o, Box::new(crate::fitted::DepthFitDecoder::new(opts.pooled(side))?))
}

fn open_lifetime_fit(o: &Opening<'_>) -> Result<NamedDecoder> {
    let mut opts = o.settings.tap_fit.clone();
    if let Some(n) = o.arg {
        let max = tcsense_fits::range::MAX_WINDOW;
        opts.window = n.parse().ok().filter(|n: &usize| n % 2 == 1 && *n <= max).ok_or_else(|| InferError::InvalidParam {
            field: "decoder",
            got: o.label.into(),
            expected: format!("lifetime-fit:N with N an odd window side from 1 to {max} pixels"),
        })?;
    }
    any_sensor(o, Box::new(crate::fitted::TapFitDecoder::new(opts)?))
}

/// The default neighbourhood of `lifetime-fit-pooled`.
pub const POOL_LIKE_SIDE: usize = 15;

fn open_lifetime_fit_pooled(o: &Opening<'_>) -> Result<NamedDecoder> {
    let mut opts = o.settings.tap_fit.clone();
    let max = tcsense_fits::range::MAX_WINDOW;
    opts.pool_like = match o.arg {
        None => POOL_LIKE_SIDE,
        Some(n) => n.parse().ok().filter(|&n: &usize| tcsense_fits::lifetime_taps::pooled_side(n, opts.window)).ok_or_else(|| {
            InferError::InvalidParam {
                field: "decoder",
                got: o.label.into(),
                expected: format!(
                    "lifetime-fit-pooled:N with N an odd multiple of the window's side {} above it, up to {max} pixels (e.g. 9, 15, 21)",
                    opts.window
                ),
            }
        })?,
    };
    any_sensor(o, Box::new(crate::fitted::TapFitDecoder::new(opts)?))
}

/// A training run of the network `kind` (its ranges fitted in the tap domain or not).
fn open_run(o: &Opening<'_>, kind: &str, range_fit: bool) -> Result<NamedDecoder> {
    let dir = o.arg.unwrap_or_default();
    let opts = runs::OpenOptions { range_fit, onset_s: o.settings.tap_fit.onset_s, onset_strict: !o.settings.onset_where_taken };
    let run = runs::open_opts(&tcsense_models::zoo::resolve(dir)?, o.device, &opts)?;
    let got = run.spec.model.name();
    if got != kind {
        return Err(InferError::File {
            path: run.dir.join(runs::CONFIG_FILE),
            msg: format!("field decoder is {got:?}: a {got} run, not {kind}; name it {got}:{dir}"),
        });
    }
    Ok(NamedDecoder { label: o.label.into(), decoder: run.decoder, sensor: Some(run.sensor) })
}

fn open_admm_net(o: &Opening<'_>) -> Result<NamedDecoder> {
    open_run(o, names::ADMM_NET, false)
}

fn open_unet(o: &Opening<'_>) -> Result<NamedDecoder> {
    open_run(o, names::UNET, true)
}

fn open_unet_raw(o: &Opening<'_>) -> Result<NamedDecoder> {
    open_run(o, names::UNET, false)
}

fn open_lifetime(o: &Opening<'_>) -> Result<NamedDecoder> {
    open_run(o, names::LIFETIME, false)
}

fn open_zoo(o: &Opening<'_>) -> Result<NamedDecoder> {
    let opts = runs::OpenOptions { onset_s: o.settings.tap_fit.onset_s, onset_strict: !o.settings.onset_where_taken, ..Default::default() };
    let run = runs::open_opts(&tcsense_models::zoo::resolve(o.label)?, o.device, &opts)?;
    Ok(NamedDecoder { label: o.label.into(), decoder: run.decoder, sensor: Some(run.sensor) })
}

fn open_onnx(o: &Opening<'_>) -> Result<NamedDecoder> {
    let model = crate::runtime::OnnxModel::open(Path::new(o.arg.unwrap_or_default()), 0)?;
    let sensor = model.meta.sensor()?;
    Ok(NamedDecoder { label: o.label.into(), decoder: Box::new(crate::runtime::OnnxDecoder::new(model)), sensor: Some(sensor) })
}

fn open_onnx_raw(o: &Opening<'_>) -> Result<NamedDecoder> {
    let model = crate::runtime::OnnxModel::open(Path::new(o.arg.unwrap_or_default()), 0)?;
    let sensor = model.meta.sensor()?;
    let decoder = crate::runtime::OnnxDecoder::new(model).without_range_fit();
    Ok(NamedDecoder { label: o.label.into(), decoder: Box::new(decoder), sensor: Some(sensor) })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_open_or_say_what_is_known() {
        let r = Registry::builtin();
        let s = DecoderSettings::default();
        let d = Device::flex();
        assert_eq!(r.open("tval3", &s, &d).unwrap().decoder.name(), names::TVAL3);
        assert_eq!(r.open("lifetime-fit", &s, &d).unwrap().label, "lifetime-fit");
        assert_eq!(r.open("lifetime-fit:9", &s, &d).unwrap().label, "lifetime-fit:9");
        assert_eq!(r.open("lifetime-fit-pooled", &s, &d).unwrap().label, "lifetime-fit-pooled");
        assert_eq!(r.open("lifetime-fit-pooled:9", &s, &d).unwrap().label, "lifetime-fit-pooled:9");
        assert_eq!(r.open("depth-fit-pooled", &s, &d).unwrap().label, "depth-fit-pooled");
        assert_eq!(r.open("depth-fit-pooled:21", &s, &d).unwrap().decoder.name(), names::DEPTH_FIT_POOLED);
        assert_eq!(r.open("depth-fit:1", &s, &d).unwrap().decoder.name(), names::DEPTH_FIT);
        for bad in [
            "tval3:x",
            "unet",
            "depth-fit:3",
            "depth-fit:",
            "unet+fit",
            "depth-fit+fit",
            "tval3+fit+fit",
            "lifetime-fit:2",
            "lifetime-fit:0",
            "lifetime-fit-pooled:3",
            "lifetime-fit-pooled:12",
            "lifetime-fit-pooled:11",
            "lifetime-fit-pooled:999",
            "depth-fit-pooled:3",
            "depth-fit-pooled:12",
            "depth-fit-pooled:x",
        ] {
            assert!(r.open(bad, &s, &d).is_err(), "{bad}");
        }
        let e = r.open("nope", &s, &d).err().unwrap().to_string();
        assert!(e.contains("nope") && e.contains("depth-fit[:K]") && e.contains("onnx:MODEL.onnx"), "{e}");
        assert!(r.open("tval3+fit", &s, &d).is_ok());
        // every entry is listed once, with its summary
        let l = r.listing();
        assert!(r.entries().iter().all(|e| l.matches(e.summary).count() == 1));
    }
}
