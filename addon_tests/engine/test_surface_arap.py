"""The add-on's ARAP pose (engine/geometry/surface_arap.py): handles pull the embedded surface, no tet
ever inverts. A bend that folds ARAP with handles pinned to cage vertices comes out flip-free with the
handles' surface close to its targets; the result depends on the frame's pose alone and is
continuous in it; a reflection is named, not folded."""

from __future__ import annotations

import numpy as np
import pytest
from fixtures import bar_handles

from blender_nerf_deform.engine.errors import EngineError
from blender_nerf_deform.engine.geometry.barycentric import inversion_report
from blender_nerf_deform.engine.geometry.deform import ArapDeformer, regions_to_cage
from blender_nerf_deform.engine.geometry.handle_pose import RegionDeformer
from blender_nerf_deform.engine.geometry.surface_arap import SurfaceArap


@pytest.fixture(scope="module")
def bar():
    """A bar's surface in a box cage of 4x4x16 cells; regions of the surface: the base (pinned), the
    middle and the tip (two handles), 0.05 apart along the bar."""
    return bar_handles.bar((4, 4, 16))


_bend = bar_handles.bend


def test_a_bend_that_folds_pinned_cage_vertices_stays_flip_free_with_the_surface_on_its_handles(bar):
    V, T, points, embedding, regions = bar
    pose = _bend(points, regions, 60)  # two adjacent handles turned 120 degrees apart, the base pinned
    middle, tip, base = regions_to_cage(embedding, [regions["middle"], regions["tip"], regions["base"]], len(V))
    hard = ArapDeformer(V, T, handles=[middle, tip], pins=[base]).solve(pose, max_iter=200)
    assert inversion_report(V, hard.vertices, T).n_inverted >= 10  # the old way folds: the test can fail

    solver = SurfaceArap(V, T, embedding, [regions["middle"], regions["tip"]], regions["base"])
    result = solver.solve(pose)
    report = inversion_report(V, result.vertices, T)
    assert report.n_inverted == 0 and report.n_degenerate == 0 and result.min_det > 0.01, report.summary()
    assert result.converged and result.barrier_tets > 0  # the barrier did shape this pose
    # Each handle's surface follows its affine to within 2 % of the region's size (the cage has about
    # 3 tets across the gap between the two regions), and the pinned base stays.
    surface = embedding.apply(result.vertices)
    for name, A in zip(("middle", "tip"), pose):
        r = regions[name]
        size = np.linalg.norm(np.ptp(points[r], axis=0))
        off = np.linalg.norm(surface[r] - (points[r] @ A[:3, :3].T + A[:3, 3]), axis=1).max() / size
        assert off < 0.02, (name, off)
    assert np.linalg.norm(surface[regions["base"]] - points[regions["base"]], axis=1).max() < 0.002
    assert result.surface_residual < 0.02


def test_a_pose_depends_on_its_transforms_alone(bar):
    V, T, points, embedding, regions = bar
    solver = SurfaceArap(V, T, embedding, [regions["middle"], regions["tip"]], regions["base"])
    pose = _bend(points, regions, 50)
    first = solver.solve(pose).vertices
    solver.solve(_bend(points, regions, 10))  # another frame in between (render order, a farm's split)
    assert np.array_equal(solver.solve(pose).vertices, first)
    fresh = SurfaceArap(V, T, embedding, [regions["middle"], regions["tip"]], regions["base"])
    assert np.array_equal(fresh.solve(pose).vertices, first)


def test_the_pose_is_continuous_across_the_angle_where_the_barrier_switches_on(bar):
    V, T, points, embedding, regions = bar
    solver = SurfaceArap(V, T, embedding, [regions["middle"], regions["tip"]], regions["base"])
    results, active = [], []
    for degrees in np.linspace(8, 20, 7):
        r = solver.solve(_bend(points, regions, degrees))
        assert inversion_report(V, r.vertices, T).n_inverted == 0
        results.append(r.vertices)
        active.append(r.barrier_tets)
    assert active[0] == 0 and active[-1] > 0, active  # the sweep crosses where the barrier starts to act
    diag = np.linalg.norm(np.ptp(V, axis=0))
    jumps = [np.abs(b - a).max() / diag for a, b in zip(results, results[1:])]
    assert max(jumps) < 2.5 * np.median(jumps), jumps


def test_a_rigid_motion_of_every_region_is_followed_exactly(bar):
    V, T, points, embedding, regions = bar
    every = np.arange(len(points))
    A = bar_handles.turn_x(35, np.array([0.1, -0.2, 0.3]))
    A[:3, 3] += [0.2, 0.0, -0.1]
    result = SurfaceArap(V, T, embedding, [every]).solve([A])
    assert np.allclose(result.vertices, V @ A[:3, :3].T + A[:3, 3], atol=1e-9)
    assert result.surface_residual < 1e-9 and result.iterations <= 2


def test_a_reflected_handle_is_named_and_nothing_folds(bar):
    V, T, points, embedding, regions = bar
    mirror = np.diag([1.0, -1.0, 1.0, 1.0])  # a handle scaled by -1 along y
    deformer = RegionDeformer(V, T, embedding, [regions["tip"]], regions["base"], names=["Tip"])
    posed, stats = deformer.solve([mirror])
    assert stats["reflected_handles"] == ["Tip"]
    assert inversion_report(V, posed, T).n_inverted == 0 and stats["min_det_f"] > 0


def test_the_fused_local_step_matches_the_jacobi_kernels(bar):
    """surface_arap_kernels.surface_local (rotations from Horn's matrix by Newton on its characteristic
    polynomial) gives ARAP's local step of deform.ElementsEnergy (cyclic Jacobi) and det F, to round-off:
    on a rigid turn, a random jiggle, and a squash to a line, a plane and a point (where the
    top eigenvalue repeats and the kernel falls back on Jacobi's sweeps)."""
    from blender_nerf_deform.engine.geometry.barycentric import signed_volumes
    from blender_nerf_deform.engine.geometry.deform import ElementsEnergy
    from blender_nerf_deform.engine.geometry.surface_arap_kernels import surface_local

    V, T = bar[0], bar[1]
    elements, vol0 = ElementsEnergy(V, T), signed_volumes(V, T)
    rng = np.random.default_rng(7)
    turn = bar_handles.turn_x(170, V.mean(0))
    for U in (
        V @ turn[:3, :3].T + turn[:3, 3],
        V + 0.05 * rng.standard_normal(V.shape),
        V * [1.0, 0.0, 0.0],
        V * [1.0, 1.0, 0.0],
        0.0 * V,
        V * [1.0, -1.0, 1.0],
    ):
        U = np.ascontiguousarray(U)
        B, J = np.empty_like(U), np.empty(len(T))
        energy = surface_local(U, T, elements.W, elements.E, 1.0 / (6.0 * vol0), B, J)
        expected = elements.local(U)
        assert np.abs(B - expected).max() <= 1e-12 * np.abs(expected).max()
        assert abs(energy - elements.tet_energy.sum()) <= 1e-12 * max(1.0, elements.tet_energy.sum())
        assert np.allclose(J, signed_volumes(U, T) / vol0, rtol=0, atol=1e-12)


def test_bad_regions_are_refused_with_one_line(bar):
    V, T, points, embedding, regions = bar
    with pytest.raises(EngineError, match="overlap"):
        SurfaceArap(V, T, embedding, [regions["tip"], regions["tip"][:5]])
    with pytest.raises(EngineError, match="has no vertices"):
        SurfaceArap(V, T, embedding, [np.zeros(0, dtype=np.int64)])
    with pytest.raises(EngineError, match="handle transforms"):
        SurfaceArap(V, T, embedding, [regions["tip"]]).solve([])
