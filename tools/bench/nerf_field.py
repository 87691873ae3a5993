#!/usr/bin/env python3
"""Benchmark: field throughput on CPU (samples/s), forward and training step, against the obvious way.

"Obvious way" = a per-level, per-corner torch implementation (one gather per level
and corner, weights built per corner; `encoding.reference_hash_encode`) with
separate per-level tables, L=16 x F=2, T=2^19, the same MLPs, torch Adam.

Variants, measured in the same run on the same samples (points along random rays,
as the renderer produces them), so each step of the ladder shows what it bought:

  naive     16x2 T=2^19  per-level per-corner gathers, torch Adam
  onegather 16x2 T=2^19  all levels x 8 corners in one embedding_bag, torch Adam (the CUDA path)
  kernels   16x2 T=2^19  fused numba forward/backward, torch Adam
  +lazyadam 16x2 T=2^19  + lazy Adam on the rows that got a gradient
  ours      8x4  T=2^17  fused kernels + lazy Adam, the trainer's configuration

Forward = encoding + density MLP + colour MLP without gradients; training step =
forward + MSE + backward + optimizer step.

    flock /tmp/nerf_cpu.lock .venv/bin/python tools/bench/nerf_field.py [--n 65536] [--repeat 5]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from blender_nerf_deform.engine import backend  # noqa: E402
from blender_nerf_deform.engine.nerf.adam_kernels import sparse_adam  # noqa: E402
from blender_nerf_deform.engine.nerf.encoding import reference_hash_encode  # noqa: E402
from blender_nerf_deform.engine.nerf.model import NerfConfig, NerfModel  # noqa: E402


def samples(n: int, seed: int = 0):
    """n points along random rays through the unit box, 32 consecutive samples per ray (step 1/170)."""
    g = torch.Generator().manual_seed(seed)
    rays = n // 32 + 1
    o = torch.rand(rays, 3, generator=g) * 3 - 1.5
    d = torch.nn.functional.normalize(torch.randn(rays, 3, generator=g), dim=-1)
    t = torch.arange(32, dtype=torch.float32) * (3 / 170)
    pts = (o[:, None] + d[:, None] * t[None, :, None]).reshape(-1, 3)[:n]
    pts = pts.clamp(-1.49, 1.49).contiguous()
    dirs = d[:, None].expand(rays, 32, 3).reshape(-1, 3)[:n].contiguous()
    return pts, dirs


class Variant:
    def __init__(self, name, levels, feats, log2t, mode):
        self.name, self.mode = name, mode
        torch.manual_seed(0)
        self.model = NerfModel(
            NerfConfig(
                n_levels=levels,
                n_features=feats,
                log2_table_size=log2t,
                finest_resolution=2048 if levels == 16 else 512,
            )
        )
        enc = self.model.encoding
        self.path = "auto" if mode in ("kernels", "lazyadam", "ours") else "torch"  # backend.forced per call
        enc.fused_grad = mode in ("lazyadam", "ours")
        mlp = list(self.model.density_net.parameters()) + list(self.model.color_net.parameters())
        if mode == "naive":
            # Separate per-level tables, as the obvious implementation keeps them.
            self.tables = torch.nn.ParameterList(
                [
                    torch.nn.Parameter(enc.table.detach()[int(o) : int(o) + s].clone())
                    for o, s in zip(enc.offsets, enc.level_sizes)
                ]
            )
            params = list(self.tables) + mlp
        elif enc.fused_grad:
            params = mlp
            self.m = torch.zeros_like(enc.table.detach())
            self.v = torch.zeros_like(enc.table.detach())
        else:
            params = [enc.table] + mlp
        self.opt = torch.optim.Adam(params, lr=1e-2, betas=(0.9, 0.99), eps=1e-15)
        self.t = 0

    def query(self, pts, dirs):
        m = self.model
        if self.mode == "naive":
            x = m.normalize(pts)
            h = m.density_net(reference_hash_encode(m.encoding, x, tables=list(self.tables)))
            sigma = torch.exp(h[:, 0] - 1.0)
            return sigma, m.color(h, dirs)
        return m.query(pts, dirs)

    def forward(self, pts, dirs):
        with torch.no_grad(), backend.forced(self.path):
            return self.query(pts, dirs)

    def train_step(self, pts, dirs, target):
        with backend.forced(self.path):
            self._train_step(pts, dirs, target)

    def _train_step(self, pts, dirs, target):
        sigma, rgb = self.query(pts, dirs)
        loss = ((rgb - target) ** 2).mean() + 1e-3 * sigma.mean()
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        self.opt.step()
        self.t += 1
        enc = self.model.encoding
        if enc.fused_grad:
            sparse_adam(
                enc.table.detach().numpy(),
                enc.grad_buffer().numpy(),
                self.m.numpy(),
                self.v.numpy(),
                enc.touched_rows(),
                1e-2,
                0.9,
                0.99,
                1e-15,
                1 - 0.9**self.t,
                1 - 0.99**self.t,
            )


def timed(fn, repeat):
    fn()  # warm-up (numba compilation, allocator)
    best = float("inf")
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=1 << 16, help="samples per call")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--json")
    args = ap.parse_args()
    pts, dirs = samples(args.n)
    target = torch.rand(args.n, 3)
    ladder = [("naive", 16, 2, 19, "naive"), ("onegather", 16, 2, 19, "onegather")]
    if backend.HAVE_NUMBA:
        ladder += [("kernels", 16, 2, 19, "kernels"), ("+lazyadam", 16, 2, 19, "lazyadam"), ("ours", 8, 4, 17, "ours")]
    ladder.append(("ours-torch", 8, 4, 17, "onegather"))
    rows = []
    for name, levels, feats, log2t, mode in ladder:
        v = Variant(name, levels, feats, log2t, mode)
        fwd = timed(lambda v=v: v.forward(pts, dirs), args.repeat)
        stp = timed(
            lambda v=v: v.train_step(pts, dirs, target), max(2, args.repeat // 2) if mode == "naive" else args.repeat
        )
        rows.append(
            {
                "variant": name,
                "levels": levels,
                "features": feats,
                "log2_table": log2t,
                "forward_Msamples_s": args.n / fwd / 1e6,
                "train_step_Msamples_s": args.n / stp / 1e6,
            }
        )
        print(json.dumps(rows[-1]), flush=True)
    base = rows[0]
    print(f"\n{'variant':<12} {'config':<14} {'forward M/s':>12} {'x naive':>8} {'train M/s':>10} {'x naive':>8}")
    for r in rows:
        cfg = f"{r['levels']}x{r['features']} 2^{r['log2_table']}"
        print(
            f"{r['variant']:<12} {cfg:<14} {r['forward_Msamples_s']:>12.3f} "
            f"{r['forward_Msamples_s'] / base['forward_Msamples_s']:>8.1f} {r['train_step_Msamples_s']:>10.3f} "
            f"{r['train_step_Msamples_s'] / base['train_step_Msamples_s']:>8.1f}"
        )
    if args.json:
        Path(args.json).write_text(
            json.dumps({"n": args.n, "threads": torch.get_num_threads(), "rows": rows}, indent=1)
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
