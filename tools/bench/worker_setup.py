#!/usr/bin/env python3
"""Time "Set Up Worker" (addon/worker/setup.py): a fresh worker environment, download included, then a reuse.

    flock /tmp/nerf_cpu.lock .venv/bin/python tools/bench/worker_setup.py [--folder DIR] [--cache]
        [--torch-source PIP|AUTO|CUSTOM] [--build CPU|CUDA]

Runs the same SetupJob the preferences' button runs (in this process, blocking), into a
temporary folder (or --folder), with pip's cache off unless --cache, so every package is
fetched from the package index (or the mirror pip is configured with). Prints the seconds of
the fresh setup, of the reuse check that a second press does, and the environment's size.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))


def folder_size(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file() and not f.is_symlink())


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--folder", type=Path, default=None)
    p.add_argument("--cache", action="store_true", help="let pip use its cache (default: off, download everything)")
    p.add_argument("--torch-source", default="PIP", choices=("PIP", "AUTO", "CUSTOM"))
    p.add_argument("--build", default="CPU", choices=("CPU", "CUDA"))
    args = p.parse_args(argv)
    import bpy  # noqa: F401  (the add-on module needs Blender's Python API)

    from blender_nerf_deform.addon.worker.setup import SetupJob

    if not args.cache:
        os.environ["PIP_NO_CACHE_DIR"] = "1"
    folder = args.folder or Path(tempfile.mkdtemp(prefix="bench_worker_setup_"))
    try:
        started = time.perf_counter()
        job = SetupJob(folder, "REBUILD", build=args.build, torch_source=args.torch_source)
        job.run()
        fresh = time.perf_counter() - started
        if job.done != "ok":
            print(f"setup failed: {job.error}", file=sys.stderr)
            return 1
        started = time.perf_counter()
        again = SetupJob(folder, "AUTO", build=args.build, torch_source=args.torch_source)
        again.run()
        reuse = time.perf_counter() - started
        assert again.done == "ok" and again.reused, again.error
        size = folder_size(folder / "worker-env")
        print(
            f"fresh setup: {fresh:.1f} s (pip cache {'on' if args.cache else 'off'}, torch {job.info['torch']}, "
            f"{'CUDA' if job.info['cuda'] else 'CPU'}), environment {size / 2**20:.0f} MiB"
        )
        print(f"second press (reuse check): {reuse:.1f} s")
        print(f"ratio fresh / reuse: {fresh / reuse:.0f}x")
    finally:
        if args.folder is None:
            shutil.rmtree(folder, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
