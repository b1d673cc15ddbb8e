#!/usr/bin/env python3
"""PyTorch CPU ports of tcsense's networks, timed one Adam step at a time: the comparison for
`tcsense bench train` (same networks, batch, frame size, bins and thread count).

    scripts/bench_torch.py --install          # once: torch + numpy into .venv-torch (PyPI)
    scripts/bench_torch.py [--size 64x64] [--bins 32,256] [--threads 2] [--steps 5]

The ports follow tcsense's modules (models/src/admm.rs, models/src/unet.rs,
models/src/sensor_tensors.rs):

- the sensor: a block-periodic per-pixel matrix A_n [M, T] (2x2 blocks, 4 taps) expanded to the
  frame, Aᵀy, the normalised back-projection Aᵀ(AAᵀ + εI)⁻¹y and ADMM-Net's exact
  data-consistency solve (AᵀA + ρI)⁻¹v through Woodbury with AAᵀ = QΛQᵀ per subpixel;
- ADMM-Net: S stages, x = DC(Aᵀy + ρ(z − u)), z = (x + u) + P(x + u), u += η(x − z), from the
  back-projection; the bins prior is 3x3 convs T → CN → CN → T with ReLUs; the delay prior is
  three layers of 3x3x3 convs on C channels per bin, circular in t with dilations 1, 3, 9, run
  two ways (`conv3d`: circular padding in t by concatenation + a dilated Conv3d, what a PyTorch
  user writes; `stack`: roll + cat of the bins t − d, t, t + d into [B·T, 3C, H, W] + Conv2d, as
  tcsense's composed path) and the faster one reported;
- Aᵀ + U-Net: Aᵀy normalised per pixel, 3 levels of two 3x3 conv + ReLU (width 8, doubling),
  2x2 max-pooling, nearest up-sampling, skip concatenation, a 1x1 head to 2K = 4 channels,
  depth = r·sigmoid, a loss on depth (L1) and confidence (BCE).

The loss of the cube networks is RMSE + MAE, as tcsense's default. Times are medians of
--steps steps after one warm-up step; the codes are random binary (timing does not depend on
their values). This script is not part of the test command.
"""

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
VENV = ROOT / ".venv-torch"


def install() -> None:
    """torch + numpy from PyPI into .venv-torch (nothing else is downloaded)."""
    if not (VENV / "bin" / "python").exists():
        subprocess.run([sys.executable, "-m", "venv", str(VENV)], check=True)
    subprocess.run([str(VENV / "bin" / "pip"), "install", "-q", "torch", "numpy"], check=True)
    print(f"torch installed into {VENV}; run scripts/bench_torch.py again")


def reexec_in_venv() -> None:
    """Run under .venv-torch's interpreter when torch is not importable here."""
    try:
        import torch  # noqa: F401
    except ImportError:
        py = VENV / "bin" / "python"
        if py.exists() and Path(sys.prefix).resolve() != VENV.resolve():
            os.execv(str(py), [str(py), *sys.argv])
        sys.exit("bench_torch.py: torch is not installed; run scripts/bench_torch.py --install (PyPI, into .venv-torch)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--install", action="store_true", help="install torch + numpy into .venv-torch and exit")
    ap.add_argument("--size", default="64x64", help="training frame HxW (default 64x64)")
    ap.add_argument("--bins", default="32,256", help="bins T, comma-separated (default 32,256)")
    ap.add_argument("--batch", type=int, default=2)
    ap.add_argument("--stages", type=int, default=9)
    ap.add_argument("--channels", type=int, default=32, help="CN of the bins prior")
    ap.add_argument("--delay-channels", type=int, default=4, help="channels per bin of the delay prior")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--steps", type=int, default=5)
    ap.add_argument("--only", default=None, help="only networks whose label contains this")
    args = ap.parse_args()
    if args.install:
        install()
        return
    reexec_in_venv()
    import torch

    try:
        h, w = (int(v) for v in args.size.lower().split("x"))
        bins = [int(t) for t in args.bins.split(",")]
    except ValueError:
        sys.exit(f"bench_torch.py: --size {args.size!r} / --bins {args.bins!r}: expected HxW and integers")
    if h % 4 or w % 4 or any(t <= 0 for t in bins):
        sys.exit("bench_torch.py: expected a frame that is a multiple of 4 and positive bins")
    torch.set_num_threads(args.threads)
    torch.manual_seed(1)
    print(f"PyTorch {torch.__version__}, {torch.get_num_threads()} threads; Adam step, batch {args.batch}, {h}x{w}, 4 taps 2x2")
    print(f"{'network':<40} {'T':>5} {'step ms':>10} {'fwd ms':>10} {'bwd ms':>10} {'adam ms':>8}")
    for t in bins:
        sensor = Sensor(torch, t, h, w)
        nets = [
            (f"ADMM-Net bins prior S={args.stages} CN={args.channels}", lambda: AdmmNet(torch, sensor, args.stages, "bins", args.channels)),
            (f"ADMM-Net delay prior S={args.stages} C={args.delay_channels}/bin [conv3d]", lambda: AdmmNet(torch, sensor, args.stages, "conv3d", args.delay_channels)),
            (f"ADMM-Net delay prior S={args.stages} C={args.delay_channels}/bin [stack]", lambda: AdmmNet(torch, sensor, args.stages, "stack", args.delay_channels)),
            ("Aᵀ + U-Net K=2 width 8, 3 levels", lambda: Unet(torch, sensor, 8, 3, 2)),
        ]
        for label, make in nets:
            if args.only and args.only not in label:
                continue
            s = time_steps(torch, make(), sensor, args.batch, args.steps)
            print(f"{label:<40} {t:>5} {s[0]:>10.1f} {s[1]:>10.1f} {s[2]:>10.1f} {s[3]:>8.1f}", flush=True)


class Sensor:
    """A block-periodic per-pixel sensor matrix expanded to the frame: A [M, T, H, W]."""

    def __init__(self, torch, t, h, w, taps=4, block=2):
        g = torch.Generator().manual_seed(7)
        # each bin of each subpixel integrates into one tap (the tap constraint), boxcar IRF
        choice = torch.randint(0, taps, (block * block, t), generator=g)
        a_n = torch.nn.functional.one_hot(choice, taps).permute(0, 2, 1).float()  # [N, M, T]
        self.lam, self.q = torch.linalg.eigh(a_n @ a_n.transpose(1, 2))  # [N, M], [N, M, M]
        pinv_n = a_n.transpose(1, 2) @ torch.linalg.inv(a_n @ a_n.transpose(1, 2) + 1e-6 * torch.eye(taps))  # [N, T, M]
        self.taps, self.bins, self.block = taps, t, block
        self.a = self.frame(torch, a_n, h, w)  # [M, T, H, W]
        self.pinv = self.frame(torch, pinv_n, h, w)  # [T, M, H, W]
        self.h, self.w = h, w

    def frame(self, torch, per_subpixel, h, w):
        """[N, I, J] per subpixel → [I, J, H, W] per pixel."""
        b = self.block
        n, i, j = per_subpixel.shape
        tile = per_subpixel.reshape(b, b, i, j).permute(2, 3, 0, 1)  # [I, J, bh, bw]
        return tile.repeat(1, 1, h // b, w // b).contiguous()

    def forward(self, x):  # [B, T, H, W] → [B, M, H, W]
        return (self.a.unsqueeze(0) * x.unsqueeze(1)).sum(2)

    def adjoint(self, y):  # [B, M, H, W] → [B, T, H, W]
        return (self.a.unsqueeze(0) * y.unsqueeze(2)).sum(1)

    def backproject(self, y):  # Aᵀ(AAᵀ + εI)⁻¹y, [B, M, H, W] → [B, T, H, W]
        return (self.pinv.unsqueeze(0) * y.unsqueeze(1)).sum(2)

    def x_update(self, torch, w, y, rho):
        """(AᵀA + ρI)⁻¹(Aᵀy + ρw) = w + Aᵀ Q diag(1/(ρ + λ)) Qᵀ (y − Aw), differentiable in w, y, ρ."""
        k_n = self.q @ torch.diag_embed(1.0 / (rho + self.lam)) @ self.q.transpose(1, 2)  # [N, M, M]
        k = self.frame(torch, k_n, self.h, self.w)  # [M, M, H, W]
        r = y - self.forward(w)  # [B, M, H, W]
        return w + self.adjoint((k.unsqueeze(0) * r.unsqueeze(1)).sum(2))


def AdmmNet(torch, sensor, stages, prior, channels):
    nn = torch.nn
    t = sensor.bins
    dil = [1, 3, 9]

    class DelayLayer(nn.Module):
        """3x3x3 conv on C channels per bin, circular in t with dilation d (conv3d or stack)."""

        def __init__(self, cin, cout, d, how):
            super().__init__()
            self.d, self.how = d % t, how
            if how == "conv3d":
                self.conv = nn.Conv3d(cin, cout, 3, padding=(0, 1, 1), dilation=(self.d, 1, 1))
            else:
                self.conv = nn.Conv2d(3 * cin, cout, 3, padding=1)

        def forward(self, x):
            d = self.d
            if self.how == "conv3d":  # x [B, C, T, H, W]
                xp = torch.cat([x[:, :, t - d:], x, x[:, :, :d]], 2)
                return self.conv(xp)
            b, tt, c, h, w = x.shape  # x [B, T, C, H, W]
            taps = torch.cat([x.roll(d, 1), x, x.roll(-d, 1)], 2).reshape(b * tt, 3 * c, h, w)
            return self.conv(taps).reshape(b, tt, -1, h, w)

    class Stage(nn.Module):
        def __init__(self):
            super().__init__()
            self.log_rho = nn.Parameter(torch.tensor(0.1).log())
            self.eta = nn.Parameter(torch.tensor(1.0))
            if prior == "bins":
                self.p = nn.Sequential(nn.Conv2d(t, channels, 3, padding=1), nn.ReLU(), nn.Conv2d(channels, channels, 3, padding=1), nn.ReLU(), nn.Conv2d(channels, t, 3, padding=1))
            else:
                self.l1, self.l2, self.l3 = DelayLayer(1, channels, dil[0], prior), DelayLayer(channels, channels, dil[1], prior), DelayLayer(channels, 1, dil[2], prior)

        def prior(self, x):  # [B, T, H, W]
            if prior == "bins":
                return self.p(x)
            z = x.unsqueeze(1) if prior == "conv3d" else x.unsqueeze(2)
            z = self.l3(torch.relu(self.l2(torch.relu(self.l1(z)))))
            return z.squeeze(1) if prior == "conv3d" else z.squeeze(2)

    class Net(nn.Module):
        cube = True

        def __init__(self):
            super().__init__()
            self.stages = nn.ModuleList(Stage() for _ in range(stages))

        def forward(self, y):
            z = sensor.backproject(y)
            u = torch.zeros_like(z)
            for st in self.stages:
                rho = st.log_rho.exp()
                x = sensor.x_update(torch, z - u, y, rho)
                xu = x + u
                z = xu + st.prior(xu)
                u = u + st.eta * (x - z)
            return z

    return Net()


def Unet(torch, sensor, base, levels, returns):
    nn = torch.nn
    t = sensor.bins

    def block(i, o):
        return nn.Sequential(nn.Conv2d(i, o, 3, padding=1), nn.ReLU(), nn.Conv2d(o, o, 3, padding=1), nn.ReLU())

    class Net(nn.Module):
        cube = False

        def __init__(self):
            super().__init__()
            wd = [base << l for l in range(levels)]
            self.down = nn.ModuleList(block(t if l == 0 else wd[l - 1], wd[l]) for l in range(levels))
            self.up = nn.ModuleList(block(wd[l + 1] + wd[l], wd[l]) for l in range(levels - 1))
            self.head = nn.Conv2d(wd[0], 2 * returns, 1)

        def forward(self, y):
            x = sensor.adjoint(y)
            norm = x.pow(2).sum(1, keepdim=True).sqrt()
            z = x / (norm + 1e-3 * norm.mean((2, 3), keepdim=True) + 1e-30)
            skips = []
            for l, blk in enumerate(self.down):
                z = blk(z)
                if l + 1 < levels:
                    skips.append(z)
                    z = nn.functional.max_pool2d(z, 2)
            for blk, skip in reversed(list(zip(self.up, skips))):
                z = blk(torch.cat([nn.functional.interpolate(z, scale_factor=2, mode="nearest"), skip], 1))
            o = self.head(z)
            return torch.cat([10.0 * torch.sigmoid(o[:, :returns]), o[:, returns:]], 1)

    return Net()


def time_steps(torch, net, sensor, batch, steps):
    """Median (step, forward, backward, Adam) ms over `steps` Adam steps after one warm-up."""
    g = torch.Generator().manual_seed(3)
    x = (torch.rand(batch, sensor.bins, sensor.h, sensor.w, generator=g) < 0.1).float()
    y = sensor.forward(x)
    depth = 2.0 + 6.0 * torch.rand(batch, 2, sensor.h, sensor.w, generator=g)
    present = (torch.rand(batch, 2, sensor.h, sensor.w, generator=g) < 0.5).float()
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    times = []
    for _ in range(steps + 1):
        t0 = time.perf_counter()
        out = net(y)
        if net.cube:
            err = out - x
            loss = err.pow(2).mean().sqrt() + err.abs().mean()
        else:
            k = out.shape[1] // 2
            loss = ((out[:, :k] - depth).abs() * present).mean() + torch.nn.functional.binary_cross_entropy_with_logits(out[:, k:], present)
        loss.item()
        t1 = time.perf_counter()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        t2 = time.perf_counter()
        opt.step()
        t3 = time.perf_counter()
        times.append(((t3 - t0) * 1e3, (t1 - t0) * 1e3, (t2 - t1) * 1e3, (t3 - t2) * 1e3))
    times = sorted(times[1:], key=lambda r: r[0])
    return times[len(times) // 2]


if __name__ == "__main__":
    main()
