#!/usr/bin/env python3
"""Train NeRF from Blender vs the command line, same data and budget: what the UI costs in steps.

    flock /tmp/nerf_cpu.lock .venv/bin/python tools/bench/train_ui.py --data ../shared/datasets/lego_200 \
        [--seconds 60] [--rounds 2] [--warmup-steps 3] [--paths cli,ui,script] [--work DIR]

Three paths, the same time budget (the trainer's own training time, so start-up is not
counted) on the same data:
  cli     `python -m blender_nerf_deform.engine train` in a subprocess (no Blender);
  ui      what the Train NeRF button does: the request submitted to the worker from Blender (the
          bpy module), progress drained by a 0.1 s timer on the main thread as the modal
          operator's timer does, the status text formatted each tick;
  script  `bpy.ops.nerf_deform.train_nerf(...)` (execute: blocking, as in `blender -b`).
Each run starts its own process (the worker is restarted between runs). First a warm-up of
--warmup-steps steps through the command line and through the worker: each compiles its numba
kernels into its own cache (the command line's beside the sources, the worker's in its working
folder), and a cold cache costs ~10 s of the first step, which would otherwise land in whichever run
comes first; the warm-up's trainer seconds are printed (the one-time cost of a fresh install).
Then --rounds rounds of the three, the order rotated each round so that the machine's drift falls
on every path alike. Prints each run's steps, batch PSNR and the `eval` PSNR of the last round's
checkpoints on the dataset's views, and the mean steps of ui and script as a fraction of cli's.
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))


def eval_psnr(ckpt: Path, data: str) -> float:
    proc = subprocess.run(
        [sys.executable, "-m", "blender_nerf_deform.engine", "eval", "--nerf", str(ckpt), "--data", data],
        capture_output=True,
        text=True,
        cwd=REPO,
    )
    if proc.returncode != 0:
        raise SystemExit(f"eval failed: {proc.stderr[-2000:]}")
    found = re.findall(r"PSNR[^0-9\-]*([0-9.]+)", proc.stdout + proc.stderr)
    return float(found[-1]) if found else float("nan")


def run_cli(data: str, out: Path, seconds: float | None, steps: int | None) -> dict:
    budget = ["--max-seconds", str(seconds)] if seconds else ["--steps", str(steps)]
    proc = subprocess.run(
        [sys.executable, "-m", "blender_nerf_deform.engine", "train", "--data", data, "--out", str(out), *budget],
        capture_output=True,
        text=True,
        cwd=REPO,
    )
    if proc.returncode != 0:
        raise SystemExit(f"train failed: {proc.stderr[-2000:]}")
    return json.loads((out / "train.json").read_text())


def run_ui(bpy, data: str, out: Path, seconds: float | None, steps: int | None) -> dict:
    """The modal operator's path, without a window: submit, then drain on a 0.1 s tick."""
    from blender_nerf_deform.addon.worker import jobs

    client = jobs.worker(bpy.context)
    client.ensure_started()
    state = {"done": None, "progress": 0.0, "message": "", "ticks": 0}
    budget = {"max_seconds": float(seconds)} if seconds else {"steps": int(steps)}
    client.submit(
        "train",
        {"data": data, "out": str(out), "device": "auto", "downscale": 1, "resume": False, **budget},
        None,
        on_done=lambda result, arrays: state.update(done=("ok", result)),
        on_error=lambda error: state.update(done=("error", error)),
        on_progress=lambda f, msg: state.update(progress=f, message=msg),
    )
    while state["done"] is None:
        time.sleep(0.1)
        client.drain()
        state["ticks"] += 1
        _status = f"Train NeRF: {100 * state['progress']:.0f}% {state['message']} (Esc to cancel)"  # noqa: F841
    kind, payload = state["done"]
    if kind != "ok":
        raise SystemExit(f"ui training failed: {payload}")
    return {**json.loads((out / "train.json").read_text()), "ticks": state["ticks"]}


def run_script(bpy, data: str, out: Path, seconds: float) -> dict:
    result = bpy.ops.nerf_deform.train_nerf(data=data, run_folder=str(out), seconds=seconds)
    if result != {"FINISHED"}:
        raise SystemExit(f"bpy.ops.nerf_deform.train_nerf returned {result}")
    return json.loads((out / "train.json").read_text())


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", required=True)
    p.add_argument("--seconds", type=float, default=60.0)
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--warmup-steps", type=int, default=3)
    p.add_argument(
        "--paths", default="cli,ui,script", help="which paths to run, comma-separated (cli first: the ratios' base)"
    )
    p.add_argument("--work", type=Path, default=None)
    args = p.parse_args(argv)
    work = args.work or Path(tempfile.mkdtemp(prefix="bench_train_ui_"))
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    data = str(Path(args.data).resolve())

    import bpy

    import blender_nerf_deform
    from blender_nerf_deform.addon.worker import client as worker_client

    bpy.ops.wm.read_factory_settings(use_empty=True)
    blender_nerf_deform.register()
    paths = {
        "cli": lambda out: run_cli(data, out, args.seconds, None),
        "ui": lambda out: run_ui(bpy, data, out, args.seconds, None),
        "script": lambda out: run_script(bpy, data, out, args.seconds),
    }
    runs: dict[str, list[dict]] = {name: [] for name in args.paths.split(",") if name in paths}
    try:
        warm_cli = run_cli(data, work / "warmup_cli", None, args.warmup_steps)
        warm_ui = run_ui(bpy, data, work / "warmup_ui", None, args.warmup_steps)
        print(
            f"warm-up ({args.warmup_steps} steps, trainer seconds, kernels compiled if their cache was cold): "
            f"cli {warm_cli['seconds']:.1f} s, worker {warm_ui['seconds']:.1f} s",
            flush=True,
        )
        names = [n for n in args.paths.split(",") if n]
        if not names or any(n not in paths for n in names):
            raise SystemExit(f"--paths: a comma-separated choice of {', '.join(paths)}, got {args.paths!r}")
        for r in range(args.rounds):
            for name in names[r % len(names) :] + names[: r % len(names)]:
                worker_client.shutdown()  # a fresh worker for each run, as each cli run is a fresh process
                summary = paths[name](work / f"{name}_{r}")
                runs[name].append(summary)
                print(f"round {r + 1} {name:7s} steps {summary['steps']:6d}", flush=True)
    finally:
        blender_nerf_deform.unregister()
    print(f"data {data}, budget {args.seconds:.0f} s of training each, {args.rounds} rounds")
    base = next(iter(runs))  # the ratios' base: cli when it ran
    base_mean = sum(s["steps"] for s in runs[base]) / len(runs[base])
    last = args.rounds - 1
    for name, summaries in runs.items():
        steps = [s["steps"] for s in summaries]
        mean = sum(steps) / len(steps)
        psnr = eval_psnr(work / f"{name}_{last}" / "nerf.ckpt", data)
        print(
            f"{name:7s} steps {' '.join(f'{n:6d}' for n in steps)}  "
            f"mean {mean:8.1f} ({mean / base_mean:6.1%} of {base})"
            f"  batch PSNR {summaries[-1].get('psnr', float('nan')):.2f} dB  eval PSNR {psnr:.2f} dB (round {last + 1})"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
