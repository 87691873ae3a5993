"""Time `make test` in a checkout and count the processes the suite starts (issue 27).

    flock /tmp/nerf_cpu.lock .venv/bin/python tools/bench/test_suite.py --checkout ../clean-clone \
        [--make-args "TEST_WORKERS=0"] [--log suite.log]

Runs `make test PYTEST_ARGS=--durations=15` in the checkout (a fresh clone measures what CI pays:
the .venv set-up, numba's kernel compiles, every fixture), with a `sitecustomize` on PYTHONPATH that
appends one line per Python process to a log when it exits: what it imported (bpy: a Blender; torch:
a worker, an engine command or a test process) and its command line. Prints the wall time, the CPU
time of the run's processes, pytest's 15 slowest tests and the processes by role. Processes that
die by a signal or `os._exit` write no line, so the counts are a floor.
"""

from __future__ import annotations

import argparse
import collections
import os
import re
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

COUNTER = """
import atexit, os, sys
def _log():
    try:
        kind = "+".join(k for k in ("bpy", "torch", "_pytest") if k in sys.modules) or "-"
        with open(os.environ["NERF_SUITE_PROCESS_LOG"], "a") as f:
            f.write(f"{kind}\\t{' '.join(sys.argv)[:200]!r}\\n")
    except Exception:
        pass
atexit.register(_log)
"""


def role(kind: str, argv: str) -> str:
    if "engine.service.worker" in argv or "service/worker.py" in argv:
        return "engine worker"
    if "engine/__main__.py" in argv or "blender_nerf_deform.engine " in argv:
        return "engine command line"
    if "_pytest" in kind:
        return "pytest (the runner and its xdist workers)"
    if "bpy" in kind:
        return "Blender (bpy) process"
    if "pip" in argv:
        return "pip"
    return "other Python"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--checkout", type=Path, required=True, help="the repository to run `make test` in")
    ap.add_argument("--make-args", default="", help="extra make arguments, e.g. TEST_WORKERS=0")
    ap.add_argument("--log", type=Path, help="keep make's output here (default: a temporary file)")
    args = ap.parse_args(argv)
    if not (args.checkout / "Makefile").is_file():
        ap.error(f"--checkout {args.checkout} has no Makefile")

    work = Path(tempfile.mkdtemp(prefix="bench_test_suite_"))
    (work / "sitecustomize.py").write_text(COUNTER)
    processes = work / "processes.tsv"
    log = args.log or work / "make_test.log"
    env = {
        **os.environ,
        "NERF_SUITE_PROCESS_LOG": str(processes),
        "PYTHONPATH": os.pathsep.join(p for p in (str(work), os.environ.get("PYTHONPATH", "")) if p),
    }
    started = time.perf_counter()
    with open(log, "w") as out:
        proc = subprocess.run(
            ["make", "test", "PYTEST_ARGS=--durations=15", *args.make_args.split()],
            cwd=args.checkout,
            env=env,
            stdout=out,
            stderr=subprocess.STDOUT,
        )
    wall = time.perf_counter() - started
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)  # every process make waited for, and theirs
    cpu = usage.ru_utime + usage.ru_stime
    text = log.read_text(errors="replace")

    summary = [line for line in text.splitlines() if re.search(r"\d+ (passed|failed)", line)]
    print(
        f"make test: exit {proc.returncode}, wall {wall:.0f} s ({wall / 60:.1f} min); "
        f"{summary[-1].strip('= ') if summary else 'no pytest summary'}"
    )
    # Processes nobody waited for (killed, orphaned) are not counted: a floor, as the counts below.
    print(
        f"CPU (user + system) of the run's processes: {cpu / 60:.1f} min, {100 * cpu / (wall * os.cpu_count()):.0f} % "
        f"of the machine's {os.cpu_count()} cores over the wall time"
    )
    durations = text.split("slowest 15 durations", 1)[-1].splitlines()[1:17] if "slowest 15 durations" in text else []
    print("slowest 15:")
    for line in durations:
        if re.match(r"^\d", line):
            print("  " + line)
    counts: collections.Counter = collections.Counter()
    if processes.is_file():
        for line in processes.read_text().splitlines():
            kind, _, cmd = line.partition("\t")
            counts[role(kind, cmd)] += 1
    print("Python processes started (that exited normally):", sum(counts.values()))
    for name, n in counts.most_common():
        print(f"  {n:5d}  {name}")
    print(f"make output: {log}")
    return proc.returncode


if __name__ == "__main__":
    sys.exit(main())
