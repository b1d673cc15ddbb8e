//! `tcsense bench decoders`: every decoder's speed on a stream at the sensor's frame size
//! beside its accuracy on a light ladder (`tcsense_infer::speed`, `tcsense_infer::eval`), as
//! a table, JSON, CSV and a speed–accuracy figure.

use anyhow::Result;
use clap::Args;
use serde_json::json;
use std::path::PathBuf;
use tcsense_datasets::Dataset;
use tcsense_infer::eval::{evaluate_ladder, EvalRow, EvalSettings};
use tcsense_infer::figures::Series;
use tcsense_infer::speed::{stream_speed, tiled_frames};
use tcsense_sensor::npy::write_bytes;
use tcsense_sensor::output::Outputs;
use tcsense_sensor::NoiseParams;

use super::dataset::interrupt_flag;
use super::recon::Tval3Args;
use super::sensor::SensorArgs;

/// The most tap-image bytes the speed's stream holds in memory.
const MAX_STREAM_BYTES: u128 = 2 << 30;

/// The settings of `tcsense bench decoders`.
#[derive(Args)]
pub struct BenchDecodersArgs {
    /// Dataset whose items are the scenes: the accuracy on its split, the speed on its items
    /// mirrored to --frame.
    #[arg(long)]
    dataset: PathBuf,
    /// Split.
    #[arg(long, default_value = "test")]
    split: String,
    /// Items of the split evaluated at each light level.
    #[arg(long, default_value_t = 8, value_parser = super::count_in(1, 1_000_000))]
    items: usize,
    #[command(flatten)]
    sensor: SensorArgs,
    /// Decoders, by their registry names (as `eval --decoder`): `depth-fit:1`, `depth-fit`,
    /// `onnx:MODEL.onnx` (the deployed path: ONNX Runtime with the fits `tcsense infer` runs
    /// around it), `unet:zoo:NAME` (burn) …; repeat the flag.
    #[arg(long, num_args = 1.., required = true)]
    decoder: Vec<String>,
    #[command(flatten)]
    tval3: Tval3Args,
    #[command(flatten)]
    device: super::DeviceArgs,
    /// The light levels of the accuracy (the brightest tap's signal as a share of the full well).
    #[arg(long, value_delimiter = ',', default_value = "0.8,0.1,0.02,0.005", value_parser = super::number_in(1e-6, 1.0))]
    light: Vec<f64>,
    /// Ambient light as a signal-to-background ratio (default: none).
    #[arg(long, value_parser = super::number_in(1e-3, 1e6))]
    sbr: Option<f64>,
    /// Frame size HxW of the speed's stream (the prototype's 188x212 by default).
    #[arg(long, default_value = "188x212", value_parser = super::parse_hw)]
    frame: (usize, usize),
    /// Frames in the speed's stream (noisy, at the first light level).
    #[arg(long, default_value_t = 30, value_parser = super::count_in(1, 100_000))]
    frames: usize,
    /// Rounds of the stream per decoder, interleaved; the median round is reported.
    #[arg(long, default_value_t = 1, value_parser = super::count_in(1, 1000))]
    rounds: usize,
    /// Noise seed.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// The results as JSON; beside it the same as CSV (`.csv`), the speed–accuracy figure
    /// (`.png`) and the photon-efficiency curve (`.photon.png`).
    #[arg(short, long)]
    output: PathBuf,
}

/// `tcsense bench decoders`.
pub fn run(a: BenchDecodersArgs) -> Result<()> {
    let sibling = |ext: &str| a.output.with_extension(ext);
    let (csv, png, photon) = (sibling("csv"), sibling("png"), sibling("photon.png"));
    let mut outputs = Outputs::plan(&[("-o", a.output.as_path()), ("-o's CSV", &csv), ("-o's figure", &png), ("-o's curve", &photon)])?;
    let ds = Dataset::open(&a.dataset)?;
    let sensor = a.sensor.sensor()?;
    let mut decoders = super::eval::open_for(&ds, &a.sensor, &sensor, &a.decoder, &a.tval3, None, &a.device)?;
    let (h, w) = a.frame;
    let (bh, bw) = sensor.nominal().block();
    if h % bh != 0 || w % bw != 0 {
        anyhow::bail!("--frame {h}x{w}: expected multiples of the sensor's {bh}x{bw} block");
    }
    // the stream is held in memory: at most 2 GiB of tap images
    let bytes = (a.frames as u128) * (sensor.nominal().taps() as u128) * (h as u128) * (w as u128) * 4;
    if bytes > MAX_STREAM_BYTES {
        anyhow::bail!(
            "--frames {} of --frame {h}x{w}: {:.1} GiB of tap images; expected a stream of at most {} GiB (fewer or smaller frames)",
            a.frames,
            bytes as f64 / (1u64 << 30) as f64,
            MAX_STREAM_BYTES >> 30
        );
    }
    let cancel = interrupt_flag();
    let pb = super::eval::item_bar();
    // speed: a stream at the first light level
    let first = NoiseParams { signal_fraction: a.light[0], ..NoiseParams::default() }
        .validate()
        .map_err(|e| anyhow::anyhow!("--light {}: {e}", a.light[0]))?;
    pb.set_message(format!("speed: {} frames of {h}x{w}", a.frames));
    pb.set_length(a.rounds as u64);
    let y = tiled_frames(&ds, &a.split, &sensor, (h, w), a.frames, &first, a.seed)?;
    let speeds = stream_speed(&mut decoders, &sensor, &y.view(), a.rounds, &|r, _| pb.set_position(r as u64), &cancel)?;
    // accuracy: the ladder
    let settings =
        EvalSettings { split: a.split.clone(), items: Some(a.items), noise: Some(first), seed: a.seed, sensor: None, sbr: a.sbr };
    let on_item = |name: &str, done: usize, of: usize| super::eval::item_done(&pb, name, done, of);
    let rows = evaluate_ladder(&ds, &sensor, &mut decoders, &settings, &a.light, &on_item, &cancel);
    pb.finish_and_clear();
    let rows = rows?;

    // the measure of accuracy: ranges in bins, else lifetimes in ns
    let lidar = rows.iter().any(|r| !r.depth_median_m.is_empty());
    if !lidar && rows.iter().all(|r| r.lifetime_mae_s.is_none()) {
        anyhow::bail!(
            "{}: the decoders gave no first-return ranges nor lifetimes on it (a LiDAR dataset with depth and decoders of depth or cubes, or a FLIm dataset and lifetime decoders)",
            a.dataset.display()
        );
    }
    let bin_m = 299_792_458.0 * sensor.nominal().bin_width_s() / 2.0;
    let error = |r: &EvalRow| -> Option<f64> {
        if lidar {
            r.depth_median_m.first().map(|m| m / bin_m)
        } else {
            r.lifetime_mae_s.map(|v| v * 1e9)
        }
    };
    let share = |r: &EvalRow| -> Option<f64> {
        if lidar {
            r.depth_within_half_bin.first().map(|s| 100.0 * s)
        } else {
            r.lifetime_coverage.map(|v| 100.0 * v)
        }
    };
    let (what, unit, share_what) = if lidar {
        ("median first-return error", "bins", "within half a bin")
    } else {
        ("lifetime MAE", "ns", "fluorophore pixels with a lifetime")
    };
    let fmt = |v: Option<f64>, d: usize| v.filter(|v| v.is_finite()).map_or("–".to_string(), |v| format!("{v:.d$}"));
    println!(
        "{} frames of {h}x{w} (signal {} of the full well), {} items of {} at each level; cells: {what} ({unit}) · {share_what} (%)",
        a.frames, a.light[0], a.items, a.split
    );
    print!("{:<40} {:>9}", "decoder", "frames/s");
    for l in &a.light {
        print!(" {:>14}", format!("signal {l}"));
    }
    println!();
    let mut csv_text = format!("decoder,frames_per_s,ms_per_frame,signal_fraction,signal_electrons,sbr,error_{unit},share_pct\n");
    for s in &speeds {
        print!("{:<40} {:>9.1}", s.decoder, s.frames_per_s);
        for r in rows.iter().filter(|r| r.decoder == s.decoder) {
            print!(" {:>14}", format!("{} · {}", fmt(error(r), 2), fmt(share(r), 0)));
            let l = r.light.expect("ladder rows carry their light");
            csv_text.push_str(&format!(
                "{},{:.3},{:.3},{},{},{},{},{}\n",
                s.decoder,
                s.frames_per_s,
                s.ms_per_frame,
                l.signal_fraction,
                l.signal_electrons,
                l.sbr.map_or(String::new(), |v| v.to_string()),
                error(r).map_or(String::new(), |v| v.to_string()),
                share(r).map_or(String::new(), |v| v.to_string())
            ));
        }
        println!();
    }

    // the figures: speed against the error at every level, and the photon-efficiency curve
    let series: Vec<Series> = speeds
        .iter()
        .map(|s| Series {
            label: s.decoder.clone(),
            points: a
                .light
                .iter()
                .map(|l| {
                    let r = rows.iter().find(|r| r.decoder == s.decoder && r.light.is_some_and(|x| x.signal_fraction == *l));
                    (s.frames_per_s, r.and_then(error).unwrap_or(f64::NAN))
                })
                .collect(),
        })
        .collect();
    let ambient = a.sbr.map_or("no ambient light".to_string(), |s| format!("ambient at SBR {s}"));
    tcsense_infer::figures::speed_accuracy(
        &outputs.stage(&png)?,
        &format!("Speed against accuracy ({h}x{w} frames, {ambient}; dots at each signal level)"),
        &format!("frames per second ({h}x{w}, one frame per call)"),
        &format!("{what} ({unit})"),
        &series,
        &a.light.iter().map(|l| l.to_string()).collect::<Vec<_>>(),
    )?;
    if lidar {
        tcsense_infer::curves::range_curve(&outputs.stage(&photon)?, &rows, &[("", sensor.nominal())], &first, a.sbr)?;
    } else {
        tcsense_infer::curves::lifetime_curve(
            &outputs.stage(&photon)?,
            &rows,
            &[("", sensor.nominal())],
            sensor.spec().sampling().k(),
            &first,
            a.sbr,
        )?;
    }
    let doc = json!({
        "dataset": a.dataset,
        "split": a.split,
        "items": a.items,
        "frame": [h, w],
        "speed": speeds,
        "accuracy": rows,
    });
    write_bytes(&outputs.stage(&a.output)?, (serde_json::to_string_pretty(&doc)? + "\n").as_bytes())?;
    write_bytes(&outputs.stage(&csv)?, csv_text.as_bytes())?;
    outputs.commit()?;
    println!("wrote {}, {}, {} and {}", a.output.display(), csv.display(), png.display(), photon.display());
    Ok(())
}
