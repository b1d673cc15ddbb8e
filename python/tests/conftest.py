"""Fixtures of the pytest suite: the command-line binary to compare against, the prototype's
codes and sensor, and a tiny LiDAR scene (8×8 pixels, 32 bins)."""

import os
import pathlib
import subprocess

import numpy as np
import pytest

import tcsense

REPO = pathlib.Path(__file__).resolve().parents[2]


def _binary() -> pathlib.Path:
    env = os.environ.get("TCSENSE_BIN")
    if env:
        return pathlib.Path(env)
    for profile in ("debug", "release"):
        p = REPO / "target" / profile / "tcsense"
        if p.is_file():
            return p
    raise RuntimeError("no tcsense binary: build it (cargo build) or set TCSENSE_BIN")


@pytest.fixture(scope="session")
def cli():
    """Run the command line; returns the CompletedProcess (stdout/stderr as text)."""
    exe = _binary()

    def run(*args, check=True):
        p = subprocess.run([str(exe), *map(str, args)], capture_output=True, text=True)
        if check and p.returncode != 0:
            raise AssertionError(f"tcsense {' '.join(map(str, args))} failed ({p.returncode}):\n{p.stderr}")
        return p

    return run


PROTOTYPE = dict(taps=4, block=(2, 2), length=32, tap_constraint=True, hamming=2, window=2)


@pytest.fixture(scope="session")
def codes():
    return tcsense.Codes.generate(**PROTOTYPE, seed=1)


@pytest.fixture(scope="session")
def codes_file(codes, tmp_path_factory):
    p = tmp_path_factory.mktemp("codes") / "codes.json"
    codes.save(p)
    return p


@pytest.fixture(scope="session")
def sensor(codes):
    return tcsense.Sensor(codes, irf="physical")


@pytest.fixture(scope="session")
def scene():
    """A LiDAR-like cube [32, 8, 8]: two returns per pixel on a dim background."""
    rng = np.random.default_rng(7)
    x = np.full((32, 8, 8), 0.01, dtype=np.float32)
    first = rng.integers(3, 12, size=(8, 8))
    for r in range(8):
        for c in range(8):
            x[first[r, c], r, c] += 1.0
            x[first[r, c] + 9, r, c] += 0.4
    return x
