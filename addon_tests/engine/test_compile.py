"""`compile` fills numba's cache so that the first real train, render, bent render and ARAP solve on a
machine compile nothing: each kernel must have been run with the argument types the real work passes."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest
from fixtures import REPO
from fixtures.room_data import write_room_dataset
from fixtures.sphere_data import write_sphere_dataset

from blender_nerf_deform.engine.geometry.mesh_io import save_cage
from blender_nerf_deform.engine.geometry.warmup import bent_pose, lattice_cage

pytestmark = pytest.mark.slow

# Asked of numba: every kernel loaded from the cache or compiled (and then saved) is reported.
SAVED = "[cache] data saved to"

# The ARAP a handle pose solves (the reference deform.ArapDeformer serves tests and benchmarks: not compiled).
_ARAP = """
import numpy as np
from blender_nerf_deform.engine.geometry.warmup import lattice_cage
v, t = lattice_cage((0, 0, 0), (2.0, 1.0, 3.0), n=5)
A = np.eye(4); A[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]  # a quarter turn
from blender_nerf_deform.engine.geometry.embedding import embed_points
from blender_nerf_deform.engine.geometry.surface_arap import SurfaceArap
p = v[(v[:, 0] > 0.1) & (v[:, 0] < 1.9)] * 0.98 + 0.01
SurfaceArap(v, t, embed_points(p, v, t), [np.flatnonzero(p[:, 2] > 2.5)], np.flatnonzero(p[:, 2] < 0.5)).solve([A])
"""


def _engine(env, *args):
    proc = subprocess.run(
        [sys.executable, "-m", "blender_nerf_deform.engine", *args], cwd=REPO, env=env, capture_output=True, text=True
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc.stdout + proc.stderr


def test_after_compile_the_first_train_render_bend_and_arap_compile_nothing(tmp_path):
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "cache"))
    out = _engine(env, "compile")
    assert "the kernels are compiled" in out
    assert len(list((tmp_path / "cache").rglob("*.nbi"))) >= 20  # every kernel module has its index

    env["NUMBA_DEBUG_CACHE"] = "1"
    logs = {}
    sphere = write_sphere_dataset(tmp_path / "sphere", n_views=4, size=24)
    room = write_room_dataset(tmp_path / "room", n_views=4, size=24)
    for name, data in (("bounded", sphere), ("unbounded", room)):
        logs[f"train {name}"] = _engine(
            env, "train", "--data", str(data), "--out", str(tmp_path / name), "--steps", "20"
        )
        ckpt = str(tmp_path / name / "nerf.ckpt")
        logs[f"render {name}"] = _engine(
            env, "render", "--nerf", ckpt, "--cameras", str(data), "--out", str(tmp_path / f"{name}_frames")
        )
        # A cage of its own (not the compile step's), bent: point location, the pose, the sample map.
        v, t = lattice_cage((-0.7, -0.6, -0.5), (0.6, 0.7, 0.8), n=4)
        save_cage(tmp_path / f"{name}_cage.npz", v, t)
        np.save(tmp_path / f"{name}_pose.npy", bent_pose(v, angle=0.5))
        logs[f"bent render {name}"] = _engine(
            env,
            "render",
            "--nerf",
            ckpt,
            "--cameras",
            str(data),
            "--out",
            str(tmp_path / f"{name}_bent"),
            "--cage",
            str(tmp_path / f"{name}_cage.npz"),
            "--deformed",
            str(tmp_path / f"{name}_pose.npy"),
        )
    proc = subprocess.run([sys.executable, "-c", _ARAP], cwd=REPO, env=env, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-3000:]
    logs["arap"] = proc.stdout + proc.stderr

    assert all("[cache] data loaded from" in log for log in logs.values()), "numba's cache reports are missing"
    compiled = {what: [line for line in log.splitlines() if SAVED in line] for what, log in logs.items()}
    assert not any(compiled.values()), json.dumps({k: v for k, v in compiled.items() if v}, indent=1)
