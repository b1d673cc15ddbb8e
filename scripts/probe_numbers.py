#!/usr/bin/env python3
"""Probe every numeric flag of tcsense's commands with absurd numbers (0, -1, 1e308, NaN, ±inf,
2^64 - 1, 1e-300, 99999999999; sizes such as 1000000000000x2; lists such as NaN,1) and report
each panic, abort, hang (over 30 s) and refusal that left a file behind or said an OS error
twice. Every case runs in a fresh copy of a small working directory (codes, taps, a cube, a
sweep, a dataset, a model, a run) made first with the binary. Needs numpy (scripts/setup.sh).

    .venv/bin/python scripts/probe_numbers.py [--all | --flim] [--binary target/debug/tcsense]

Without --all: the commands of wave 4 (codes analyze|select|check|export, reconstruct
depth-fit|lifetime-fit, infer and its fits, calibrate, simulate and its sweep, eval and its
photon ladder, lifetime, depth, bringup); with --all: the others too (dataset, train, export,
plot, codes generate|show|project, bench, sweep, demo); with --flim: the lifetime commands
(dataset flim, codes select for lifetimes, train lifetime on the harmonics and on the fit's
evidence, reconstruct lifetime, infer with a lifetime network, eval of lifetime decoders on the
photon ladder). Valid values that start long work (a demo) show up as timeouts. Exit status 1
when a case went wrong.
"""
import argparse, os, shutil, subprocess, sys, tempfile, concurrent.futures as cf

import numpy as np

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
ap = argparse.ArgumentParser()
ap.add_argument("--all", action="store_true")
ap.add_argument("--flim", action="store_true")
ap.add_argument("--show-accepted", action="store_true", help="also list the cases that exited 0, to read for values that should have been refused")
ap.add_argument("--binary", default=os.path.join(ROOT, "target", "debug", "tcsense"))
ARGS = ap.parse_args()
T = os.path.abspath(ARGS.binary)
BASE = tempfile.mkdtemp(prefix="probe-base-")
NUM = ["0", "-1", "1e308", "NaN", "inf", "-inf", "18446744073709551615", "1e-300", "2.5", "99999999999"]
HW = ["0x0", "1x1", "99999x99999", "1000000000000x2", "3x3"]
LIST = ["0,0", "NaN,1", "1e308,1e309", "-1,5", "5,1", "1"]
SKIP = {"--codes", "--measurements", "--model", "--sweep", "--cube", "--dataset", "--calibration", "--plot", "--ply", "--png",
        "--irf", "--decoder", "--products", "--units", "--criterion", "--split", "--device", "--components", "--components-out", "--phasor", "--sensor-matrix", "--output"}
HWF = {"--size", "--block"}
LISTF = {"--tau-ns", "--tv-weights", "--light", "--signal", "--ambient", "--irf-fwhm-ns", "--background", "--lifetimes", "--onset-ns-range"}
CMDS2 = [
    ["dataset", "lidar", "--count", "4", "--size", "8x8", "--length", "8", "-o", "dl"],
    ["dataset", "flim", "--count", "4", "--size", "8x8", "--length", "8", "-o", "df"],
    ["dataset", "show", "ds", "-o", "m.png"],
    ["dataset", "import", "--cube", "x.npy", "--length", "8", "-o", "imp"],
    ["sensor", "matrix", "--codes", "dcodes.json", "--irf", "physical", "-o", "A.npy"],
    ["train", "admm-net", "--dataset", "ds", "--codes", "dcodes.json", "--epochs", "1", "--stages", "2", "--channels", "4", "-o", "newrun"],
    ["train", "unet", "--dataset", "ds", "--codes", "dcodes.json", "--epochs", "1", "--base-width", "4", "--levels", "2", "-o", "newrun"],
    ["reconstruct", "tval3", "--codes", "dcodes.json", "--measurements", "y32.npy", "--maxit", "5", "-o", "xh.npy"],
    ["reconstruct", "admm-net", "--run", "run", "--measurements", "y32.npy", "-o", "xh.npy"],
    ["export", "onnx", "--run", "run", "-o", "r.onnx"],
    ["plot", "waveforms", "--cube", "x.npy", "--pixel", "1,1", "-o", "w.png"],
    ["codes", "generate", "--length", "8", "-o", "g.json"],
    ["codes", "show", "dcodes.json", "-o", "c.png"],
    ["codes", "project", "--logits", "x.npy", "-o", "p.json"],
    ["bench", "range-fit", "--size", "8x8"],
    ["bench", "dataset", "--size", "8x8", "--count", "2"],
    ["bench", "infer", "--decoder", "unet", "--size", "8x8", "--reps", "1"],
    ["sweep", "constraints", "--dataset", "ds", "--items", "1", "--maxit", "5", "-o", "swc"],
    ["demo", "--quick", "-o", "demo"],
]
FLIM = ["--codes", "fcodes.json", "--heterodyne", "8"]
CMDS3 = [
    ["dataset", "flim", "--count", "4", "--size", "8x8", "--heterodyne", "8", "-o", "df"],
    ["codes", "select", "--criterion", "lifetime", "--heterodyne", "8", "--taps", "4", "--block", "2x2", "--length", "32",
     "--tap-constraint", "--candidates", "10", "--search", "10", "-o", "s.json"],
    ["train", "lifetime", "--dataset", "fds", *FLIM[:2], "--epochs", "1", "--base-width", "4", "-o", "newrun"],
    ["train", "lifetime", "--input", "costs", "--dataset", "fds", *FLIM[:2], "--epochs", "1", "--base-width", "4", "--points", "16",
     "-o", "newrun"],
    ["reconstruct", "lifetime", "--run", "frun", "--measurements", "fy.npy", "-o", "t.npy"],
    ["reconstruct", "lifetime-fit", *FLIM, "--measurements", "fy.npy", "-o", "t.npy"],
    ["infer", "--model", "frun.onnx", "--measurements", "fy.npy", "-o", "out"],
    ["eval", "--dataset", "fds", *FLIM, "--irf", "physical", "--decoder", "lifetime-fit", "--decoder", "lifetime:frun",
     "--items", "1", "--light", "0.5"],
]
CMDS = CMDS3 if ARGS.flim else CMDS2 if ARGS.all else [
    ["codes", "analyze", "dcodes.json"],
    ["codes", "select", "--criterion", "range", "--tap-constraint", "--candidates", "10", "--search", "10", "-o", "s.json"],
    ["codes", "check", "dcodes.json"],
    ["codes", "export", "dcodes.json", "-o", "mem"],
    ["reconstruct", "depth-fit", "--codes", "dcodes.json", "--irf", "physical", "--measurements", "y32.npy", "-o", "d.npy"],
    ["reconstruct", "lifetime-fit", "--codes", "dcodes.json", "--heterodyne", "8", "--measurements", "y32.npy", "-o", "t.npy"],
    ["infer", "--model", "admm.onnx", "--measurements", "stack2.npy", "-o", "out"],
    ["infer", "--model", "admm.onnx", "--measurements", "stack2.npy", "--depth-fit", "-o", "out"],
    ["infer", "--model", "admm.onnx", "--measurements", "stack2.npy", "--lifetime-fit", "-o", "out"],
    ["calibrate", "--codes", "codes.json", "--irf", "physical", "--sweep", "sweep", "-o", "cal"],
    ["simulate", "--codes", "dcodes.json", "--cube", "x32.npy", "-o", "yy.npy"],
    ["simulate", "--codes", "dcodes.json", "--sweep", "sw", "--size", "8x8", "--average", "2"],
    ["eval", "--dataset", "ds", "--codes", "dcodes.json", "--irf", "physical", "--decoder", "depth-fit", "--items", "1", "--light", "0.5"],
    ["lifetime", "x.npy", "--length", "8", "-o", "lt.npy"],
    ["depth", "x.npy", "--length", "8", "-o", "d2.npy"],
    ["bringup", "--sweep", "sweep32", "--codes", "dcodes.json", "--decoder", "admm-lidar-designed", "--epochs", "1", "--scenes", "4", "--size", "8x8", "--check-items", "1", "-o", "bu"],
]

def flags(cmd):
    sub = [c for c in cmd[:2] if not c.endswith(".json") and not c.startswith("-")]
    if cmd[0] in ("infer", "calibrate", "simulate", "eval", "lifetime", "depth", "bringup", "demo"):
        sub = cmd[:1]
    h = subprocess.run([T] + sub + ["--help"], capture_output=True, text=True).stdout
    out = []
    for line in h.splitlines():
        s = line.strip()
        if s.startswith("--") and " <" in s:
            f = s.split()[0].rstrip(",")
            if f not in SKIP:
                out.append(f)
    return out

def snapshot(d):
    r = {}
    for root, dirs, files in os.walk(d):
        for x in dirs + files:
            p = os.path.join(root, x)
            r[os.path.relpath(p, d)] = os.path.getsize(p) if os.path.isfile(p) else -1
    return r

def one(args):
    cmd, flag, val = args
    d = tempfile.mkdtemp(prefix="probe-")
    try:
        for x in os.listdir(BASE):
            s = os.path.join(BASE, x)
            (shutil.copytree if os.path.isdir(s) else shutil.copy)(s, os.path.join(d, x))
        before = snapshot(d)
        full = [T] + cmd + [f"{flag}={val}"]
        try:
            o = subprocess.run(full, cwd=d, capture_output=True, text=True, timeout=30)
        except subprocess.TimeoutExpired:
            return ("TIMEOUT", full, "")
        err = o.stderr
        if o.returncode not in (0, 1, 2) or "panicked" in err:
            return ("PANIC/ABORT rc=%d" % o.returncode, full, err[-600:])
        if o.returncode == 2:
            after = snapshot(d)
            if after != before:
                changed = sorted(k for k in set(after) | set(before) if after.get(k) != before.get(k))
                return ("LEFT", full, str(changed)[:300])
            if err.count("(os error") > 1:
                return ("TWICE", full, err[-300:])
        return (None, full, o.returncode)
    finally:
        shutil.rmtree(d, ignore_errors=True)

def make_base():
    """The working directory every case starts from."""
    def tc(*a):
        subprocess.run([T, *a], cwd=BASE, check=True, capture_output=True)
    shutil.copy(os.path.join(ROOT, "zoo", "admm-lidar-designed", "codes.json"), os.path.join(BASE, "dcodes.json"))
    shutil.copy(os.path.join(ROOT, "tests", "fixtures", "admm-net-run-v1", "codes.json"), os.path.join(BASE, "codes.json"))
    x = np.zeros((32, 16, 16), np.float32)
    x[11], x[12] = 0.7, 0.3
    np.save(os.path.join(BASE, "x32.npy"), x)
    np.save(os.path.join(BASE, "x.npy"), np.full((8, 8, 8), 0.5, np.float32))
    tc("simulate", "--codes", "dcodes.json", "--irf", "physical", "--cube", "x32.npy", "-o", "y32.npy")
    os.remove(os.path.join(BASE, "y32.meta.json"))  # so that the fits' own checks are reached
    y = np.load(os.path.join(BASE, "y32.npy"))
    np.save(os.path.join(BASE, "stack2.npy"), np.stack([y, y]))
    tc("export", "onnx", "--run", "zoo:admm-lidar-designed", "-o", "admm.onnx")
    tc("simulate", "--codes", "codes.json", "--irf", "physical", "--sweep", "sweep", "--size", "8x8", "--average", "2")
    tc("simulate", "--codes", "dcodes.json", "--irf", "physical", "--sweep", "sweep32", "--size", "8x8", "--average", "2", "--tap-gain", "0.05")
    tc("dataset", "lidar", "--count", "6", "--size", "16x16", "--seed", "1", "-o", "ds")
    tc("train", "admm-net", "--dataset", "ds", "--codes", "dcodes.json", "--epochs", "1", "--stages", "2", "--channels", "4", "-o", "run")
    if ARGS.flim:
        shutil.copy(os.path.join(ROOT, "zoo", "lifetime-flim-designed", "codes.json"), os.path.join(BASE, "fcodes.json"))
        tc("dataset", "flim", "--count", "6", "--size", "16x16", "--heterodyne", "8", "--seed", "1", "-o", "fds")
        cube = sorted(f for f in os.listdir(os.path.join(BASE, "fds", "test")) if f.startswith("x_"))[0]
        tc("simulate", *FLIM, "--irf", "physical", "--cube", os.path.join("fds", "test", cube), "--noise", "-o", "fy.npy")
        tc("train", "lifetime", "--input", "costs", "--dataset", "fds", *FLIM[:2], "--epochs", "1", "--base-width", "4", "--points",
           "16", "-o", "frun")
        tc("export", "onnx", "--run", "frun", "-o", "frun.onnx")


make_base()
jobs = []
for cmd in CMDS:
    for f in flags(cmd):
        vals = HW if f in HWF else LIST if f in LISTF else NUM
        for v in vals:
            jobs.append((cmd, f, v))
print(len(jobs), "probes", flush=True)
bad = []
codes = {}
with cf.ThreadPoolExecutor(max_workers=2) as ex:
    for res in ex.map(one, jobs):
        kind, full, info = res
        if kind:
            bad.append((kind, " ".join(full[1:]), info))
            print(kind, " ".join(full[1:]), "|", info, flush=True)
        else:
            codes[info] = codes.get(info, 0) + 1
            if ARGS.show_accepted and info == 0:
                print("accepted", " ".join(full[1:]), flush=True)
print("exit codes of the rest:", codes)
print(len(bad), "problems of", len(jobs))
shutil.rmtree(BASE, ignore_errors=True)
sys.exit(1 if bad else 0)
