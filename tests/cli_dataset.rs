//! End-to-end tests of `tcsense dataset …` on tiny problems.

mod common;
use common::*;
use ndarray::{Array2, Array4, Ix4};
use tcsense_datasets::lidar::LidarParams;
use tcsense_datasets::store::{Dataset, Generator, Manifest};
use tcsense_datasets::TimeGrid;
use tcsense_sensor::npy::{read_npy, write_npy};

#[test]
fn lidar_dataset_is_seeded_and_items_are_pure_functions_of_seed_and_index() {
    let d = tempdir();
    let d = d.path();
    let args = |out: &'static str, seed: &'static str| -> Vec<&'static str> {
        vec![
            "dataset",
            "lidar",
            "--count",
            "5",
            "--size",
            "8x8",
            "--shard-size",
            "2",
            "--sheet-probability",
            "1",
            "--seed",
            seed,
            "-o",
            out,
        ]
    };
    ok(d, &args("a", "7"));
    ok(d, &args("b", "7"));
    ok(d, &args("c", "8"));
    for f in ["train/x_000.npy", "train/x_001.npy", "val/depth_000.npy", "test/intensity_000.npy"] {
        assert_eq!(std::fs::read(d.join("a").join(f)).unwrap(), std::fs::read(d.join("b").join(f)).unwrap(), "{f}");
    }
    assert_ne!(std::fs::read(d.join("a/train/x_000.npy")).unwrap(), std::fs::read(d.join("c/train/x_000.npy")).unwrap());
    let ds = Dataset::open(&d.join("a")).unwrap();
    // manifest round trip
    let text = std::fs::read_to_string(d.join("a/manifest.json")).unwrap();
    let again: Manifest = serde_json::from_str(&serde_json::to_string(&ds.manifest).unwrap()).unwrap();
    assert_eq!(again, ds.manifest);
    assert!(text.contains("\"kind\": \"lidar\""));
    let counts: Vec<usize> = ds.manifest.splits.iter().map(|s| s.count).collect();
    assert_eq!(counts, vec![3, 1, 1]);
    let train = ds.load("train", "x").unwrap();
    assert_eq!(train.shape(), &[3, 32, 8, 8]);
    // the test item equals the generator's item (seed, global index 4)
    let test = ds.split("test").unwrap();
    assert_eq!(test.first_index, 4);
    let gen = Generator::Lidar(LidarParams { height: 8, width: 8, sheet_probability: 1.0, ..Default::default() });
    let item = gen.item(&TimeGrid::default(), 7, 4);
    assert_eq!(ds.item("test", 0, "x").unwrap(), item[0].1);
    ok(d, &["dataset", "show", "a", "--split", "val", "-o", "m.png"]);
    assert!(std::fs::read(d.join("m.png")).unwrap().starts_with(b"\x89PNG"));
    // an existing dataset is not overwritten without --force
    fails(d, &args("a", "9"), &["exists", "--force"]);
}

#[test]
fn flim_dataset_on_the_heterodyne_grid() {
    let d = tempdir();
    let d = d.path();
    ok(d, &["dataset", "flim", "--paper", "--count", "3", "--size", "8x8", "--seed", "2", "-o", "f"]);
    let ds = Dataset::open(&d.join("f")).unwrap();
    assert_eq!(ds.manifest.bins, 256);
    assert!((ds.manifest.bin_width_s - 205.93e-12).abs() < 0.1e-12);
    let tau = ds.load("train", "tau").unwrap();
    assert_eq!(tau.shape(), &[1, 3]);
    assert!(tau[[0, 0]] >= 0.5e-9 && tau[[0, 2]] < 3.5e-9);
    assert!((ds.load("train", "onset").unwrap()[[0, 0]] - 2e-9).abs() < 1e-15, "the paper's onset");

    // randomised by default, recorded in the manifest; a knob can be fixed
    ok(d, &["dataset", "flim", "--count", "12", "--size", "8x8", "--seed", "2", "--tau-ns", "4,5", "--lifetimes", "1", "-o", "r"]);
    let ds = Dataset::open(&d.join("r")).unwrap();
    let text = std::fs::read_to_string(d.join("r/manifest.json")).unwrap();
    assert!(text.contains("randomization") && text.contains("onset_cycle"), "{text}");
    let tau = ds.load("train", "tau").unwrap();
    assert!(tau.iter().all(|&t| (4e-9..=5e-9).contains(&t)), "{tau:?}");
    assert!(tau.rows().into_iter().all(|r| r[0] == r[1] && r[1] == r[2]), "one lifetime per scene");
    let onsets = ds.load("train", "onset").unwrap();
    assert!(onsets.iter().any(|&o| (o - 2e-9).abs() > 0.5e-9), "onsets move: {onsets:?}");
    fails(d, &["dataset", "flim", "--count", "3", "--size", "8x8", "--paper", "--tau-ns", "1,2", "-o", "x"], &["--paper"]);
    fails(d, &["dataset", "flim", "--count", "3", "--size", "8x8", "--lifetimes", "0,4", "-o", "x"], &["lifetimes"]);
    fails(d, &["dataset", "lidar", "--count", "3", "--size", "8x8", "--wall-range", "0.5,2", "-o", "x"], &["wall_range"]);
    fails(d, &["dataset", "flim", "--count", "3", "--size", "8x8", "--brightness", "a,b", "-o", "x"], &["--brightness"]);
}

#[test]
fn import_cubes_and_depth_maps() {
    let d = tempdir();
    let d = d.path();
    let cube = Array4::from_shape_fn((2, 16, 4, 6), |(f, j, r, c)| (f * 1000 + j * 31 + r * 7 + c) as f32 * 0.01);
    write_npy(&d.join("cubes.npy"), &cube.view()).unwrap();
    ok(d, &["dataset", "import", "--cube", "cubes.npy", "--length", "16", "-o", "imp"]);
    let ds = Dataset::open(&d.join("imp")).unwrap();
    let x = ds.load("test", "x").unwrap().into_dimensionality::<Ix4>().unwrap();
    assert_eq!(x, cube, "imported cube equals the file");

    // a 16-bit PNG depth map in millimetres
    let (h, w) = (4usize, 4usize);
    let mm: Vec<u16> = (0..h * w).map(|i| 1000 + 100 * i as u16).collect();
    let f = std::fs::File::create(d.join("depth.png")).unwrap();
    let mut enc = png::Encoder::new(f, w as u32, h as u32);
    enc.set_color(png::ColorType::Grayscale);
    enc.set_depth(png::BitDepth::Sixteen);
    let mut wr = enc.write_header().unwrap();
    let bytes: Vec<u8> = mm.iter().flat_map(|v| v.to_be_bytes()).collect();
    wr.write_image_data(&bytes).unwrap();
    wr.finish().unwrap();
    ok(d, &["dataset", "import", "--depth", "depth.png", "--depth-scale", "0.001", "-o", "dep"]);
    let ds = Dataset::open(&d.join("dep")).unwrap();
    let depth = ds.load("test", "depth").unwrap();
    assert!((depth[[0, 0, 1, 2]] - 1.6).abs() < 1e-6, "{}", depth[[0, 0, 1, 2]]);
    let x = ds.load("test", "x").unwrap();
    // the return of pixel (1, 2) sits at 2r/c
    let dt = ds.manifest.bin_width_s;
    let wave: Vec<f64> = (0..32).map(|j| x[[0, j, 1, 2]] as f64).collect();
    let centroid = wave.iter().enumerate().map(|(j, v)| (j as f64 + 0.5) * v).sum::<f64>() / wave.iter().sum::<f64>();
    assert!((centroid * dt - 2.0 * 1.6 / 299_792_458.0).abs() < 1e-3 * dt);
}

#[test]
fn bad_inputs_exit_2() {
    let d = tempdir();
    let d = d.path();
    let o = run(d, &["dataset", "mystery", "--count", "1", "-o", "x"]);
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("mystery"));
    fails(d, &["dataset", "lidar", "--count", "0", "-o", "x"], &["--count 0"]);
    fails(d, &["dataset", "lidar", "--count", "2", "--size", "9x8", "-o", "x"], &["9x8", "2x2 pixel block"]);
    fails(d, &["dataset", "flim", "--count", "2", "--size", "8x8", "--length", "12", "-o", "x"], &["length", "multiple of 8"]);
    // negative depth
    let mut dm = Array2::<f32>::ones((4, 4));
    dm[(2, 3)] = -0.5;
    write_npy(&d.join("neg.npy"), &dm.view()).unwrap();
    fails(d, &["dataset", "import", "--depth", "neg.npy", "-o", "x"], &["neg.npy", "negative depth", "(2, 3)"]);
    // wrong number of bins
    write_npy(&d.join("c.npy"), &ndarray::Array3::<f32>::zeros((20, 4, 4)).view()).unwrap();
    fails(d, &["dataset", "import", "--cube", "c.npy", "-o", "x"], &["c.npy", "20 time bins", "T = L·K = 32"]);
    assert!(!d.join("x").exists(), "no output after failures");
    // a manifest that is not one
    std::fs::create_dir_all(d.join("bad")).unwrap();
    std::fs::write(d.join("bad/manifest.json"), "{\"format\": 3}").unwrap();
    fails(d, &["dataset", "show", "bad", "-o", "m.png"], &["manifest.json", "malformed manifest"]);
    let _ = read_npy(&d.join("c.npy")).unwrap();
}
