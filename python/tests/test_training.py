"""Training and bring-up from Python: the same options give the command line's run directories
to the byte; fine-tuning takes the architecture from its run; sweeps match `simulate --sweep`."""

import json

import pytest

import tcsense

from conftest import PROTOTYPE


@pytest.fixture(scope="module")
def lab(tmp_path_factory, cli):
    """A tiny LiDAR dataset (8 items, 8×8, L = 32) and the prototype's codes, made by the CLI."""
    d = tmp_path_factory.mktemp("lab")
    cli("dataset", "lidar", "--count", "8", "--size", "8x8", "--seed", "2", "-o", d / "ds")
    tcsense.Codes.generate(**PROTOTYPE, seed=1).save(d / "codes.json")
    return d


def test_train_writes_the_command_lines_run(lab, cli):
    epochs = []
    rows = tcsense.train("admm-net", lab / "py", dataset=lab / "ds", codes=lab / "codes.json", stages=1, channels=2, epochs=2, seed=3, progress=epochs.append)
    cli("train", "admm-net", "--dataset", lab / "ds", "--codes", lab / "codes.json", "--stages", "1", "--channels", "2", "--epochs", "2", "--seed", "3", "-o", lab / "cli")
    assert (lab / "py" / "model.bpk").read_bytes() == (lab / "cli" / "model.bpk").read_bytes()
    py_cfg, cli_cfg = (json.loads((lab / r / "config.json").read_text()) for r in ("py", "cli"))
    assert py_cfg == cli_cfg
    assert [r["epoch"] for r in rows] == [1, 2] and [e["epoch"] for e in epochs] == [1, 2]
    assert "val_mse" in rows[-1] and rows[-1]["train_loss"] > 0
    # resume continues the run
    more = tcsense.train("admm-net", lab / "py", epochs=3, resume=True)
    assert [r["epoch"] for r in more] == [3]


def test_the_objective_is_the_command_lines(lab, cli):
    """`objective="range"` gives the run `--objective range` gives, to the byte; a product the
    dataset does not have is refused before anything is written."""
    tcsense.train("admm-net", lab / "obj-py", dataset=lab / "ds", codes=lab / "codes.json", stages=1, channels=2, epochs=1, seed=3, objective="range")
    cli("train", "admm-net", "--dataset", lab / "ds", "--codes", lab / "codes.json", "--stages", "1", "--channels", "2", "--epochs", "1", "--seed", "3",
        "--objective", "range", "-o", lab / "obj-cli")
    assert (lab / "obj-py" / "model.bpk").read_bytes() == (lab / "obj-cli" / "model.bpk").read_bytes()
    assert json.loads((lab / "obj-py" / "config.json").read_text())["objective"] == "range"
    with pytest.raises(tcsense.TcsenseError, match=r"objective lifetime"):
        tcsense.train("admm-net", lab / "obj-bad", dataset=lab / "ds", codes=lab / "codes.json", epochs=1, objective="lifetime")
    assert not (lab / "obj-bad").exists()


def test_fine_tune_takes_the_architecture_from_its_run(lab):
    tcsense.train("admm-net", lab / "src", dataset=lab / "ds", codes=lab / "codes.json", stages=1, channels=2, prior="delay", epochs=1, seed=4)
    rows = tcsense.fine_tune(lab / "src", lab / "tuned", dataset=lab / "ds", codes=lab / "codes.json", epochs=1)
    cfg = json.loads((lab / "tuned" / "config.json").read_text())
    assert (cfg["model"]["stages"], cfg["model"]["channels"], cfg["model"]["prior"]) == (1, 2, "Delay")
    assert cfg["init_from"] == str(lab / "src") and len(rows) == 1
    with pytest.raises(tcsense.TcsenseError, match=r"--stages 3 contradicts the run's stages 1"):
        tcsense.fine_tune(lab / "src", lab / "bad", dataset=lab / "ds", codes=lab / "codes.json", stages=3)
    with pytest.raises(tcsense.TcsenseError, match=r"unknown setting\(s\) \[\"epoch\"\]"):
        tcsense.train("admm-net", lab / "bad", dataset=lab / "ds", codes=lab / "codes.json", epoch=3)
    assert not (lab / "bad").exists()


def test_simulate_sweep_matches_the_command_line_and_calibrates(lab, cli, tmp_path):
    sensor = tcsense.Sensor(tcsense.Codes.load(lab / "codes.json"), irf="physical")
    # the values as the command line computes them from its flags (ns × 1e-9; its tail default)
    nonideal = {"tap_gain": 0.05, "prnu": 0.02, "dark": 0.01, "gate_skew_s": 0.1 * 1e-9, "tail_tau_s": 0.5 * 1e-9, "seed": 7}
    m = tcsense.simulate_sweep(sensor, tmp_path / "py", size=(8, 8), average=4, seed=3, nonideal=nonideal)
    cli("simulate", "--codes", lab / "codes.json", "--irf", "physical", "--sweep", tmp_path / "cli", "--size", "8x8", "--average", "4", "--noise",
        "--seed", "3", "--tap-gain", "0.05", "--prnu", "0.02", "--dark", "0.01", "--gate-skew-ns", "0.1", "--sensor-seed", "7")
    assert len(m["delays_s"]) == 32 and m["units"] == "electrons"
    files = sorted(p.relative_to(tmp_path / "cli") for p in (tmp_path / "cli").rglob("*") if p.is_file())
    assert files and all((tmp_path / "py" / f).read_bytes() == (tmp_path / "cli" / f).read_bytes() for f in files)
    cal = tcsense.calibrate(lab / "codes.json", tmp_path / "py", tmp_path / "cal", irf="physical", report=False)
    assert len(cal["tap_gains"]) == 4
    with pytest.raises(tcsense.TcsenseError, match=r"size 7x8"):
        tcsense.simulate_sweep(sensor, tmp_path / "bad", size=(7, 8))
    with pytest.raises(tcsense.TcsenseError, match=r"nonideal: .*prnu"):
        tcsense.simulate_sweep(sensor, tmp_path / "bad", size=(8, 8), nonideal={"prnu": 0.9})


def test_bringup_from_python(tmp_path):
    codes = tcsense.open_run("zoo:admm-lidar-designed").codes
    codes.save(tmp_path / "codes.json")
    sensor = tcsense.Sensor(codes, irf="physical")
    tcsense.simulate_sweep(sensor, tmp_path / "sweep", size=(8, 8), average=8, nonideal={"tap_gain": 0.05, "prnu": 0.02, "seed": 3})
    s = tcsense.bringup(tmp_path / "sweep", tmp_path / "codes.json", tmp_path / "out", decoders=["admm-lidar-designed"],
                        budget_minutes=0.03, epochs=2, scenes=8, size=(16, 16), check_items=2, quiet=True)
    assert str(s["report"]).endswith("report.html") and (tmp_path / "out" / "onnx" / "admm-lidar-designed.onnx").is_file()
    assert [n for n, _ in s["steps"]][0] == "calibration from the sweep" and len(s["steps"]) == 5
    check = json.loads((tmp_path / "out" / "results" / "check.json").read_text())
    assert {r["condition"] for r in check["rows"]} == {"ideal sensor", "nominal model", "calibration", "calibration + fine-tuning"}
    with pytest.raises(tcsense.TcsenseError, match=r"no-such-entry"):
        tcsense.bringup(tmp_path / "sweep", tmp_path / "codes.json", tmp_path / "bad", decoders=["no-such-entry"], quiet=True)
