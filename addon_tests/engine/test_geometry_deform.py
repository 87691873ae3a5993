"""Deformers: affine region, ARAP (ours and libigl's) against linear blending, regions mapped from the surface,
bad input."""

from __future__ import annotations

import numpy as np
import pytest

from blender_nerf_deform.engine.errors import EngineError
from blender_nerf_deform.engine.geometry.cage import box_cage
from blender_nerf_deform.engine.geometry.deform import (
    ArapDeformer,
    affine_region,
    edge_length_distortion,
    linear_blend,
    regions_to_cage,
)


def _cube():
    V, T = box_cage((6, 6, 6))
    bottom = np.flatnonzero(np.linalg.norm(V, axis=1) < 0.35)  # around corner (0,0,0)
    top = np.flatnonzero(np.linalg.norm(V - 1, axis=1) < 0.35)  # around corner (1,1,1)
    return V, T, bottom, top


def _translate(t):
    A = np.eye(4)
    A[:3, 3] = t
    return A


def test_affine_region_moves_only_the_region():
    V, T, bottom, top = _cube()
    A = _translate([0.1, 0.2, 0.3])
    A[:3, :3] *= 1.5
    W = affine_region(V, top, A)
    assert np.allclose(W[top], V[top] * 1.5 + [0.1, 0.2, 0.3])
    others = np.setdiff1d(np.arange(len(V)), top)
    assert np.array_equal(W[others], V[others])
    with pytest.raises(EngineError, match="no vertices"):
        affine_region(V, [], A)
    with pytest.raises(EngineError, match="4x4"):
        affine_region(V, top, np.eye(2))


def test_cube_arap_keeps_edge_lengths_far_better_than_linear_blending():
    """The seed's check: bottom corner fixed, top corner pulled."""
    V, T, bottom, top = _cube()
    pull = _translate([0.6, -0.3, 0.4])
    arap = ArapDeformer(V, T, handles=[top], pins=[bottom])
    res = arap.solve([pull], max_iter=100, tol=1e-5)
    assert res.converged and res.iterations > 1
    # Constraints hold exactly.
    assert np.allclose(res.vertices[top], V[top] + [0.6, -0.3, 0.4], atol=1e-9)
    assert np.allclose(res.vertices[bottom], V[bottom], atol=1e-9)
    blended = linear_blend(V, [top, bottom], [pull, np.eye(4)])
    assert np.allclose(blended[top], res.vertices[top]) and np.allclose(blended[bottom], V[bottom])
    e_arap = edge_length_distortion(V, res.vertices, T)
    e_blend = edge_length_distortion(V, blended, T)
    assert e_arap < 0.5 * e_blend, (e_arap, e_blend)
    from blender_nerf_deform.engine.geometry.barycentric import inversion_report

    assert inversion_report(V, res.vertices, T).n_inverted == 0


def test_arap_of_a_rigid_motion_of_all_handles_is_that_motion():
    V, T, bottom, top = _cube()
    c, s = np.cos(0.7), np.sin(0.7)
    A = np.eye(4)
    A[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    A[:3, 3] = [0.2, 0.1, -0.3]
    arap = ArapDeformer(V, T, handles=[top, bottom])
    res = arap.solve([A, A], max_iter=200, tol=1e-7)
    assert np.allclose(res.vertices, V @ A[:3, :3].T + A[:3, 3], atol=1e-4)


def test_arap_reports_non_convergence_without_hanging():
    V, T, bottom, top = _cube()
    c, s = np.cos(2.5), np.sin(2.5)
    A = np.eye(4)
    A[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    arap = ArapDeformer(V, T, handles=[top], pins=[bottom])
    res = arap.solve([A], max_iter=2, tol=1e-9)
    assert res.iterations == 2 and not res.converged and res.last_step > 1e-9
    with pytest.raises(EngineError, match="did not converge in 2 iterations"):
        arap.solve([A], max_iter=2, tol=1e-9, strict=True)
    # The warm-started per-frame step makes progress from the previous result.
    first = arap.step([A]).vertices
    second = arap.step([A]).vertices
    assert not np.allclose(first, second)
    with pytest.raises(EngineError, match="non-finite"):
        arap.solve([np.full((4, 4), np.nan)])


def test_our_arap_converges_to_libigls_deformation():
    """Our local/global iteration (the default) minimises the same energy as libigl's elements ARAP."""
    V, T, bottom, top = _cube()
    c, s = np.cos(0.8), np.sin(0.8)
    A = _translate([0.3, -0.2, 0.5])
    A[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    ours = ArapDeformer(V, T, handles=[top], pins=[bottom])
    assert ours.backend == "numba"
    ref = ArapDeformer(V, T, handles=[top], pins=[bottom], backend="igl")
    a = ours.solve([A], max_iter=2000, tol=1e-9)
    b = ref.solve([A], max_iter=2000, tol=1e-9)
    assert a.converged
    assert np.abs(a.vertices - b.vertices).max() < 1e-4 * ours.diag
    e_ours, e_ref = ours.energy(a.vertices), ours.energy(b.vertices)
    assert e_ours <= e_ref * (1 + 1e-6) + 1e-12, (e_ours, e_ref)
    # One iteration from the same start gives libigl's positions, up to the single-precision
    # 3x3 SVDs libigl fits its rotations with (ours are double: differences ~1e-5 here).
    start = linear_blend(V, [top, bottom], [A, np.eye(4)])
    one_ours = ours.solve([A], max_iter=1, initial=start).vertices
    one_ref = ref.solve([A], max_iter=1, initial=start).vertices
    assert np.abs(one_ours - one_ref).max() < 1e-4
    # The energy is zero at rest and for any rigid motion, positive for a stretch.
    assert ours.energy(V) < 1e-20
    assert ours.energy(V @ A[:3, :3].T + A[:3, 3]) < 1e-20
    assert ours.energy(V * [1.2, 1, 1]) > 1e-3


def test_arap_rejects_a_cage_part_that_no_handle_reaches():
    V1, T1 = box_cage((2, 2, 2))
    V = np.concatenate([V1, V1 + [3, 0, 0]])
    T = np.concatenate([T1, T1 + len(V1)])
    with pytest.raises(EngineError, match="1 connected part"):
        ArapDeformer(V, T, handles=[[0]])
    with pytest.raises(EngineError, match="unknown ARAP backend"):
        ArapDeformer(V1, T1, handles=[[0]], backend="cuda")
    with pytest.raises(EngineError, match="elements energy only"):
        ArapDeformer(V1, T1, handles=[[0]], energy="spokes", backend="numba")
    assert ArapDeformer(V1, T1, handles=[[0]], energy="spokes").backend == "igl"


def test_bad_handle_regions_are_rejected():
    V, T, bottom, top = _cube()
    with pytest.raises(EngineError, match="handle region 1 has no vertices"):
        ArapDeformer(V, T, handles=[top, []], pins=[bottom])
    with pytest.raises(EngineError, match="handle region 0 and pinned region 0 overlap"):
        ArapDeformer(V, T, handles=[top], pins=[np.concatenate([bottom, top[:3]])])
    with pytest.raises(EngineError, match="outside"):
        ArapDeformer(V, T, handles=[[len(V) + 5]])
    arap = ArapDeformer(V, T, handles=[top], pins=[bottom])
    with pytest.raises(EngineError, match="1 handle regions but got 2"):
        arap.solve([np.eye(4), np.eye(4)])


def test_regions_chosen_on_the_surface_map_to_cage_vertices():
    from blender_nerf_deform.engine.geometry.embedding import embed_points

    V, T = box_cage((5, 5, 5), (-1, -1, -1), (1, 1, 1))
    rng = np.random.default_rng(0)
    surface = rng.uniform(-0.9, 0.9, (3000, 3))
    emb = embed_points(surface, V, T)
    top = np.flatnonzero(surface[:, 2] > 0.6)
    bottom = np.flatnonzero(surface[:, 2] < -0.6)
    cage_top, cage_bottom = regions_to_cage(emb, [top, bottom], len(V))
    assert len(np.intersect1d(cage_top, cage_bottom)) == 0
    assert V[cage_top, 2].min() >= 0.2 and V[cage_bottom, 2].max() <= -0.2
    # Moving the mapped cage region moves the selected surface points exactly with it.
    moved = affine_region(V, cage_top, _translate([0, 0, 0.5]))
    assert np.allclose(emb.apply(moved)[top], surface[top] + [0, 0, 0.5])
    with pytest.raises(EngineError, match="handle region 0 and handle region 1 overlap"):
        regions_to_cage(emb, [top, np.concatenate([bottom, top[:2]])], len(V))
    with pytest.raises(EngineError, match="handle region 1 has no vertices"):
        regions_to_cage(emb, [top, np.array([], dtype=int)], len(V))
