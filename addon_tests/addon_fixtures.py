"""Session fixtures for the add-on's tests: a small trained NeRF, made once per session.

The NeRF is trained by the engine's own command line on the analytic sphere
dataset of nerf_fixtures (no Blender, no ../shared), for 300 steps (about 30 s
on 2 cores): enough for a density with a surface to extract (peak density
~150), while the render tests compare Blender's output with the engine's on
the same checkpoint.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from nerf_fixtures import write_sphere_dataset

REPO = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="session")
def sphere_nerf(tmp_path_factory):
    """(checkpoint path, dataset folder) of a NeRF trained briefly on the analytic sphere."""
    root = tmp_path_factory.mktemp("sphere_nerf")
    data = write_sphere_dataset(root / "data", n_views=16, size=32)
    run = root / "run"
    proc = subprocess.run(
        [sys.executable, "-m", "blender_nerf_deform.engine", "train", "--data", str(data), "--out", str(run),
         "--steps", "300", "--device", "cpu"],
        cwd=REPO, capture_output=True, text=True,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    return run / "nerf.ckpt", data
