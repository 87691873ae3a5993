"""Every benchmark in tools/ still starts: its imports resolve and `--help` answers. A function a
benchmark uses that a change removes breaks this test, not the next person's figure (BENCHMARKS.md
names these scripts in its commands)."""

from __future__ import annotations

import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor

import pytest

from fixtures import REPO

# Benchmarks are the tools/bench_*.py scripts that run as programs (bench_geometry_common.py is
# their shared helper module).
BENCHMARKS = sorted(p for p in (REPO / "tools").glob("bench_*.py") if '__name__ == "__main__"' in p.read_text())


def _help(path):
    return subprocess.run([sys.executable, str(path), "--help"], cwd=REPO, capture_output=True, text=True, timeout=300)


def test_the_benchmarks_are_found():
    assert len(BENCHMARKS) >= 20 and REPO / "tools" / "bench_nerf_train.py" in BENCHMARKS


@pytest.mark.parametrize("path", BENCHMARKS, ids=lambda p: p.name)
def test_a_benchmark_starts_and_answers_help(path, _help_answers):
    proc = _help_answers[path]
    assert proc.returncode == 0 and "usage:" in proc.stdout, f"{path.name}: {(proc.stderr or proc.stdout)[-2000:]}"


@pytest.fixture(scope="module")
def _help_answers():
    # Two at a time: most of each is importing torch and the engine.
    with ThreadPoolExecutor(2) as pool:
        return dict(zip(BENCHMARKS, pool.map(_help, BENCHMARKS)))
