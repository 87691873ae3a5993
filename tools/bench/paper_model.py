#!/usr/bin/env python3
"""The paper model of an H100 for the device path: per kernel, the bytes it moves and the FLOPs it does in one
training step and in one 1920x1080 frame, the time those take at the H100's rates, beside the launch
overhead (launches x 5 us) before and after.

    .venv/bin/python tools/bench/paper_model.py --before BEFORE.json --after AFTER.json

BEFORE/AFTER: tools/bench/cuda_launches.py's JSON (launches per step and per round, rays, samples per ray).
The model's sizes are the default NerfConfig's (8 levels x 4 features, 2^17 rows a level, density MLP
32-64-16, colour MLP 32-64-64-3, SH degree 4, occupancy 128^3). Bytes count DRAM traffic of each kernel's
inputs and outputs (float32); the hash table (16 MiB) and the occupancy grid (2 MiB) stay in the H100's
50 MiB L2, so their gathers are not counted as DRAM bytes. A 1080p frame's samples per ray are the lego
figures measured on the CPU path (13.2 density samples per ray, BENCHMARKS.md, "fast" path), all of them
coloured on the device path (it does not skip faint samples' colour). Launch overhead: ~5 us a launch.
"""

from __future__ import annotations

import argparse
import json

BANDWIDTH = 3.35e12  # bytes/s, H100 SXM HBM3
FLOPS_FP16 = 990e12  # dense fp16 tensor cores
FLOPS_FP32 = 67e12  # fp32 CUDA cores (the MLPs run in float32 today)
LAUNCH_S = 5e-6

LEVELS, FEATURES, TABLE_ROWS = 8, 4, 1 << 17
ENC = LEVELS * FEATURES  # 32
DENSITY_MACS = ENC * 64 + 64 * 16
COLOR_MACS = 32 * 64 + 64 * 64 + 64 * 3
TABLE_PARAMS = LEVELS * TABLE_ROWS * FEATURES  # upper bound (the coarse levels are dense and smaller)


def kernels(rays: float, samples: float, k_slots: float, train: bool) -> list[tuple[str, float, float]]:
    """(kernel, DRAM bytes, FLOPs) for `rays` rays and `samples` density samples (all coloured)."""
    s = samples
    rows = [
        ("march setup (rays in, state out)", rays * (24 + 41), rays * 60),
        ("march (t, dt slots written)", rays * k_slots * 8, rays * k_slots * 20),
        ("flat samples (index, t, dt, position, direction)", s * (8 * 3 + 4 * 2 + 12 * 2 + 1), s * 20),
        ("hash encoding forward (x in, 32 features out)", s * (12 + ENC * 4), s * LEVELS * 8 * (FEATURES * 2 + 12)),
        ("density MLP forward (32 in, 64 hidden, 16 out)", s * 4 * (ENC + 2 * 64 + 16), s * 2 * DENSITY_MACS),
        ("SH encoding (direction in, 16 out)", s * (12 + 64), s * 40),
        ("colour MLP forward (32 in, 2x64 hidden, 3 out)", s * 4 * (32 + 4 * 64 + 3), s * 2 * COLOR_MACS),
        ("composite (sigma, dt, t, rgb in; pixels out)", s * 4 * 6 + rays * 20, s * 20),
    ]
    if train:
        rows += [
            (
                "second pass: density + colour MLP forward again",
                s * 4 * (ENC + 2 * 64 + 16 + 32 + 4 * 64 + 3),
                s * 2 * (DENSITY_MACS + COLOR_MACS),
            ),
            (
                "MLP backward (both, activations and weight gradients)",
                2 * s * 4 * (ENC + 2 * 64 + 16 + 32 + 4 * 64 + 3),
                s * 4 * (DENSITY_MACS + COLOR_MACS),
            ),
            ("composite backward", s * 4 * 8, s * 30),
            (
                "hash backward (gradient in; atomics into the L2-resident table gradient)",
                s * (12 + ENC * 4),
                s * LEVELS * 8 * FEATURES * 2,
            ),
            ("table gradient zeroed", TABLE_PARAMS * 4, 0),
            ("fused Adam (param, grad, m, v read; param, m, v written)", TABLE_PARAMS * 4 * 7, TABLE_PARAMS * 12),
        ]
    return rows


def report(name: str, rows, launches_before: float, launches_after: float) -> dict:
    total_b = sum(r[1] for r in rows)
    total_f = sum(r[2] for r in rows)
    print(f"\n{name}")
    print("| kernel | DRAM bytes | FLOPs | time at 3.35 TB/s | time at 990 TFLOP/s |")
    print("| --- | --- | --- | --- | --- |")
    for kernel, b, f in rows:
        print(
            f"| {kernel} | {b / 1e6:.1f} MB | {f / 1e9:.2f} GFLOP | {b / BANDWIDTH * 1e6:.1f} us | "
            f"{f / FLOPS_FP16 * 1e6:.2f} us |"
        )
    mem_s, fp16_s, fp32_s = total_b / BANDWIDTH, total_f / FLOPS_FP16, total_f / FLOPS_FP32
    print(
        f"| **all** | {total_b / 1e6:.0f} MB | {total_f / 1e9:.1f} GFLOP | **{mem_s * 1e3:.3f} ms** | "
        f"{fp16_s * 1e3:.3f} ms (fp32 cores: {fp32_s * 1e3:.3f} ms) |"
    )
    print(
        f"launch overhead: before {launches_before:.0f} x 5 us = {launches_before * LAUNCH_S * 1e3:.2f} ms, "
        f"after {launches_after:.0f} x 5 us = {launches_after * LAUNCH_S * 1e3:.2f} ms"
    )
    return {
        "bytes": total_b,
        "flops": total_f,
        "memory_ms": mem_s * 1e3,
        "fp16_ms": fp16_s * 1e3,
        "fp32_ms": fp32_s * 1e3,
        "launch_ms_before": launches_before * LAUNCH_S * 1e3,
        "launch_ms_after": launches_after * LAUNCH_S * 1e3,
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--before", required=True)
    ap.add_argument("--after", required=True)
    ap.add_argument("--box-steps", type=float, default=514, help="lattice steps across lego's box (512 + 2)")
    ap.add_argument("--frame-samples-per-ray", type=float, default=13.2)
    ap.add_argument("--frame-chunk", type=int, default=1 << 18, help="rays a CUDA frame chunk holds")
    args = ap.parse_args()
    before, after = json.load(open(args.before)), json.load(open(args.after))
    step = after["train"]["a_step"]
    rays = after["train"]["rays_mean"]
    samples = rays * (step.get("density_samples_per_ray") or step["samples_per_ray"])
    out = {
        "step": report(
            f"Training step ({rays:.0f} rays, {samples:.0f} density samples, all with gradients)",
            kernels(rays, samples, args.box_steps, True),
            before["train"]["launches_mean"],
            after["train"]["launches_mean"],
        )
    }
    pixels = 1920 * 1080
    chunks = -(-pixels // args.frame_chunk)
    frame = []
    for name in ("rest", "bent"):
        # Launches of a 1080p frame: the counted frame's fixed part is small; its rounds scale with the chunks.
        per_round_b, per_round_a = before[name]["launches_per_round"], after[name]["launches_per_round"]
        rounds_per_chunk = after[name]["rounds"]
        frame.append((name, per_round_b, per_round_a, rounds_per_chunk))
    name, per_round_b, per_round_a, rounds_per_chunk = frame[0]
    # Before: 64K-ray chunks on every device; after: FRAME_CHUNK_CUDA.
    chunks_before = -(-pixels // (1 << 16))
    out["frame"] = report(
        f"1920x1080 frame, rest ({pixels * args.frame_samples_per_ray / 1e6:.1f} M density "
        f"samples; {chunks} chunks x ~{rounds_per_chunk} rounds after, {chunks_before} before)",
        kernels(pixels, pixels * args.frame_samples_per_ray, 2 * args.frame_samples_per_ray, False),
        chunks_before * rounds_per_chunk * per_round_b,
        chunks * rounds_per_chunk * per_round_a,
    )
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
