"""Live preview: the extracted mesh follows the deformation of the cage.

The surface mesh is embedded in the rest cage (a tet and 4 weights per
vertex, stored in the .blend), so its deformed shape is a sparse linear map of
the deformed cage vertices. The result goes into a shape key, "NeRF Deform",
so the mesh's own vertices stay the rest shape (selections, re-embedding and
new handles are made on it) while the viewport shows the deformed shape.

Cage Modifiers mode needs no worker: the cage object's evaluated vertices
(after its Armature, Lattice, ... modifiers) are the deformed cage. ARAP and
affine-region modes ask the worker to solve for the handles' poses, without
waiting: a request carries only the handle transforms (the cage, embedding and
regions are in the worker's session), the answer is the deformed surface
itself and updates the mesh when it arrives, and while a solve runs only the
newest pose waits behind it. The handler runs after every depsgraph
update and frame change, is guarded against re-entrancy (writing the shape key
triggers another update), and skips NeRFs whose pose did not change.

While a render job runs, its frame changes ask the worker for no preview
solves: the render engine solves each frame itself on the same worker, and a
blocking (`blender -b`) render never collects an answer anyway. Cage Modifiers
previews, computed on the spot, keep following the frames.
"""

from __future__ import annotations

import bpy

import numpy as np

from ...engine.geometry.embedding import Embedding
from ..data.cage_store import CageDataError, deformed_cage_in_nerf_frame, has_cage, load_cage, load_embedding
from ..data.guards import say_once
from ..data.properties import PREVIEW_KEY, Role, add_app_handlers, remove_app_handlers, settings
from ..worker import jobs
from ..worker.client import WorkerError
from .poses import AsyncSolver, handle_pose

_updating = False
_rendering = False  # between render_init and render_complete / render_cancel
_last_pose: dict[str, bytes] = {}
_solvers: dict[str, AsyncSolver] = {}
_said: set[str] = set()


def _say(message: str) -> None:
    """Print a preview's problem once until it changes (the handler runs on every update)."""
    if message not in _said:
        _said.add(message)
        print(message)


def surface_embedding(surface: bpy.types.Object, tets: np.ndarray) -> Embedding:
    tet_ids, weights = load_embedding(surface.data, len(tets))
    return Embedding(tet_ids=tet_ids, corners=tets[tet_ids], weights=weights, n_outside=0)


def show_deformed(surface: bpy.types.Object, positions: np.ndarray) -> None:
    """Put `positions` (the surface's vertices, its local frame) in the preview shape key."""
    if surface.data.shape_keys is None:
        surface.shape_key_add(name="Basis", from_mix=False)
    key = surface.data.shape_keys.key_blocks.get(PREVIEW_KEY) or surface.shape_key_add(name=PREVIEW_KEY, from_mix=False)
    key.value = 1.0
    # `points` (Blender 4.1+) takes the array in one copy; `data` goes point by point, many times
    # slower on a large mesh. Tagging is enough for the depsgraph to re-evaluate the mesh; a full
    # `update()` would also rebuild its derived data here.
    points = getattr(key, "points", None) or key.data
    points.foreach_set("co", np.ascontiguousarray(positions, dtype=np.float32).ravel())
    surface.data.update_tag()


def hide_deformed(surface: bpy.types.Object) -> None:
    """Drop the preview shape key: the mesh shows its rest shape."""
    keys = surface.data.shape_keys
    if keys is not None and (key := keys.key_blocks.get(PREVIEW_KEY)) is not None:
        surface.shape_key_remove(key)


def preview_positions(nerf: bpy.types.Object, depsgraph) -> np.ndarray | None:
    """Deformed surface of `nerf` in Cage Modifiers mode (None in the modes the worker solves)."""
    s = settings(nerf)
    if s.deformation_mode != "MODIFIERS":
        return None
    cage, surface = s.cage, s.surface
    _rest, tets = load_cage(cage.data)
    deformed = deformed_cage_in_nerf_frame(nerf, cage, depsgraph)
    return surface_embedding(surface, tets).apply(deformed)


def _solve_in_background(nerf: bpy.types.Object, depsgraph) -> None:
    """Send the handles' pose to the worker when it changed; the deformed surface it answers is the preview."""
    request = handle_pose(nerf, depsgraph)
    if request is None:  # the last handle was removed: the surface is back at rest
        if _last_pose.pop(nerf.name, None) is not None:
            hide_deformed(settings(nerf).surface)
        return
    pose, shared = request
    state = repr((pose.params(), sorted((slot, key) for slot, (key, _load) in shared.items()))).encode()
    if _last_pose.get(nerf.name) == state:
        return
    _last_pose[nerf.name] = state
    name = nerf.name
    solver = _solvers.get(name)
    if solver is None:

        def show(result, surface_positions, name=name):
            target = bpy.data.objects.get(name)
            if target is not None and _previewable(target):
                surface = settings(target).surface
                if len(surface_positions) == len(surface.data.vertices):
                    show_deformed(surface, surface_positions)

        solver = _solvers[name] = AsyncSolver(jobs.worker(bpy.context), show)
    solver.request(pose, shared)


def _previewable(nerf: bpy.types.Object) -> bool:
    s = settings(nerf)
    return (
        s.cage is not None
        and s.surface is not None
        and has_cage(s.cage.data)
        and s.surface.mode != "EDIT"  # the artist is editing selections on the rest shape
    )


def update_all(depsgraph) -> None:
    """Refresh every NeRF's preview whose deformed cage changed."""
    global _updating
    if _updating:
        return
    _updating = True
    try:
        for nerf in [o for o in depsgraph.scene.objects if o.nerf_deform.role == Role.NERF]:
            if not _previewable(nerf):
                continue
            try:
                positions = preview_positions(nerf, depsgraph)
                if positions is None:
                    if not _rendering:
                        _solve_in_background(nerf, depsgraph)
                    continue
            except (CageDataError, WorkerError) as error:
                _say(f"NeRF Deform preview of {nerf.name}: {error}")
                continue
            except Exception as error:  # one NeRF's unforeseen error: said once, the others still previewed
                say_once(f"NeRF Deform preview of {nerf.name}", error)
                continue
            pose = positions.astype(np.float32).tobytes()
            if _last_pose.get(nerf.name) == pose:
                continue
            _last_pose[nerf.name] = pose
            show_deformed(settings(nerf).surface, positions)
    finally:
        _updating = False


@bpy.app.handlers.persistent
def _on_depsgraph_update(scene, depsgraph):
    update_all(depsgraph)


@bpy.app.handlers.persistent
def _on_frame_change(scene, depsgraph):
    update_all(depsgraph)


@bpy.app.handlers.persistent
def _on_render_init(*_args):
    global _rendering
    _rendering = True


@bpy.app.handlers.persistent
def _on_render_end(*_args):
    global _rendering
    _rendering = False
    _last_pose.clear()  # the next update shows the pose of the frame the scene is back on


def _handlers():
    h = bpy.app.handlers
    return (
        (h.depsgraph_update_post, _on_depsgraph_update),
        (h.frame_change_post, _on_frame_change),
        (h.render_init, _on_render_init),
        (h.render_complete, _on_render_end),
        (h.render_cancel, _on_render_end),
    )


def register():
    add_app_handlers(_handlers())


def unregister():
    global _rendering
    remove_app_handlers(_handlers())
    _rendering = False
    _last_pose.clear()
    _said.clear()
    _solvers.clear()
