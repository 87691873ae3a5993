#!/usr/bin/env python3
"""Train NeRF from Blender vs the command line, same data and budget: what the UI costs in steps.

    flock /tmp/nerf_cpu.lock .venv/bin/python tools/bench_train_ui.py --data ../shared/datasets/lego_200 \
        [--seconds 60] [--work DIR]

Three runs of the same time budget (the trainer's own training time, so start-up is not
counted) on the same data, one after the other:
  cli     `python -m blender_nerf_deform.engine train` in a subprocess (no Blender);
  ui      what the Train NeRF button does: the request submitted to the worker from Blender (the
          bpy module), progress drained by a 0.1 s timer on the main thread as the modal
          operator's timer does, the status text formatted each tick;
  script  `bpy.ops.nerf_deform.train_nerf(...)` (execute: blocking, as in `blender -b`).
Each run starts its own process (the worker is restarted between ui and script), so each pays
the kernels' compilation in its first step alike. Prints steps reached, batch PSNR and the `eval` PSNR of each checkpoint on the dataset's views,
and the steps of ui and script as a fraction of cli.
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

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))


def eval_psnr(ckpt: Path, data: str) -> float:
    proc = subprocess.run([sys.executable, "-m", "blender_nerf_deform.engine", "eval", "--nerf", str(ckpt), "--data", data],
                          capture_output=True, text=True, cwd=REPO)
    if proc.returncode != 0:
        raise SystemExit(f"eval failed: {proc.stderr[-2000:]}")
    found = re.findall(r"PSNR[^0-9\-]*([0-9.]+)", proc.stdout + proc.stderr)
    return float(found[-1]) if found else float("nan")


def run_cli(data: str, out: Path, seconds: float) -> dict:
    proc = subprocess.run([sys.executable, "-m", "blender_nerf_deform.engine", "train", "--data", data, "--out", str(out),
                           "--max-seconds", str(seconds)], capture_output=True, text=True, cwd=REPO)
    if proc.returncode != 0:
        raise SystemExit(f"train failed: {proc.stderr[-2000:]}")
    return json.loads((out / "train.json").read_text())


def run_ui(bpy, data: str, out: Path, seconds: float) -> dict:
    """The modal operator's path, without a window: submit, then drain on a 0.1 s tick."""
    from blender_nerf_deform.addon import jobs

    client = jobs.worker(bpy.context)
    client.ensure_started()
    state = {"done": None, "progress": 0.0, "message": "", "ticks": 0}
    client.submit("train", {"data": data, "out": str(out), "device": "auto", "downscale": 1, "resume": False,
                            "max_seconds": float(seconds)}, None,
                  on_done=lambda result, arrays: state.update(done=("ok", result)),
                  on_error=lambda error: state.update(done=("error", error)),
                  on_progress=lambda f, msg: state.update(progress=f, message=msg))
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
    from blender_nerf_deform.addon import worker_client

    worker_client.shutdown()  # a fresh worker, as cli and ui have: each run compiles its kernels once
    result = bpy.ops.nerf_deform.train_nerf(data=data, run_folder=str(out), seconds=seconds)
    if result != {"FINISHED"}:
        raise SystemExit(f"bpy.ops.nerf_deform.train_nerf returned {result}")
    return json.loads((out / "train.json").read_text())


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", required=True)
    p.add_argument("--seconds", type=float, default=60.0)
    p.add_argument("--work", type=Path, default=None)
    args = p.parse_args(argv)
    work = args.work or Path(tempfile.mkdtemp(prefix="bench_train_ui_"))
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    data = str(Path(args.data).resolve())

    import bpy

    import blender_nerf_deform

    bpy.ops.wm.read_factory_settings(use_empty=True)
    blender_nerf_deform.register()
    try:
        runs = {"cli": run_cli(data, work / "cli", args.seconds),
                "ui": run_ui(bpy, data, work / "ui", args.seconds),
                "script": run_script(bpy, data, work / "script", args.seconds)}
    finally:
        blender_nerf_deform.unregister()
    print(f"data {data}, budget {args.seconds:.0f} s of training each")
    for name, summary in runs.items():
        psnr = eval_psnr(work / name / "nerf.ckpt", data)
        ratio = summary["steps"] / runs["cli"]["steps"]
        print(f"{name:7s} steps {summary['steps']:6d} ({ratio:6.1%} of cli)  batch PSNR {summary.get('psnr', float('nan')):.2f} dB"
              f"  eval PSNR {psnr:.2f} dB  training {summary.get('seconds', float('nan')):.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
