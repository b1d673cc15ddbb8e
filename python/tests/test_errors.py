"""Bad input raises a Python exception naming the argument or the file, with the command
line's message."""

import numpy as np
import pytest

import tcsense


def test_dtype_is_a_type_error(sensor, scene):
    with pytest.raises(TypeError, match=r"x: expected a numpy array of float32, got dtype float64"):
        sensor.forward(scene.astype(np.float64))
    with pytest.raises(TypeError, match=r"y: expected a numpy array of float32, got list"):
        sensor.adjoint([[1.0]])


def test_bad_shapes(sensor, scene):
    with pytest.raises(tcsense.TcsenseError, match=r"x: shape \[8, 8\]; expected \[T, H, W\] or \[B, T, H, W\]"):
        sensor.forward(scene[0])
    # 7 pixels wide is not a multiple of the 2×2 block
    with pytest.raises(tcsense.TcsenseError, match=r"7"):
        sensor.forward(np.zeros((32, 8, 7), dtype=np.float32))
    # 16 bins for a 32-bin sensor
    with pytest.raises(tcsense.TcsenseError, match=r"16"):
        sensor.forward(np.zeros((16, 8, 8), dtype=np.float32))
    with pytest.raises(tcsense.TcsenseError, match=r"32 time bins|T = L·K = 32"):
        sensor.measure(np.zeros((16, 8, 8), dtype=np.float32))
    with pytest.raises(tcsense.TcsenseError, match=r"measurements y"):
        tcsense.tval3(np.zeros((3, 8, 8), dtype=np.float32), sensor)


def test_nan(sensor, scene):
    y = sensor.forward(scene)
    y[1, 2, 3] = np.nan
    with pytest.raises(tcsense.TcsenseError, match=r"measurements y.*(finite|NaN)|(finite|NaN).*measurements y"):
        tcsense.tval3(y, sensor)
    x = scene.copy()
    x[0, 0, 0] = np.inf
    with pytest.raises(tcsense.TcsenseError, match=r"x"):
        sensor.measure(x)


def test_mismatched_codes(cli, codes, sensor, scene, tmp_path):
    # measurements of these codes, with their sidecar, read by a sensor of other codes
    np.save(tmp_path / "x.npy", scene)
    codes.save(tmp_path / "c.json")
    cli("simulate", "--codes", tmp_path / "c.json", "--irf", "physical", "--cube", tmp_path / "x.npy", "-o", tmp_path / "y.npy")
    assert np.array_equal(sensor.load_measurements(tmp_path / "y.npy"), np.load(tmp_path / "y.npy"))
    other = tcsense.Sensor(tcsense.Codes.generate(taps=4, block=(2, 2), length=32, tap_constraint=True, hamming=2, window=2, seed=2), irf="physical")
    with pytest.raises(tcsense.TcsenseError, match=r"y\.meta\.json"):
        other.load_measurements(tmp_path / "y.npy")
    # the ideal IRF is another matrix than the measurements' physical one
    with pytest.raises(tcsense.TcsenseError, match=r"y\.meta\.json"):
        tcsense.Sensor(codes, irf="ideal").load_measurements(tmp_path / "y.npy")
    # what the module writes, the command line reads with the same rules
    sensor.save_measurements(tmp_path / "y2.npy", sensor.forward(scene))
    assert other is not None
    p = cli("reconstruct", "tval3", "--codes", tmp_path / "c.json", "--irf", "ideal", "--measurements", tmp_path / "y2.npy", "-o", tmp_path / "xt.npy", check=False)
    assert p.returncode == 2 and "y2.meta.json" in p.stderr


def test_learned_decoder_refuses_other_codes(sensor, scene):
    run = tcsense.open_run("zoo:admm-lidar-delay")
    other = tcsense.Sensor(tcsense.Codes.generate(taps=4, block=(2, 2), length=32, tap_constraint=True, hamming=2, window=2, seed=2), irf="physical")
    assert run.codes != other.codes
    with pytest.raises(tcsense.TcsenseError, match=r"trained with codes"):
        run.decode(other.forward(scene), other)


def test_missing_files(tmp_path):
    missing = tmp_path / "nope.json"
    with pytest.raises(FileNotFoundError, match=r"nope\.json") as e:
        tcsense.Codes.load(missing)
    assert e.value.filename == str(missing)
    with pytest.raises(FileNotFoundError, match=r"no-run"):
        tcsense.open_run(tmp_path / "no-run")
    with pytest.raises(FileNotFoundError, match=r"cal-dir"):
        tcsense.Sensor(tcsense.Codes.generate(seed=1), calibration=tmp_path / "cal-dir")
    with pytest.raises(FileNotFoundError, match=r"m\.onnx"):
        tcsense.OnnxModel(tmp_path / "m.onnx")
    with pytest.raises(FileNotFoundError, match=r"ds"):
        tcsense.Dataset(tmp_path / "ds")


def test_bad_files_and_settings(tmp_path):
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(tcsense.TcsenseError, match=r"bad\.json"):
        tcsense.Codes.load(tmp_path / "bad.json")
    with pytest.raises(tcsense.TcsenseError, match=r"zoo:no-such-entry"):
        tcsense.open_run("zoo:no-such-entry")
    with pytest.raises(tcsense.TcsenseError, match=r'unknown setting\(s\) \["mux"\]'):
        tcsense.tval3(np.zeros((4, 8, 8), dtype=np.float32), tcsense.Sensor(tcsense.Codes.generate(seed=1)), mux=3)
    with pytest.raises(tcsense.TcsenseError, match=r"irf \"gaussian\""):
        tcsense.Sensor(tcsense.Codes.generate(seed=1), irf="gaussian")
    with pytest.raises(tcsense.TcsenseError, match=r"--size 12x12"):
        tcsense.run_demo(tmp_path / "demo", quick=True, size=(12, 12))
    assert not (tmp_path / "demo").exists()


def test_violations_are_listed():
    bits = np.zeros((4, 4, 32), dtype=np.uint8)
    bits[:, 0, :] = 1
    bits[0, :, 5] = 1  # subpixel 0 has all four taps on at mask 5
    codes = tcsense.Codes.from_bits(bits, block=(2, 2), tap_constraint=True)
    v = codes.violations()
    assert not codes.feasible
    assert len(v) == 1 and v[0]["subpixel"] == 0 and v[0]["mask"] == 5
    bits[0, 1:, 5] = 0
    assert tcsense.Codes.from_bits(bits, block=(2, 2), tap_constraint=True).feasible
    with pytest.raises(tcsense.TcsenseError, match=r"bits\[0, 0, 0\] = 2"):
        tcsense.Codes.from_bits(bits * 2, block=(2, 2))


def test_projection_is_feasible_and_follows_the_logits():
    rng = np.random.default_rng(0)
    target = tcsense.Codes.generate(taps=4, block=(2, 2), length=32, tap_constraint=True, hamming=2, window=2, seed=9)
    # logits that favour the target codes: the projection gives them back
    logits = (target.bits.astype(np.float32) * 2 - 1) + 0.1 * rng.standard_normal((4, 4, 32)).astype(np.float32)
    p = tcsense.Codes.project(logits, block=(2, 2), tap_constraint=True, hamming=2, window=2)
    assert p.feasible
    assert np.array_equal(p.bits, target.bits)
