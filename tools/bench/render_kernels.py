#!/usr/bin/env python3
"""Benchmark: the fused CPU kernels of rendering against their torch versions (best of 5, same process).

SH encoding of 300k directions, contraction of 1M points, per-ray transmittance of 1M samples.

    flock /tmp/nerf_cpu.lock .venv/bin/python tools/bench/render_kernels.py
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from blender_nerf_deform.engine import backend  # noqa: E402
from blender_nerf_deform.engine.nerf import renderer  # noqa: E402
from blender_nerf_deform.engine.nerf.encoding import sh_encode  # noqa: E402
from blender_nerf_deform.engine.nerf.model import NerfConfig, NerfModel  # noqa: E402


def best_ms(f, n=5) -> float:
    f()
    times = []
    for _ in range(n):
        t = time.perf_counter()
        f()
        times.append(time.perf_counter() - t)
    return min(times) * 1e3


def main() -> int:
    argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter).parse_args()
    g = torch.Generator().manual_seed(0)
    d = torch.nn.functional.normalize(torch.randn(300000, 3, generator=g), dim=1)
    p = torch.randn(1000000, 3, generator=g) * 4
    tau = torch.rand(1000000, generator=g) * 0.1
    rays = torch.sort(torch.randint(0, 30000, (1000000,), generator=g)).values
    model = NerfModel(NerfConfig(contraction="linf"))
    for name, f in (
        ("SH encoding, 300k directions", lambda: sh_encode(d)),
        ("contraction, 1M points", lambda: model.normalize(p)),
        ("transmittance, 1M samples", lambda: renderer._exclusive_transmittance(tau, rays, 30000)),
    ):
        fast = best_ms(f)
        with backend.forced("torch"):
            slow = best_ms(f)
        print(f"{name}: kernel {fast:.1f} ms, torch {slow:.1f} ms, {slow / fast:.1f}x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
