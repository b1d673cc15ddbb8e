#!/usr/bin/env python3
"""Write the bad-input corpus under tests/corpus/ (run once; the files are committed).

Each file is one kind of bad input that a user or a broken tool could hand to tcsense;
tests/bad_inputs.rs feeds every one to every command that reads that kind of file and
asserts exit status 2, a message naming the file, and no output. Needs numpy and onnx
(scripts/setup.sh installs both into .venv).

    .venv/bin/python scripts/make_bad_corpus.py
"""
import json
import os
import shutil

import numpy as np
import onnx
from onnx import TensorProto, helper

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
OUT = os.path.join(ROOT, "tests", "corpus")
FIXTURE = os.path.join(ROOT, "tests", "fixtures", "admm-net-run-v1")


def path(*p):
    full = os.path.join(OUT, *p)
    os.makedirs(os.path.dirname(full), exist_ok=True)
    return full


def npy():
    good = np.arange(8 * 4 * 4, dtype=np.float32).reshape(8, 4, 4)
    open(path("npy", "empty.npy"), "wb").close()
    with open(path("npy", "garbage.npy"), "wb") as f:
        f.write(b"this is not an array\n" * 4)
    np.save(path("npy", "full.npy"), good)
    raw = open(path("npy", "full.npy"), "rb").read()
    os.remove(path("npy", "full.npy"))
    with open(path("npy", "truncated.npy"), "wb") as f:
        f.write(raw[: len(raw) - 100])
    with open(path("npy", "header-truncated.npy"), "wb") as f:
        f.write(raw[:40])
    with open(path("npy", "bad-version.npy"), "wb") as f:
        f.write(raw[:6] + b"\x09\x00" + raw[8:])
    np.save(path("npy", "complex.npy"), good.astype(np.complex64))
    np.save(path("npy", "float16.npy"), good.astype(np.float16))
    np.save(path("npy", "object.npy"), np.array([[1, "a"], [None, 2.0]], dtype=object), allow_pickle=True)
    np.save(path("npy", "structured.npy"), np.zeros((4, 4), dtype=[("a", "<f4"), ("b", "<i4")]))
    np.save(path("npy", "unicode.npy"), np.array(["tap", "image"]))
    np.save(path("npy", "rank1.npy"), np.zeros(16, dtype=np.float32))
    np.save(path("npy", "rank5.npy"), np.zeros((1, 2, 4, 2, 2), dtype=np.float32))
    # values: a cube [T = 8, 4, 4] and tap images [M = 4, 4, 4] with one NaN / -Inf each
    for what, shape in (("cube", (8, 4, 4)), ("taps", (4, 4, 4))):
        nan = np.ones(shape, dtype=np.float32)
        nan[3, 1, 2] = np.nan
        np.save(path("npy", f"nan-{what}.npy"), nan)
        inf = np.ones(shape, dtype=np.float32)
        inf[0, 0, 1] = -np.inf
        np.save(path("npy", f"inf-{what}.npy"), inf)
    np.save(path("npy", "zero-size.npy"), np.zeros((8, 0, 4), dtype=np.float32))
    # a header that claims ~4 PB of data: must be refused, not allocated
    hdr = b"{'descr': '<f4', 'fortran_order': False, 'shape': (1000000, 1000000, 1000), }"
    hdr += b" " * ((64 - (10 + len(hdr) + 1) % 64) % 64) + b"\n"
    with open(path("npy", "huge-shape.npy"), "wb") as f:
        f.write(b"\x93NUMPY\x01\x00" + len(hdr).to_bytes(2, "little") + hdr + b"\x00" * 64)


def variants(kind, base_file):
    """A writer of `kind/NAME`: a deep copy of the JSON in `base_file` changed by `edit`."""
    base = json.load(open(base_file))

    def variant(name, edit):
        c = json.loads(json.dumps(base))
        edit(c)
        json.dump(c, open(path(kind, name), "w"), indent=1)

    return variant


def codes():
    base_file = os.path.join(FIXTURE, "codes.json")
    variant = variants("codes", base_file)
    base = json.load(open(base_file))

    open(path("codes", "empty.json"), "w").close()
    open(path("codes", "garbage.json"), "w").write("taps = 4\nblock = 2x2\n")
    open(path("codes", "array.json"), "w").write("[1, 2, 3]\n")
    open(path("codes", "truncated.json"), "w").write(json.dumps(base)[:150])
    variant("wrong-type.json", lambda c: c.update(taps="four"))
    variant("missing-bits.json", lambda c: c.pop("bits"))
    variant("unknown-field.json", lambda c: c.update(tapz=4))
    variant("absurd-taps.json", lambda c: c.update(taps=10**12))
    variant("negative-length.json", lambda c: c.update(length=-8))
    variant("zero-block.json", lambda c: c.update(block=[0, 0]))
    variant("foreign-format.json", lambda c: c.update(format="something-else"))
    variant("bits-wrong-length.json", lambda c: c["bits"][0].__setitem__(0, "0101"))
    variant("bits-not-binary.json", lambda c: c["bits"][0].__setitem__(0, "0120abcd"))

    def two_taps_on(c):  # declares the tap constraint, then opens taps 0 and 1 together
        c["bits"][0][0] = "10000000"
        c["bits"][0][1] = "10000000"

    variant("breaks-tap-constraint.json", two_taps_on)


def config():
    variant = variants("config", os.path.join(FIXTURE, "config.json"))

    open(path("config", "empty.json"), "w").close()
    open(path("config", "garbage.json"), "w").write("epochs: 3\n")
    variant("wrong-type.json", lambda c: c.update(epochs="ten"))
    variant("missing-field.json", lambda c: c.pop("learning_rate"))
    variant("unknown-field.json", lambda c: c.update(learning_rat=0.01))
    variant("absurd-stages.json", lambda c: c["model"].update(stages=10**12))
    variant("negative-learning-rate.json", lambda c: c.update(learning_rate=-1.0))
    variant("zero-batch.json", lambda c: c.update(batch_size=0))


def manifest():
    variant = variants("manifest", os.path.join(ROOT, "fuzz", "seeds", "manifest.json"))

    open(path("manifest", "empty.json"), "w").close()
    open(path("manifest", "garbage.json"), "w").write("<dataset/>\n")
    variant("wrong-type.json", lambda m: m.update(bins="eight"))
    variant("missing-field.json", lambda m: m.pop("splits"))
    variant("unknown-field.json", lambda m: m.update(binz=8))
    variant("absurd-size.json", lambda m: m.update(size=[10**9, 10**9]))
    variant("bins-mismatch.json", lambda m: m.update(bins=9))
    variant("missing-shard.json", lambda m: m["splits"][0]["shards"][0]["files"].update(x="train/x_009.npy"))
    variant("count-mismatch.json", lambda m: m["splits"][0]["shards"][0].update(count=60))
    variant("escaping-path.json", lambda m: m["splits"][0]["shards"][0]["files"].update(x="../../etc/passwd"))


def registers():
    """Variants of an exported code memory's registers.json (of the fixture's codes): every
    field that `codes import` must honour or refuse."""
    variant = variants("registers", os.path.join(ROOT, "fuzz", "seeds", "registers.json"))

    open(path("registers", "empty.json"), "w").close()
    open(path("registers", "garbage.json"), "w").write("ECLEN=0\n")
    variant("wrong-type.json", lambda r: r.update(ECLEN="zero"))
    variant("unknown-field.json", lambda r: r.update(ECLEM=0))
    variant("missing-field.json", lambda r: r.pop("bit_order"))
    variant("eclen-mismatch.json", lambda r: r.update(ECLEN=7))
    variant("zero-length.json", lambda r: r.update(length=0, ECLEN=0))
    variant("bytes-per-channel.json", lambda r: r.update(bytes_per_channel=2))
    variant("channel-count.json", lambda r: r.update(channel_count=15))
    variant("bit-order.json", lambda r: r.update(bit_order="lsb-first"))
    variant("combined-layout.json", lambda r: r.update(combined_layout="tap-major"))
    variant("escaping-combined-file.json", lambda r: r.update(combined_file="../codes.bin"))
    variant("escaping-channel-file.json", lambda r: r["channels"][3].update(file="/etc/passwd"))
    variant("channel-misplaced.json", lambda r: r["channels"][1].update(tap=2))
    variant("channels-missing.json", lambda r: r.update(channels=r["channels"][:-1]))
    variant("absurd-taps.json", lambda r: r.update(taps=10**12))
    variant("zero-clock.json", lambda r: r.update(clock_hz=0.0))


def sweep():
    """Variants of a simulated sweep's sweep.json (the fixture's codes, 8x8, 8 delays): every
    field that calibration and bring-up must honour or refuse."""
    variant = variants("sweep", os.path.join(ROOT, "fuzz", "seeds", "sweep.json"))

    open(path("sweep", "empty.json"), "w").close()
    open(path("sweep", "garbage.json"), "w").write("<sweep/>\n")
    variant("wrong-type.json", lambda m: m.update(full_scale="max"))
    variant("unknown-field.json", lambda m: m.update(unitz="electrons"))
    variant("foreign-format.json", lambda m: m.update(format="something-else"))
    variant("units-unknown.json", lambda m: m.update(units="furlongs"))
    variant("units-empty.json", lambda m: m.update(units=""))
    variant("no-delays.json", lambda m: m.update(delays_s=[]))
    variant("delays-mismatch.json", lambda m: m.update(delays_s=m["delays_s"][:-1]))
    variant("zero-full-scale.json", lambda m: m.update(full_scale=0.0))
    variant("missing-frames.json", lambda m: m.update(frames="nothing.npy"))
    variant("absurd-gate-skew.json", lambda m: m["sensor"].update(gate_skew_s=1e30))


def onnx_files():
    seed = open(os.path.join(ROOT, "fuzz", "seeds", "admm-net.onnx"), "rb").read()
    open(path("onnx", "garbage.onnx"), "wb").write(b"\x08\x09garbage" * 50)
    open(path("onnx", "empty.onnx"), "wb").close()
    open(path("onnx", "truncated.onnx"), "wb").write(seed[: len(seed) // 3])
    # a valid ONNX model from elsewhere: no tcsense metadata
    x = helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 4, 8, 8])
    y = helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 4, 8, 8])
    graph = helper.make_graph([helper.make_node("Relu", ["x"], ["y"])], "foreign", [x], [y])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 9
    onnx.save(model, path("onnx", "foreign.onnx"))


if __name__ == "__main__":
    if os.path.isdir(OUT):
        shutil.rmtree(OUT)
    npy()
    codes()
    config()
    manifest()
    registers()
    sweep()
    onnx_files()
    for d in sorted(os.listdir(OUT)):
        print(d, len(os.listdir(os.path.join(OUT, d))))
