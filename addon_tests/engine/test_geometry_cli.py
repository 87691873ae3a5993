"""`extract` and `cage` end to end on a NeRF trained briefly on the analytic sphere (radius 0.8)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from fixtures import REPO
from fixtures.sphere_data import RADIUS, write_sphere_dataset


def _cli(*args, check=True):
    proc = subprocess.run(
        [sys.executable, "-m", "blender_nerf_deform.engine", *map(str, args)], cwd=REPO, capture_output=True, text=True
    )
    if check:
        assert proc.returncode == 0, proc.stderr[-3000:]
    return proc


@pytest.fixture(scope="module")
def trained_sphere(tmp_path_factory):
    root = tmp_path_factory.mktemp("geometry_sphere")
    data = write_sphere_dataset(root / "data", n_views=24, size=48)
    _cli("train", "--data", data, "--out", root / "run", "--steps", "200", "--device", "cpu")
    return root / "run" / "nerf.ckpt", root


@pytest.mark.slow
def test_extract_and_cage_a_briefly_trained_nerf(trained_sphere):
    from blender_nerf_deform.engine.geometry.embedding import locate
    from blender_nerf_deform.engine.geometry.mesh_io import load_cage, read_ply

    ckpt, root = trained_sphere
    mesh = root / "sphere.ply"
    # After 200 steps the density at the surface is still low (a few units): threshold 1.
    # (The default 10 suits a trained NeRF: the lego after 150 s, BENCHMARKS.md.)
    proc = _cli("extract", "--nerf", ckpt, "--out", mesh, "--resolution", "96", "--threshold", "1")
    assert "kept 1 component(s)" in proc.stdout, proc.stdout
    v, f, c = read_ply(mesh)
    r = np.linalg.norm(v, axis=1)
    # The object is found: the surface is the sphere, within a few grid steps (3/96 = 0.03),
    # and the floaters of brief training are gone (nothing far from the sphere). Trainings before the
    # seed was fixed left bumps up to 0.13 above the surface, never a floater (which sits in empty
    # space, 0.3 and more away), so 0.2 separates the two.
    assert abs(np.median(r) - RADIUS) < 0.06, np.median(r)
    assert np.percentile(r, 2) > RADIUS - 0.15 and r.max() < RADIUS + 0.2, (np.percentile(r, 2), r.max())
    assert c is not None and c.shape == v.shape
    # Colours are 0.5 + 0.5 * normal: more blue on the +z cap than on the -z cap, more red on +x than -x.
    c = c.astype(float)
    assert c[v[:, 2] > 0.6, 2].mean() > c[v[:, 2] < -0.6, 2].mean() + 60
    assert c[v[:, 0] > 0.6, 0].mean() > c[v[:, 0] < -0.6, 0].mean() + 60

    cage_path = root / "cage.npz"
    proc = _cli("cage", "--nerf", ckpt, "--mesh", mesh, "--out", cage_path, "--margin", "0.08", "--threshold", "1")
    cage = load_cage(cage_path)
    assert cage["vertices"].dtype == np.float64 and cage["tets"].shape[1] == 4
    tid, _ = locate(v, cage["vertices"], cage["tets"])
    assert (tid >= 0).all()
    assert float(np.load(cage_path)["clearance"]) >= 0.08


@pytest.mark.slow
def test_extract_and_cage_cli_errors(trained_sphere, tmp_path):
    ckpt, root = trained_sphere
    out = tmp_path / "m.ply"
    proc = _cli("extract", "--nerf", ckpt, "--out", out, "--resolution", "32", "--threshold", "1e9", check=False)
    assert proc.returncode == 2 and "density grid is empty" in proc.stderr and not out.exists()
    proc = _cli(
        "extract",
        "--nerf",
        ckpt,
        "--out",
        out,
        "--resolution",
        "48",
        "--threshold",
        "1",
        "--min-volume",
        "100",
        check=False,
    )
    assert (
        proc.returncode == 2 and "no component left above the volume threshold 100" in proc.stderr and not out.exists()
    )
    bad = tmp_path / "open.ply"
    from blender_nerf_deform.engine.geometry.mesh_io import write_ply

    write_ply(bad, np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0.0]]), np.array([[0, 1, 2]]))
    cage = tmp_path / "c.npz"
    proc = _cli("cage", "--nerf", ckpt, "--mesh", bad, "--out", cage, check=False)
    assert proc.returncode == 2 and "is open" in proc.stderr and not cage.exists()
    assert list(tmp_path.iterdir()) == [bad]  # nothing half-written
