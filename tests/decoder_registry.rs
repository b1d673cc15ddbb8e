//! The worked example of adding a decoder: its implementation of the contract plus one
//! registry entry, and it is reachable by name from the paths `reconstruct` and `eval` take
//! (`Registry::open` → `infer::decode::decode_file`, `Registry::open` → `eval::evaluate`)
//! without touching either. In the toolkit the entry is one line of `Registry::builtin`; here it
//! is added from outside with `Registry::with`.

use ndarray::{Array4, ArrayView4, Axis, Ix3};
use std::path::Path;
use std::process::Command;
use std::sync::atomic::AtomicBool;
use tcsense_datasets::Dataset;
use tcsense_infer::eval::{evaluate, EvalSettings};
use tcsense_infer::registry::{check_measurements, ArgUse, Control, Decoded, Decoder, DecoderSettings, Entry, NamedDecoder, Registry};
use tcsense_models::{Device, ModelError};
use tcsense_sensor::npy::{read_npy, write_npy};
use tcsense_sensor::output::Outputs;
use tcsense_sensor::Sensor;

/// The back-projection `x̂ = s·Aᵀy` (a trivial decoder of cubes), scaled by `s` (`adjoint:S`).
struct Adjoint {
    scale: f32,
}

impl Decoder for Adjoint {
    fn name(&self) -> &str {
        "adjoint"
    }

    fn decode(&mut self, y: ArrayView4<'_, f32>, sensor: &Sensor, ctl: &Control<'_>) -> tcsense_models::Result<Decoded> {
        check_measurements(&y, sensor.matrix())?;
        let (b, _, h, w) = y.dim();
        let plan = sensor.matrix().plan(h, w)?;
        let mut cube = Array4::<f32>::zeros((b, sensor.bins(), h, w));
        for (mut x, yb) in cube.outer_iter_mut().zip(y.outer_iter()) {
            ctl.check()?;
            x.assign(&(plan.adjoint(&yb)? * self.scale));
        }
        Ok(Decoded { cube: Some(cube), ..Default::default() })
    }
}

fn open_adjoint(o: &tcsense_infer::registry::Opening<'_>) -> tcsense_infer::Result<NamedDecoder> {
    let scale = match o.arg {
        None => 1.0,
        Some(s) => s.parse().map_err(|_| {
            tcsense_infer::InferError::Model(ModelError::InvalidParam { field: "adjoint:S", got: s.into(), expected: "a scale".into() })
        })?,
    };
    Ok(NamedDecoder { label: o.label.into(), decoder: Box::new(Adjoint { scale }), sensor: None })
}

/// The one line.
fn registry() -> Registry {
    Registry::builtin().with(Entry {
        name: "adjoint",
        usage: "adjoint[:S]",
        summary: "the back-projection s·Aᵀy",
        arg: ArgUse::Optional,
        cubes: true,
        open: open_adjoint,
    })
}

fn tcsense(dir: &Path, args: &[&str]) {
    let out = Command::new(env!("CARGO_BIN_EXE_tcsense")).current_dir(dir).args(args).output().unwrap();
    assert!(out.status.success(), "{args:?}: {}", String::from_utf8_lossy(&out.stderr));
}

#[test]
fn a_decoder_added_with_one_entry_reaches_decode_and_eval() {
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path();
    tcsense(
        d,
        &["codes", "generate", "--block", "2x2", "--taps", "4", "--length", "8", "--tap-constraint", "--seed", "1", "-o", "codes.json"],
    );
    tcsense(d, &["dataset", "lidar", "--count", "8", "--size", "8x8", "--length", "8", "--seed", "2", "-o", "ds"]);
    let sensor = Sensor::ideal(
        tcsense_sensor::Codes::load(&d.join("codes.json")).unwrap(),
        tcsense_sensor::Sampling::Oversample(1),
        tcsense_sensor::Irf::Ideal,
    )
    .unwrap();
    let reg = registry();
    assert!(reg.listing().contains("adjoint[:S]"));
    // the path of `reconstruct`: by name, then decode_file
    let ds = Dataset::open(&d.join("ds")).unwrap();
    let x = ds.load("test", "x").unwrap();
    let x0 = x.index_axis(Axis(0), 0).into_dimensionality::<Ix3>().unwrap().to_owned();
    let y = sensor.matrix().plan(8, 8).unwrap().forward(&x0.view()).unwrap();
    write_npy(&d.join("y.npy"), &y.view().into_dyn()).unwrap();
    let mut opened = reg.open("adjoint:2", &DecoderSettings::default(), &Device::flex()).unwrap();
    let never = AtomicBool::new(false);
    let out = d.join("xhat.npy");
    let mut outputs = Outputs::plan(&[("-o", out.as_path())]).unwrap();
    tcsense_infer::decode::decode_file(
        opened.decoder.as_mut(),
        &sensor,
        &d.join("y.npy"),
        &out,
        &Control::quiet(&never),
        &mut outputs,
        None,
    )
    .unwrap();
    outputs.commit().unwrap();
    let xhat = read_npy(&out).unwrap().into_dimensionality::<Ix3>().unwrap();
    let want = sensor.matrix().plan(8, 8).unwrap().adjoint(&y.view()).unwrap() * 2.0;
    assert_eq!(xhat, want, "decode_file wrote the decoder's cube");
    // its peaks refined in the tap domain: `+fit` applies to it as to any decoder of cubes
    assert!(reg.open("adjoint+fit", &DecoderSettings::default(), &Device::flex()).is_ok());
    assert!(reg.open("adjoint:x", &DecoderSettings::default(), &Device::flex()).is_err());
    // the path of `eval`: by name, beside a built-in decoder, one row each
    let mut decoders = vec![
        reg.open("adjoint", &DecoderSettings::default(), &Device::flex()).unwrap(),
        reg.open("tval3", &DecoderSettings::default(), &Device::flex()).unwrap(),
    ];
    let settings = EvalSettings { split: "test".into(), items: Some(1), noise: None, seed: 0, sensor: None, sbr: None };
    let rows = evaluate(&ds, &sensor, &mut decoders, &settings, &|_, _, _| {}, &never).unwrap();
    assert_eq!(rows.iter().map(|r| r.decoder.as_str()).collect::<Vec<_>>(), ["adjoint", "tval3"]);
    // TVAL3 inverts A; the bare back-projection does not
    assert!(rows[0].mse > 2.0 * rows[1].mse, "{} vs {}", rows[0].mse, rows[1].mse);
}
