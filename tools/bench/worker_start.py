#!/usr/bin/env python3
"""How long the engine worker takes from its start to its hello (torch, numba and the engine imported).

    .venv/bin/python tools/bench/worker_start.py [--repeats 3] [--python PY]

Starts `python -m blender_nerf_deform.engine.service.worker` with the environment the add-on gives it
(`addon/worker/client.worker_environment`) and, alternating, with that environment plus all bytecode
redirected to a folder (`PYTHONPYCACHEPREFIX`, what the add-on set before issue 28), written there
or not (`PYTHONDONTWRITEBYTECODE`, which container images often set). Prints each run and the medians.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from blender_nerf_deform.addon.worker.client import WORKER_MODULE, worker_environment  # noqa: E402
from blender_nerf_deform.engine.service.protocol import read_message  # noqa: E402


def hello_seconds(python: str, env: dict, cwd: str) -> float:
    start = time.perf_counter()
    proc = subprocess.Popen(
        [python, "-m", WORKER_MODULE],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        env=env,
        cwd=cwd,
    )
    try:
        message = read_message(proc.stdout)
        if message is None or message[0].get("type") != "hello":
            raise SystemExit(f"the worker did not say hello: {message!r}")
        return time.perf_counter() - start
    finally:
        proc.kill()
        proc.wait()


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=3, help="starts per environment (default 3)")
    parser.add_argument("--python", default=sys.executable, help="the worker's Python (default this one)")
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error("--repeats must be at least 1")
    env, work = worker_environment()
    with tempfile.TemporaryDirectory(prefix="worker_start_") as tmp:
        envs = {
            "add-on's environment": env,
            "bytecode redirected, not written": {
                **env,
                "PYTHONPYCACHEPREFIX": str(Path(tmp) / "a"),
                "PYTHONDONTWRITEBYTECODE": "1",
            },
            "bytecode redirected and written": {
                k: v
                for k, v in {**env, "PYTHONPYCACHEPREFIX": str(Path(tmp) / "b")}.items()
                if k != "PYTHONDONTWRITEBYTECODE"
            },
        }
        times: dict[str, list[float]] = {name: [] for name in envs}
        for _ in range(args.repeats):
            for name, e in envs.items():
                times[name].append(hello_seconds(args.python, e, work))
                print(f"{name}: {times[name][-1]:.2f} s", flush=True)
    for name, t in times.items():
        print(f"{name:34s} median {statistics.median(t):.2f} s ({', '.join(f'{x:.2f}' for x in t)})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
