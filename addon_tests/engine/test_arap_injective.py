"""The flip-free step after ARAP (engine/geometry/injective.py): a pose that ARAP folds comes out with
no inverted tet and the handles on their targets; a pose ARAP gets right is not touched; targets that
force a flip end in bounded time with the count reported."""

from __future__ import annotations

import numpy as np

from blender_nerf_deform.engine.geometry.barycentric import inversion_report
from blender_nerf_deform.engine.geometry.cage import box_cage
from blender_nerf_deform.engine.geometry.deform import ArapDeformer

# Handles within this fraction of the cage's diagonal of their targets (soft constraints; BENCHMARKS).
HANDLE_TOLERANCE = 1e-3


def _slab_pose(V, handle, angle, shift):
    """The handle slab turned by `angle` about its own centre (about +Y) and pushed sideways:
    with the bottom slab pinned, ARAP folds tets near the slabs' edges from about 1 rad on."""
    centre = V[handle].mean(0)
    c, s = np.cos(angle), np.sin(angle)
    R = np.array([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]])
    A = np.eye(4)
    A[:3, :3] = R
    A[:3, 3] = centre - R @ centre + [0.0, shift, 0.0]
    return A


def _cube():
    V, T = box_cage((6, 6, 6))
    pin = np.flatnonzero(V[:, 2] < 0.1)
    top = np.flatnonzero(V[:, 2] > 0.9)
    return V, T, pin, top


def test_a_pose_arap_folds_comes_out_flip_free_with_handles_on_target():
    V, T, pin, top = _cube()
    arap = ArapDeformer(V, T, handles=[top], pins=[pin])
    pose = [_slab_pose(V, top, 1.0, 0.1)]
    plain = arap.solve(pose, max_iter=200, injective=False)
    before = inversion_report(V, plain.vertices, T)
    assert before.n_inverted >= 5, before.summary()  # ARAP alone folds this pose: the test can fail

    res = arap.solve(pose, max_iter=200)
    after = inversion_report(V, res.vertices, T)
    assert after.n_inverted == 0 and after.n_degenerate == 0, after.summary()
    assert after.det.min() > 1e-3
    step = res.injective
    assert step.ran and step.inverted_before == before.n_inverted and step.inverted == 0
    bc = arap.constraints(pose)
    residual = np.linalg.norm(res.vertices[arap.b] - bc, axis=1).max() / arap.diag
    assert residual < HANDLE_TOLERANCE and abs(residual - step.handle_residual) < 1e-12
    # Away from the fold the step keeps ARAP's deformation: most vertices move by little.
    moved = np.linalg.norm(res.vertices - plain.vertices, axis=1) / arap.diag
    assert np.median(moved) < 0.01, np.median(moved)
    # Deterministic, and independent of what was solved before (render order).
    arap.solve([_slab_pose(V, top, 0.3, 0.0)])
    again = arap.solve(pose, max_iter=200)
    assert np.array_equal(again.vertices, res.vertices)


def test_a_pose_arap_gets_right_is_returned_unchanged():
    V, T, pin, top = _cube()
    arap = ArapDeformer(V, T, handles=[top], pins=[pin])
    pose = [_slab_pose(V, top, 0.6, 0.1)]
    plain = arap.solve(pose, max_iter=200, injective=False)
    assert inversion_report(V, plain.vertices, T).det.min() > 0.1  # above the step's threshold
    res = arap.solve(pose, max_iter=200)
    assert np.array_equal(res.vertices, plain.vertices)
    assert not res.injective.ran and res.injective.start == "unchanged"


def test_the_step_is_continuous_in_the_pose():
    """Across the angle where ARAP starts to fold, consecutive poses give nearby results: no jump
    where the step switches on (from ARAP's own result to the projected start)."""
    V, T = box_cage((3, 3, 12), hi=(0.25, 0.25, 1.0))
    pin = np.flatnonzero(V[:, 2] < 0.1)
    top = np.flatnonzero(V[:, 2] > 0.9)
    arap = ArapDeformer(V, T, handles=[top], pins=[pin])
    angles = np.linspace(1.3, 1.6, 7)
    results, folded = [], []
    for a in angles:
        pose = [_slab_pose(V, top, a, 0.1)]
        folded.append(inversion_report(V, arap.solve(pose, max_iter=200, injective=False).vertices, T).n_inverted)
        res = arap.solve(pose, max_iter=200)
        assert inversion_report(V, res.vertices, T).n_inverted == 0
        results.append(res.vertices)
    assert folded[0] == 0 and folded[-1] > 0, folded  # the sweep crosses the fold
    jumps = [np.abs(b - a).max() / arap.diag for a, b in zip(results, results[1:])]
    # Each step of 0.05 rad moves the tip by ~0.05 of the bar's length; no jump stands out.
    assert max(jumps) < 2.5 * np.median(jumps), jumps


def test_targets_that_force_a_flip_end_with_the_count_reported():
    """A handle region whose own affine is a reflection: its own tets must invert. The solve ends
    (bounded iterations), the handles stay on their targets, the remaining count is reported."""
    V, T = box_cage((4, 4, 4))
    pin = np.flatnonzero(V[:, 2] < 0.1)
    top = np.flatnonzero(V[:, 2] > 0.7)  # two layers of vertices: whole tets inside the handle
    mirror = np.diag([1.0, 1.0, -1.0, 1.0])
    mirror[2, 3] = 2 * 0.875  # about the handle's middle
    arap = ArapDeformer(V, T, handles=[top], pins=[pin])
    res = arap.solve([mirror], max_iter=200)
    inside = np.all(np.isin(T, top), axis=1).sum()
    report = inversion_report(V, res.vertices, T)
    assert report.n_inverted >= inside > 0
    assert res.injective.ran and res.injective.inverted == report.n_inverted
    assert res.injective.inverted <= res.injective.inverted_before
    assert np.allclose(res.vertices[top], V[top] @ mirror[:3, :3].T + mirror[:3, 3])
