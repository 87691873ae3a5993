"""The cage and the surface embedding survive in the .blend exactly, and stale data is refused."""

import subprocess
import sys

import numpy as np
import pytest
from fixtures import REPO

CUBE = np.array([[x, y, z] for z in (0, 1) for y in (0, 1) for x in (0, 1)], dtype=np.float64)
# Five tets filling the unit cube, deliberately with mixed orientations.
CUBE_TETS = np.array([[0, 1, 2, 4], [3, 2, 1, 7], [5, 1, 7, 4], [6, 2, 4, 7], [1, 2, 4, 7]])


def _make_cage(bpy, rng):
    from blender_nerf_deform.addon.data.cage_store import store_cage

    vertices = CUBE * 2.0 - 1.0 + rng.normal(0, 1e-9, CUBE.shape)  # float64 detail float32 would lose
    mesh = bpy.data.meshes.new("Cage")
    store_cage(mesh, vertices, CUBE_TETS)
    obj = bpy.data.objects.new("Cage", mesh)
    bpy.context.scene.collection.objects.link(obj)
    return obj, vertices


_READ_BACK = """
import sys, numpy as np, bpy
sys.path.insert(0, {repo!r})
from blender_nerf_deform.addon.data.cage_store import load_cage, load_embedding
bpy.ops.wm.open_mainfile(filepath={path!r})
rest, tets = load_cage(bpy.data.meshes["Cage"])
tet_ids, weights = load_embedding(bpy.data.meshes["Surface"])
np.savez({out!r}, rest=rest, tets=tets, tet_ids=tet_ids, weights=weights)
"""


def test_cage_and_embedding_round_trip_through_a_saved_blend_in_a_fresh_process(blender, tmp_path):
    bpy = blender
    from blender_nerf_deform.addon.data.cage_store import store_embedding

    rng = np.random.default_rng(0)
    _, vertices = _make_cage(bpy, rng)
    surface = bpy.data.meshes.new("Surface")
    surface.from_pydata(rng.random((6, 3)).tolist(), [], [])
    tet_ids = rng.integers(0, 5, 6)
    weights = rng.dirichlet(np.ones(4), 6)
    store_embedding(surface, tet_ids, weights)
    bpy.data.objects.new("Surface", surface)
    bpy.context.scene.collection.objects.link(bpy.data.objects["Surface"])
    blend = tmp_path / "scene.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))

    out = tmp_path / "read.npz"
    script = _READ_BACK.format(repo=str(REPO), path=str(blend), out=str(out))
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-2000:]
    got = np.load(out)
    assert np.array_equal(got["rest"], vertices)  # bit-exact float64
    assert np.array_equal(got["tets"], CUBE_TETS)
    assert np.array_equal(got["tet_ids"], tet_ids) and np.array_equal(got["weights"], weights)


def test_cage_edited_in_edit_mode_is_refused(blender):
    bpy = blender
    import bmesh

    from blender_nerf_deform.addon.data.cage_store import CageDataError, load_cage

    obj, _ = _make_cage(bpy, np.random.default_rng(1))
    bm = bmesh.new()
    bm.from_mesh(obj.data)
    bm.verts.ensure_lookup_table()
    bmesh.ops.delete(bm, geom=[bm.verts[0]], context="VERTS")
    bm.to_mesh(obj.data)
    bm.free()
    with pytest.raises(CageDataError, match="has 7 vertices but its cage has 8"):
        load_cage(obj.data)


def test_modifiers_on_the_cage_object_drive_its_vertices(blender):
    bpy = blender
    from blender_nerf_deform.addon.data.cage_store import CageDataError, evaluated_cage_vertices

    obj, vertices = _make_cage(bpy, np.random.default_rng(2))
    mod = obj.modifiers.new("Twist", "SIMPLE_DEFORM")
    mod.deform_method, mod.angle = "TWIST", 0.8
    depsgraph = bpy.context.evaluated_depsgraph_get()
    moved = evaluated_cage_vertices(obj, depsgraph)
    assert moved.shape == vertices.shape
    assert np.abs(moved - vertices).max() > 0.1
    obj.modifiers.new("Subdiv", "SUBSURF")
    with pytest.raises(CageDataError, match="change its vertex count"):
        evaluated_cage_vertices(obj, bpy.context.evaluated_depsgraph_get())


def test_embedding_of_a_changed_mesh_is_refused(blender):
    bpy = blender
    from blender_nerf_deform.addon.data.cage_store import CageDataError, load_embedding, store_embedding

    mesh = bpy.data.meshes.new("Surface")
    mesh.from_pydata([(0, 0, 0), (1, 0, 0), (0, 1, 0)], [], [])
    with pytest.raises(CageDataError, match="one tet and 4 weights per vertex"):
        store_embedding(mesh, np.zeros(2, int), np.full((2, 4), 0.25))
    store_embedding(mesh, np.zeros(3, int), np.full((3, 4), 0.25))
    mesh.vertices.add(1)
    with pytest.raises(CageDataError, match="has 4 vertices but was embedded with 3"):
        load_embedding(mesh)


def test_loaded_cage_and_embedding_are_copies_not_views_of_the_id_properties(blender):
    """A numpy view of an ID property reads freed memory once Blender frees it (undo, Build Cage
    again, quitting; Blender then also reports 'Not freed memory blocks' at exit). Loads copy."""
    bpy = blender
    from blender_nerf_deform.addon.data.cage_store import (
        EMBED_WEIGHTS_KEY,
        REST_KEY,
        load_cage,
        load_embedding,
        store_embedding,
    )

    obj, vertices = _make_cage(bpy, np.random.default_rng(1))
    rest, _tets = load_cage(obj.data)
    obj.data[REST_KEY][0] = 123.0  # the stored data changes after the load
    assert rest[0, 0] == vertices[0, 0]

    surface = bpy.data.meshes.new("Surface")
    surface.from_pydata([(0, 0, 0), (1, 0, 0), (0, 1, 0)], [], [])
    store_embedding(surface, np.zeros(3, int), np.full((3, 4), 0.25))
    _ids, weights = load_embedding(surface)
    surface[EMBED_WEIGHTS_KEY][0] = 7.0
    assert weights[0, 0] == 0.25
