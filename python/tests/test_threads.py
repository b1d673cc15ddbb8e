"""Long calls release the GIL (two threads decode at once, and Python runs meanwhile) and
stop on Ctrl-C."""

import shutil
import signal
import subprocess
import sys
import textwrap
import threading
import time

import numpy as np

import tcsense


def test_decode_from_two_threads(scene):
    run = tcsense.open_run("zoo:admm-lidar-delay")
    ys = [run.sensor.measure(scene * (1 + i), noise=True, seed=i) for i in range(4)]
    want = [run.decode(y)["cube"] for y in ys]
    got = [None] * 4
    errors = []

    def work(i):
        try:
            dec = tcsense.open_run("zoo:admm-lidar-delay")
            for j in (i, i + 2):
                got[j] = dec.decode(ys[j])["cube"]
        except Exception as e:  # noqa: BLE001 - reported below
            errors.append(e)

    threads = [threading.Thread(target=work, args=(i,)) for i in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    for g, w in zip(got, want):
        assert np.array_equal(g, w)


def test_tval3_releases_the_gil(sensor):
    # a frame that takes TVAL3 a while; with the GIL held the main thread could not tick at all
    x = np.random.default_rng(1).random((32, 96, 96), dtype=np.float32)
    y = sensor.forward(x)
    ticks = 0
    done = threading.Event()

    def tv():
        tcsense.tval3(y, sensor, maxit=200)
        done.set()

    t = threading.Thread(target=tv)
    t.start()
    while not done.is_set():
        ticks += 1
        time.sleep(0.001)
    t.join()
    # the main thread kept running Python while TVAL3 ran
    assert ticks >= 3


def test_ctrl_c_stops_a_long_call(tmp_path):
    script = textwrap.dedent(
        """
        import faulthandler, signal, sys, time, numpy as np, tcsense
        faulthandler.register(signal.SIGUSR1, all_threads=True)  # the test's dump on a hang
        # a shell's background job starts with SIGINT ignored, and Python then installs no
        # KeyboardInterrupt handler (CI launched with `&` hung here): Ctrl-C as in a terminal
        signal.signal(signal.SIGINT, signal.default_int_handler)
        codes = tcsense.Codes.generate(seed=1)
        s = tcsense.Sensor(codes)
        y = s.forward(np.random.default_rng(0).random((32, 128, 128), dtype=np.float32))
        print("ready", flush=True)
        t0 = time.time()
        try:
            tcsense.tval3(y, s, maxit=100000, tol=1e-30, tol_inn=1e-30)
        except KeyboardInterrupt:
            print(f"interrupted after {time.time() - t0:.2f} s", flush=True)
            sys.exit(3)
        """
    )
    p = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert p.stdout.readline().strip() == "ready"
    time.sleep(1.0)
    p.send_signal(signal.SIGINT)
    try:
        out, err = p.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        raise AssertionError(f"no exit within 60 s of Ctrl-C; where the child was:\n{_stacks(p)}") from None
    assert p.returncode == 3, err
    assert "interrupted after" in out


def _stacks(p):
    """The Python stacks (faulthandler, on SIGUSR1) and native stacks (gdb, where installed) of
    a hung child, which is then killed: what a failure report needs."""
    p.send_signal(signal.SIGUSR1)
    time.sleep(1.0)
    native = ""
    if shutil.which("gdb"):
        g = subprocess.run(["gdb", "-p", str(p.pid), "-batch", "-ex", "thread apply all bt 30"], capture_output=True, text=True, timeout=120)
        native = g.stdout[-20000:]
    p.kill()
    out, err = p.communicate()
    return f"stdout:\n{out}\nstderr (Python stacks):\n{err[-20000:]}\nnative stacks:\n{native}"
