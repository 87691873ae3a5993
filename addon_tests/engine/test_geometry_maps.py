"""Barycentric maps, inversion detection, point location and the surface embedding, on real small cages."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from blender_nerf_deform.engine.errors import EngineError
from blender_nerf_deform.engine.geometry.barycentric import (
    deformed_to_rest_affines,
    inversion_report,
    signed_volumes,
    tet_inverses,
    tet_matrices,
)
from blender_nerf_deform.engine.geometry.cage import boundary_faces, box_cage


def barycentric(points, tet_ids, inverses):
    """Reference: (N, 4) barycentric coordinates of each point in its tet, from every tet's T⁻¹."""
    Ti = inverses[np.asarray(tet_ids)]
    return np.einsum("nij,nj->ni", Ti[:, :, :3], np.asarray(points, dtype=np.float64)) + Ti[:, :, 3]


def map_points(points, tet_ids, affines):
    """Reference: each point through its tet's affine."""
    A = affines[np.asarray(tet_ids)]
    return np.einsum("nij,nj->ni", A[:, :3, :3], np.asarray(points, dtype=np.float64)) + A[:, :3, 3]


def _jittered_box(n=5, seed=0):
    V, T = box_cage((n, n, n), (-1, -1, -1), (1, 1, 1))
    rng = np.random.default_rng(seed)
    inner = np.all(np.abs(V) < 0.999, axis=1)
    V = V.copy()
    V[inner] += rng.uniform(-0.12, 0.12, (inner.sum(), 3)) * (2 / n)
    assert (signed_volumes(V, T) > 0).all()
    return V, T


def _random_affine(seed=1):
    rng = np.random.default_rng(seed)
    Q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    if np.linalg.det(Q) < 0:
        Q[:, 0] *= -1
    A = np.eye(4)
    A[:3, :3] = Q @ np.diag([1.3, 0.7, 1.1])
    A[:3, 3] = [0.3, -0.2, 0.5]
    return A


def test_box_cage_is_positively_oriented_and_fills_the_box():
    V, T = box_cage((3, 4, 5), (0, 0, 0), (3, 4, 5))
    vol = signed_volumes(V, T)
    assert (vol > 0).all() and np.isclose(vol.sum(), 60.0)
    # A closed surface: the boundary has 2 triangles per boundary cell face.
    assert len(boundary_faces(T)) == 2 * 2 * (3 * 4 + 4 * 5 + 3 * 5)


def test_T_inverse_is_the_inverse_and_barycentric_reproduces_points():
    V, T = _jittered_box()
    M, Minv = tet_matrices(V, T), tet_inverses(V, T)
    assert np.allclose(M @ Minv, np.eye(4), atol=1e-10)
    rng = np.random.default_rng(3)
    lam = rng.dirichlet(np.ones(4), size=len(T))
    pts = np.einsum("mij,mj->mi", M[:, :3], lam)
    assert np.allclose(barycentric(pts, np.arange(len(T)), Minv), lam, atol=1e-10)


def test_identity_deformation_maps_every_point_to_itself():
    V, T = _jittered_box()
    A = deformed_to_rest_affines(V, V.copy(), T)
    rng = np.random.default_rng(4)
    ids = rng.integers(0, len(T), 5000)
    lam = rng.dirichlet(np.ones(4), size=len(ids))
    pts = np.einsum("nij,nj->ni", V[T[ids]].transpose(0, 2, 1), lam)
    assert np.allclose(map_points(pts, ids, A), pts, atol=1e-12)
    assert inversion_report(V, V, T).ok


def test_affine_deformation_of_the_whole_cage_maps_points_exactly():
    V, T = _jittered_box()
    A = _random_affine()
    Vd = V @ A[:3, :3].T + A[:3, 3]
    D2R = deformed_to_rest_affines(V, Vd, T)
    # Every tet's deformed->rest affine is the inverse of A.
    assert np.allclose(D2R, np.linalg.inv(A)[None], atol=1e-10)
    rng = np.random.default_rng(5)
    ids = rng.integers(0, len(T), 2000)
    lam = rng.dirichlet(np.ones(4), size=len(ids))
    rest_pts = np.einsum("nij,nj->ni", V[T[ids]].transpose(0, 2, 1), lam)
    deformed_pts = rest_pts @ A[:3, :3].T + A[:3, 3]
    assert np.allclose(map_points(deformed_pts, ids, D2R), rest_pts, atol=1e-10)


def test_points_on_shared_faces_map_consistently_under_a_nonlinear_deformation():
    V, T = _jittered_box(4)
    Vd = V + 0.2 * np.sin(2.0 * V[:, [1, 2, 0]])  # a smooth non-affine bend
    D2R = deformed_to_rest_affines(V, Vd, T)
    f = np.concatenate([T[:, [1, 2, 3]], T[:, [0, 2, 3]], T[:, [0, 1, 3]], T[:, [0, 1, 2]]])
    owner = np.tile(np.arange(len(T)), 4)
    key = np.sort(f, axis=1)
    order = np.lexsort(key.T[::-1])
    key, owner, f = key[order], owner[order], f[order]
    shared = np.flatnonzero(np.all(key[1:] == key[:-1], axis=1))
    assert len(shared) > 100
    rng = np.random.default_rng(6)
    w = rng.dirichlet(np.ones(3), size=len(shared))
    p = np.einsum("nij,ni->nj", Vd[f[shared]], w)  # a point on each shared face, in deformed space
    a = map_points(p, owner[shared], D2R)
    b = map_points(p, owner[shared + 1], D2R)
    assert np.allclose(a, b, atol=1e-10)
    assert np.allclose(a, np.einsum("nij,ni->nj", V[f[shared]], w), atol=1e-10)


def test_inversion_is_detected_on_a_flipped_tet():
    V, T = _jittered_box(3)
    Vd = V.copy()
    t = 17
    a, b, c, d = T[t]
    # Push vertex a through the opposite face (b, c, d): tet t turns inside out.
    centroid = Vd[[b, c, d]].mean(0)
    Vd[a] = centroid + 0.5 * (centroid - Vd[a])
    rep = inversion_report(V, Vd, T)
    assert t in rep.inverted
    assert rep.n_inverted >= 1 and not rep.ok
    # Flatten another tet onto a plane: degenerate.
    Vd2 = V.copy()
    a, b, c, d = T[3]
    Vd2[a] = Vd2[[b, c, d]].mean(0)
    rep2 = inversion_report(V, Vd2, T)
    assert 3 in rep2.degenerate and 3 not in rep2.inverted


def test_bad_cage_arrays_are_rejected():
    V, T = box_cage((1, 1, 1))
    with pytest.raises(EngineError, match="outside"):
        tet_matrices(V, T + 100)
    with pytest.raises(EngineError, match=r"\(N, 3\)"):
        tet_matrices(V[:, :2], T)


# ---------------------------------------------------------------- point location (torch)


def _igl_locate(V, T, Q):
    import igl

    tree = igl.AABB()
    tree.init(V, T)
    return igl.in_element(V, T, Q, tree)


@pytest.mark.parametrize("backend,dtype_name", [("torch", "float64"), ("torch", "float32"), ("numba", "float64")])
def test_point_location_agrees_with_igl_in_element(backend, dtype_name):
    import torch

    from blender_nerf_deform.engine.geometry.locate import TetLocator

    V, T = _jittered_box(8, seed=2)
    # Warp it into a non-convex, non-uniform shape so cells hold tets of many sizes.
    V = V.copy()
    V[:, 2] += 0.5 * V[:, 0] ** 2
    V[:, 0] *= 1.0 + 0.6 * (V[:, 1] + 1) ** 2
    assert (signed_volumes(V, T) > 0).all()
    rng = np.random.default_rng(7)
    lo, hi = V.min(0), V.max(0)
    Q = rng.uniform(lo - 0.05, hi + 0.05, (40000, 3))
    dtype = getattr(torch, dtype_name)
    if backend == "numba":
        pytest.importorskip("numba")
    loc = TetLocator(V, T, dtype=dtype, backend=backend)
    assert loc.backend == backend
    got, bary = loc.locate(Q, return_barycentric=True)
    got, bary = got.numpy(), bary.double().numpy()
    ref = _igl_locate(V, T, Q)
    assert (ref >= 0).sum() > 10000 and (ref < 0).sum() > 1000
    # Identical tet for every point not within a tolerance of a tet boundary.
    Minv = tet_inverses(V, T)
    lam_ref = np.full((len(Q), 4), -1.0)
    lam_ref[ref >= 0] = barycentric(Q[ref >= 0], ref[ref >= 0], Minv)
    tol = 1e-9 if dtype_name == "float64" else 1e-4
    clear = np.where(ref >= 0, lam_ref.min(1) > tol, True)
    # (A point outside is "clear" unless it lies within tol of some tet, which igl's -1 does not tell; check below.)
    differ = np.flatnonzero(got != ref)
    for i in differ:
        # Wherever they differ, both answers are within tolerance of a boundary.
        if ref[i] >= 0:
            assert not clear[i], (i, got[i], ref[i], lam_ref[i])
        if got[i] >= 0:
            assert barycentric(Q[i : i + 1], [got[i]], Minv).min() > -tol
            if ref[i] < 0:
                assert barycentric(Q[i : i + 1], [got[i]], Minv).min() < tol
    assert len(differ) <= 0.001 * len(Q)
    # The barycentric coordinates returned are those of the point in the found tet.
    inside = got >= 0
    assert np.allclose(
        bary[inside], barycentric(Q[inside], got[inside], Minv), atol=1e-4 if dtype_name == "float32" else 1e-9
    )
    # Membership: contains == located.
    assert np.array_equal(loc.contains(Q).numpy(), inside)


@pytest.mark.parametrize("backend", ["torch", "numba"])
def test_point_location_of_points_on_vertices_faces_and_far_away(backend):
    import torch

    from blender_nerf_deform.engine.geometry.locate import TetLocator

    if backend == "numba":
        pytest.importorskip("numba")
    V, T = box_cage((3, 3, 3))
    loc = TetLocator(V, T, dtype=torch.float64, backend=backend)
    # Every cage vertex (on up to 24 tets' corners) is found in a tet that has it as a vertex.
    got = loc.locate(V).numpy()
    assert (got >= 0).all()
    assert all(i in T[t] for i, t in enumerate(got))
    far = np.array([[5.0, 5.0, 5.0], [-0.5, 0.5, 0.5], [0.5, 0.5, 1.0 + 1e-6]])
    assert (loc.locate(far).numpy() == -1).all()


@pytest.mark.parametrize("backend", ["torch", "numba"])
def test_locator_rejects_a_degenerate_cage(backend):
    from blender_nerf_deform.engine.geometry.locate import TetLocator

    if backend == "numba":
        pytest.importorskip("numba")
    V, T = box_cage((2, 2, 2))
    V = V.copy()
    V[:, 2] = 0.0  # flatten: every tet has zero volume
    with pytest.raises(EngineError, match="degenerate cage"):
        TetLocator(V, T, backend=backend)


def test_numba_grid_lists_candidates_best_first_whatever_the_thread_count(tmp_path):
    """Each cell lists its tets best first (the tet nearest to covering the cell's centre), and the
    build is deterministic: the same lists with one thread as with all of them."""
    numba = pytest.importorskip("numba")
    from blender_nerf_deform.engine.geometry.locate_kernels import NumbaGrid

    if numba.config.NUMBA_NUM_THREADS < 2:
        # This process has a one-thread pool (make test's xdist workers run one thread each): the
        # comparison runs in a child process with two.
        import subprocess
        import sys

        env = {**os.environ, "NUMBA_NUM_THREADS": "2"}
        env.pop("PYTEST_XDIST_WORKER_COUNT", None)
        this_test = f"{__file__}::test_numba_grid_lists_candidates_best_first_whatever_the_thread_count"
        proc = subprocess.run(
            [
                sys.executable,
                "-m",
                "pytest",
                "-q",
                "-p",
                "no:cacheprovider",
                "--basetemp",
                str(tmp_path / "child"),
                this_test,
            ],
            env=env,
            cwd=Path(__file__).parent.parent,
            capture_output=True,
            text=True,
            timeout=600,
        )
        assert proc.returncode == 0 and "1 passed" in proc.stdout, proc.stdout[-3000:] + proc.stderr[-2000:]
        return

    V, T = _jittered_box(6, seed=3)
    n_threads = numba.get_num_threads()
    grids = []
    for threads in sorted({1, n_threads}):
        numba.set_num_threads(threads)
        try:
            grids.append(NumbaGrid(V, T, cells_per_tet=2.0, eps=1e-10, max_res=64))
        finally:
            numba.set_num_threads(n_threads)
    for g in grids[1:]:
        assert np.array_equal(g.cell_start, grids[0].cell_start) and np.array_equal(g.cell_tets, grids[0].cell_tets)
    g = grids[0]
    # Cell centres that lie inside the cage are found in the first tet of their cell's list.
    res = g.res
    ijk = np.stack(np.meshgrid(*[np.arange(r) for r in res], indexing="ij"), -1).reshape(-1, 3)
    centres = g.glo + (ijk + 0.5) / g.inv
    cells = (ijk[:, 2] * res[1] + ijk[:, 1]) * res[0] + ijk[:, 0]
    located, _ = g.query(centres, want_bary=False)
    inside = located >= 0
    assert inside.any()
    Minv = tet_inverses(V, T)
    first = g.cell_tets[g.cell_start[cells[inside]]]
    assert (barycentric(centres[inside], first, Minv).min(1) > -1e-9).all()


# Five tets filling the unit cube, deliberately with mixed orientations (also the add-on's cage-store test's).
CUBE = np.array([[x, y, z] for z in (0, 1) for y in (0, 1) for x in (0, 1)], dtype=np.float64)
CUBE_TETS = np.array([[0, 1, 2, 4], [3, 2, 1, 7], [5, 1, 7, 4], [6, 2, 4, 7], [1, 2, 4, 7]])


def _enclosed_volume(vertices, faces):
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    return np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0


def test_boundary_of_a_tetrahedralized_cube_is_its_12_outward_triangles():
    faces = boundary_faces(CUBE_TETS, CUBE)
    assert len(faces) == 12
    assert _enclosed_volume(CUBE, faces) == pytest.approx(1.0)  # outward winding gives +volume
    # No interior face: every boundary triangle lies on a face of the cube.
    on_face = [(np.ptp(CUBE[f], axis=0) == 0).any() for f in faces]
    assert all(on_face)
