"""The Python module against the command line on the same inputs: the same code path gives
the same bits."""

import json
import pathlib

import numpy as np
import pytest

import tcsense


def test_codes_generate_matches_cli(cli, codes, tmp_path):
    out = tmp_path / "c.json"
    cli("codes", "generate", "--taps", 4, "--block", "2x2", "--length", 32, "--tap-constraint", "--hamming", 2, "--window", 2, "--seed", 1, "-o", out)
    theirs = tcsense.Codes.load(out)
    assert theirs == codes
    assert theirs.digest == codes.digest
    assert np.array_equal(theirs.bits, codes.bits)
    assert codes.bits.shape == (4, 4, 32)
    # the tap constraint: exactly one tap on per subpixel and mask
    assert (codes.bits.sum(axis=1) == 1).all()


def test_code_memory_matches_cli(cli, codes, codes_file, tmp_path):
    regs = codes.to_code_memory(tmp_path / "py")
    # the seed-1 codes alias (bins 9 and 22): the command line exports them only when forced
    cli("codes", "export", codes_file, "--force", "-o", tmp_path / "cli")
    for name in ["codes.bin", "registers.json"] + [f"ch{c:02d}.bin" for c in range(16)]:
        assert (tmp_path / "py" / name).read_bytes() == (tmp_path / "cli" / name).read_bytes(), name
    assert regs["ECLEN"] == 32 // 8 - 1
    assert tcsense.Codes.from_code_memory(tmp_path / "py") == codes


def test_forward_matches_cli(cli, codes_file, sensor, scene, tmp_path):
    np.save(tmp_path / "x.npy", scene)
    cli("simulate", "--codes", codes_file, "--irf", "physical", "--cube", tmp_path / "x.npy", "-o", tmp_path / "y.npy")
    y_cli = np.load(tmp_path / "y.npy")
    y = sensor.forward(scene)
    assert y.shape == (4, 8, 8) and y.dtype == np.float32
    assert np.array_equal(y, y_cli)
    # and it is A x: y[m, r, c] = Σ_t A[n(r, c), m, t] x[t, r, c]
    a = sensor.matrix()
    n = (np.arange(8)[:, None] % 2) * 2 + (np.arange(8)[None, :] % 2)
    want = np.einsum("rcmt,trc->mrc", a[n], scene.astype(np.float64))
    np.testing.assert_allclose(y, want, rtol=1e-5, atol=1e-6)


def test_batch_forward_is_each_frame(sensor, scene):
    xb = np.stack([scene, 2 * scene])
    yb = sensor.forward(xb)
    assert yb.shape == (2, 4, 8, 8)
    assert np.array_equal(yb[0], sensor.forward(scene))
    assert np.array_equal(yb[1], sensor.forward(2 * scene))


def test_adjoint_is_the_adjoint(sensor, scene):
    rng = np.random.default_rng(3)
    v = rng.random((4, 8, 8), dtype=np.float32)
    lhs = float((sensor.forward(scene).astype(np.float64) * v).sum())
    rhs = float((scene.astype(np.float64) * sensor.adjoint(v)).sum())
    assert abs(lhs - rhs) <= 1e-5 * abs(lhs)
    a = sensor.matrix()
    n = (np.arange(8)[:, None] % 2) * 2 + (np.arange(8)[None, :] % 2)
    want = np.einsum("rcmt,mrc->trc", a[n], v.astype(np.float64))
    np.testing.assert_allclose(sensor.adjoint(v), want, rtol=1e-5, atol=1e-6)


def test_strided_input_is_read_in_place(sensor, scene):
    big = np.zeros((32, 16, 16), dtype=np.float32)
    big[:, ::2, ::2] = scene
    view = big[:, ::2, ::2]
    assert not view.flags["C_CONTIGUOUS"]
    assert np.array_equal(sensor.forward(view), sensor.forward(scene))


def test_measure_matches_cli(cli, codes_file, sensor, scene, tmp_path):
    np.save(tmp_path / "x.npy", scene)
    cli("simulate", "--codes", codes_file, "--irf", "physical", "--cube", tmp_path / "x.npy", "--noise", "--seed", 5, "-o", tmp_path / "y.npy")
    y = sensor.measure(scene, noise=True, seed=5)
    assert np.array_equal(y, np.load(tmp_path / "y.npy"))
    assert not np.array_equal(y, sensor.measure(scene, noise=True, seed=6))
    assert np.array_equal(y, sensor.measure(scene, noise=True, seed=5))
    # non-idealities, in electrons, as `simulate --tap-gain --prnu --dark --units electrons`
    ni = dict(tap_gain=0.05, prnu=0.02, dark=0.01, seed=3)
    cli("simulate", "--codes", codes_file, "--irf", "physical", "--cube", tmp_path / "x.npy", "--noise", "--seed", 5,
        "--tap-gain", 0.05, "--prnu", 0.02, "--dark", 0.01, "--sensor-seed", 3, "--units", "electrons", "-o", tmp_path / "e.npy")
    e = sensor.measure(scene, noise=True, seed=5, units="electrons", nonideal=ni)
    assert np.array_equal(e, np.load(tmp_path / "e.npy"))


def test_tval3_matches_cli(cli, codes_file, sensor, scene, tmp_path):
    y = sensor.forward(scene)
    np.save(tmp_path / "y.npy", y)
    cli("reconstruct", "tval3", "--codes", codes_file, "--irf", "physical", "--measurements", tmp_path / "y.npy", "--maxit", 40, "-o", tmp_path / "xt.npy")
    xt = tcsense.tval3(y, sensor, maxit=40)
    assert xt.shape == (32, 8, 8)
    assert np.array_equal(xt, np.load(tmp_path / "xt.npy"))
    # a reconstruction: it explains the tap images
    fit = np.linalg.norm(sensor.forward(xt) - y) / np.linalg.norm(y)
    ya = sensor.forward(sensor.adjoint(y))
    fit_adjoint = np.linalg.norm(ya * (ya * y).sum() / (ya * ya).sum() - y) / np.linalg.norm(y)
    assert fit < 0.1 and fit < 0.5 * fit_adjoint


@pytest.fixture(scope="module")
def zoo_run():
    return tcsense.open_run("zoo:admm-lidar-delay")


def test_run_decode_matches_cli(cli, zoo_run, scene, tmp_path):
    y = zoo_run.sensor.measure(scene, noise=True, seed=2)
    np.save(tmp_path / "y.npy", y)
    cli("reconstruct", "admm-net", "--run", "zoo:admm-lidar-delay", "--measurements", tmp_path / "y.npy", "-o", tmp_path / "xa.npy")
    out = zoo_run.decode(y)
    assert set(out) == {"cube"}
    assert out["cube"].shape == (32, 8, 8)
    assert np.array_equal(out["cube"], np.load(tmp_path / "xa.npy"))
    # batched input keeps its batch axis and gives each frame's result
    ob = zoo_run.decode(np.stack([y, y]))
    assert ob["cube"].shape == (2, 32, 8, 8)
    np.testing.assert_allclose(ob["cube"][1], out["cube"], rtol=0, atol=1e-6)


def test_onnx_export_and_inference_match_cli(cli, zoo_run, scene, tmp_path):
    n = tcsense.export_onnx("zoo:admm-lidar-delay", tmp_path / "py.onnx")
    cli("export", "onnx", "--run", "zoo:admm-lidar-delay", "-o", tmp_path / "cli.onnx")
    assert n == (tmp_path / "py.onnx").stat().st_size
    assert (tmp_path / "py.onnx").read_bytes() == (tmp_path / "cli.onnx").read_bytes()
    y = zoo_run.sensor.measure(scene, noise=True, seed=2)
    np.save(tmp_path / "y.npy", y)
    cli("infer", "--model", tmp_path / "py.onnx", "--measurements", tmp_path / "y.npy", "--products", "cube", "-o", tmp_path / "out")
    theirs = np.load(tmp_path / "out" / "y.cube.npy") if (tmp_path / "out" / "y.cube.npy").exists() else np.load(sorted((tmp_path / "out").glob("*cube*.npy"))[0])
    model = tcsense.OnnxModel(tmp_path / "py.onnx", threads=1)
    assert model.metadata["decoder"] == "admm-net"
    assert model.codes == zoo_run.codes
    (cube,) = model.run(y)
    assert cube.shape == (1, 32, 8, 8)
    assert np.array_equal(cube[0], theirs.reshape(cube[0].shape))
    dec = tcsense.open_decoder(f"onnx:{tmp_path / 'py.onnx'}")
    assert np.array_equal(dec.decode(y)["cube"], cube[0])
    # the same network in burn, to rounding
    np.testing.assert_allclose(cube[0], zoo_run.decode(y)["cube"], rtol=0, atol=1e-4 * float(np.abs(cube).max()))


def test_onnx_export_from_the_taps_matches_cli(cli, scene, tmp_path):
    """A U-Net on the range fit's evidence as one graph from the taps: the same bytes as the CLI's,
    the measurements as its only input, one refined return; other models are refused."""
    zoo = "zoo:unet-lidar-evidence-8k"
    n = tcsense.export_onnx(zoo, tmp_path / "py.onnx", from_taps=True)
    cli("export", "onnx", "--run", zoo, "--from-taps", "-o", tmp_path / "cli.onnx")
    assert n == (tmp_path / "py.onnx").stat().st_size
    assert (tmp_path / "py.onnx").read_bytes() == (tmp_path / "cli.onnx").read_bytes()
    codes = tcsense.Codes.load(pathlib.Path(__file__).resolve().parents[2] / "zoo" / "unet-lidar-evidence-8k" / "codes.json")
    y = tcsense.Sensor(codes, irf="physical").measure(scene, noise=True, seed=2)
    model = tcsense.OnnxModel(tmp_path / "py.onnx", threads=1)
    assert model.metadata["refined_in_graph"] is True
    depth, confidence = model.run(y)
    assert depth.shape == confidence.shape == (1, 1, 8, 8)
    assert np.isfinite(depth).sum() > 32 and np.nanmax(depth) < float(model.metadata["range_m"])
    with pytest.raises(Exception, match="from-taps"):
        tcsense.export_onnx("zoo:unet-lidar-designed", tmp_path / "bad.onnx", from_taps=True)
    assert not (tmp_path / "bad.onnx").exists()


def test_dataset_matches_cli(cli, tmp_path):
    ds = tcsense.generate_dataset("lidar", tmp_path / "py", 30, size=(8, 8), seed=4)
    cli("dataset", "lidar", "--count", 30, "--size", "8x8", "--seed", 4, "-o", tmp_path / "cli")
    for f in sorted((tmp_path / "cli").rglob("*")):
        if f.is_file():
            rel = f.relative_to(tmp_path / "cli")
            assert (tmp_path / "py" / rel).read_bytes() == f.read_bytes(), rel
    assert ds.kind == "lidar"
    assert sum(ds.splits.values()) == 30 == len(ds)
    assert ds.fields["x"] == [32, 8, 8]
    x = ds.load("train", "x")
    items = list(ds.items("train"))
    assert len(items) == ds.splits["train"] == x.shape[0]
    for i, it in enumerate(items):
        assert set(it) == {"x", "depth", "intensity"}
        assert np.array_equal(it["x"], x[i])
    assert np.array_equal(ds.item("train", 3)["depth"], items[3]["depth"])
    again = tcsense.Dataset(tmp_path / "py")
    assert again.manifest == json.loads((tmp_path / "py" / "manifest.json").read_text())


def test_out_arrays_are_written_in_place(sensor, scene):
    y = np.empty((4, 8, 8), dtype=np.float32)
    assert sensor.forward(scene, out=y) is y
    assert np.array_equal(y, sensor.forward(scene))
    xa = np.empty((2, 32, 8, 8), dtype=np.float32)
    sensor.adjoint(np.stack([y, 2 * y]), out=xa)
    assert np.array_equal(xa[1], sensor.adjoint(2 * y))
    with pytest.raises(tcsense.TcsenseError, match=r"out: shape \[4, 8, 9\]; expected \[4, 8, 8\]"):
        sensor.forward(scene, out=np.empty((4, 8, 9), dtype=np.float32))
    with pytest.raises(TypeError, match=r"out: .*float64"):
        sensor.forward(scene, out=np.empty((4, 8, 8)))
