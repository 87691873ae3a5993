"""Every benchmark in tools/bench/ still starts: its imports resolve and `--help` answers; those that
can run small without a demo scene or Blender run once, tiny. A function a benchmark uses that a
change removes breaks this test, not the next person's figure (BENCHMARKS.md names these scripts in
its commands)."""

from __future__ import annotations

import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor

import pytest
from fixtures import REPO

BENCH = REPO / "tools" / "bench"
# The scripts that run as programs (geometry_common.py is their shared helper module).
BENCHMARKS = sorted(p for p in BENCH.glob("*.py") if '__name__ == "__main__"' in p.read_text())
LEGO = REPO.parent / "shared" / "datasets" / "lego_200"
# Tiny runs: (script, arguments, a line the output must hold). They run the code paths the figures
# come from (a deferred import or a renamed function fails here, not only at full size).
TINY_RUNS = (
    ("geometry_locate.py", ("--tets", "2000", "--points", "20000", "--repeat", "1"), "numba (CPU kernels):"),
    ("geometry_extract.py", ("--resolution", "48"), "cage: total"),
    ("nerf_field.py", ("--n", "4096", "--repeat", "1"), "ours-torch"),
    ("nerf_train.py", ("--data", str(LEGO), "--seconds", "3", "--at", "3", "--downscale", "8"), '"psnr"'),
    (
        "hash_kernels.py",
        (
            "--old-tree",
            str(REPO),
            "--data",
            str(LEGO),
            "--downscale",
            "8",
            "--warm",
            "2",
            "--steps",
            "1",
            "--repeats",
            "1",
        ),
        "same values: True",
    ),
)


def _run(path, *args):
    return subprocess.run([sys.executable, str(path), *args], cwd=REPO, capture_output=True, text=True, timeout=600)


def test_the_benchmarks_are_found():
    assert len(BENCHMARKS) >= 20 and BENCH / "nerf_train.py" in BENCHMARKS
    assert not list((REPO / "tools").glob("bench_*.py")), "benchmarks live in tools/bench/"


@pytest.mark.parametrize("path", BENCHMARKS, ids=lambda p: p.name)
def test_a_benchmark_starts_and_answers_help(path, _answers):
    proc = _answers[(path.name, ("--help",))]
    assert proc.returncode == 0 and "usage:" in proc.stdout, f"{path.name}: {(proc.stderr or proc.stdout)[-2000:]}"


@pytest.mark.parametrize("script,args,expected", TINY_RUNS, ids=[t[0] for t in TINY_RUNS])
def test_a_benchmark_runs_tiny(script, args, expected, _answers):
    proc = _answers[(script, args)]
    assert proc.returncode == 0 and expected in proc.stdout, f"{script}: {(proc.stderr or proc.stdout)[-2000:]}"


@pytest.fixture(scope="module")
def _answers():
    runs = [(p.name, ("--help",)) for p in BENCHMARKS] + [(script, args) for script, args, _ in TINY_RUNS]
    # Two at a time: most of each is importing torch and the engine.
    with ThreadPoolExecutor(2) as pool:
        return dict(zip(runs, pool.map(lambda run: _run(BENCH / run[0], *run[1]), runs)))
