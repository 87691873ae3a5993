"""Handles: Empties that move regions of the extracted surface, and pinned regions.

A handle's region is a vertex group of the surface mesh (so an artist can see
and edit it with Blender's own tools); the Empty carries the pose. Anything
that moves an Empty moves the region: its gizmos, keyframes, drivers,
constraints, a parent bone. The target transform of a region is the handle's
matrix in the NeRF's frame times the inverse of its rest matrix.
"""

from __future__ import annotations

import bpy  # first: bmesh is importable only once bpy is loaded (the bpy module from PyPI)
from bpy.app.handlers import persistent

import bmesh
import numpy as np
from mathutils import Matrix

from ..data.cage_store import separate_regions
from ..data.mesh_attributes import part_labels
from ..data.properties import (
    PIN_GROUP,
    OnNeRF,
    PlacementError,
    Role,
    add_app_handlers,
    alive,
    handles_of,
    owning_nerf,
    remove_app_handlers,
    select_only,
    to_nerf_frame,
)


def selected_vertices(surface: bpy.types.Object) -> np.ndarray:
    """Indices of the selected vertices of a mesh, in Edit Mode or not."""
    if surface.mode == "EDIT":
        bm = bmesh.from_edit_mesh(surface.data)
        return np.array([v.index for v in bm.verts if v.select], dtype=np.int64)
    flags = np.zeros(len(surface.data.vertices), dtype=bool)
    surface.data.vertices.foreach_get("select", flags)
    return np.flatnonzero(flags)


def group_vertices(surface: bpy.types.Object, group_name: str) -> np.ndarray:
    """Indices of the vertices in a vertex group (any weight > 0), read in Object Mode data."""
    group = surface.vertex_groups.get(group_name)
    if group is None:
        return np.zeros(0, dtype=np.int64)
    gi = group.index
    return np.array(
        [v.index for v in surface.data.vertices if any(g.group == gi and g.weight > 0 for g in v.groups)],
        dtype=np.int64,
    )


# The vertices of each region, cached for renders and previews (reading a vertex group is a
# Python loop over the mesh). Keyed by the mesh's session_uid, never its pointer: a mesh made after
# another was freed (File > New, a re-extracted surface) can reuse its memory and would get the old
# mesh's regions. Vertex groups change in Edit Mode and Weight Paint, through this module's
# operators, by undo and by loading a file: each of those drops the cache.
_region_cache: dict[tuple[int, str, int], np.ndarray] = {}


def forget_regions() -> None:
    _region_cache.clear()


def region_vertices(surface: bpy.types.Object, group_name: str) -> np.ndarray:
    """group_vertices, cached while the surface is in Object Mode."""
    if surface.mode != "OBJECT":
        _region_cache.clear()
        return group_vertices(surface, group_name)
    # The groups' names too: a group renamed (its list in the UI, a script) is not this region any more.
    key = (
        surface.data.session_uid,
        group_name,
        len(surface.data.vertices),
        tuple(g.name for g in surface.vertex_groups),
    )
    if key not in _region_cache:
        _region_cache[key] = group_vertices(surface, group_name)
    return _region_cache[key]


@persistent
def _forget_regions_in_group_editing_modes(_scene, _depsgraph):
    # Every operator in Edit Mode or Weight Paint ends in a depsgraph update, and so does leaving them.
    if bpy.context.mode in ("EDIT_MESH", "PAINT_WEIGHT"):
        _region_cache.clear()


@persistent
def _forget_regions(*_args):
    _region_cache.clear()


def _handlers():
    h = bpy.app.handlers
    return (
        (h.depsgraph_update_post, _forget_regions_in_group_editing_modes),
        (h.load_post, _forget_regions),
        (h.undo_post, _forget_regions),
        (h.redo_post, _forget_regions),
    )


def handle_target(handle: bpy.types.Object, nerf: bpy.types.Object, depsgraph=None, to_nerf=None) -> np.ndarray:
    """4x4 affine (NeRF frame) that takes the handle's region from rest to where the handle is,
    as evaluated in `depsgraph` (a frame being rendered) or as the objects are now. `to_nerf`: the
    NeRF's world -> NeRF frame Matrix as evaluated there, when the caller has it (a frame's pose
    computes it once for all its handles). A NeRF scaled to zero has no frame: PlacementError naming it."""
    # The rest matrix is stored data, read from the handle itself: an evaluated copy may hold an older one
    # (a change of a property group does not re-evaluate the object).
    rest = np.reshape(handle.original.nerf_deform.rest_matrix, (4, 4))
    if depsgraph is not None:
        handle = handle.evaluated_get(depsgraph)
    if to_nerf is None:
        to_nerf = to_nerf_frame(nerf, (nerf.evaluated_get(depsgraph) if depsgraph is not None else nerf).matrix_world)
    if (
        not np.isfinite(rest).all()
        or abs(np.linalg.det(rest[:3, :3])) < 1e-12
        or not np.allclose(rest[3], [0, 0, 0, 1])
    ):
        raise PlacementError(
            f"handle '{handle.name}': its rest matrix (stored when it was made) is damaged "
            f"({'not invertible' if np.isfinite(rest).all() else 'not finite'}: "
            f"{np.round(rest, 6).tolist()}); remove the handle and add it again"
        )
    world = np.array(handle.matrix_world)
    if not np.isfinite(world).all():
        location = ", ".join(f"{x:g}" for x in world[:3, 3])
        raise PlacementError(
            f"handle '{handle.name}' has a non-finite transform (location {location}): give it a "
            "finite location, rotation and scale (its keyframes, drivers or constraints too)"
        )
    return np.array(to_nerf @ handle.matrix_world @ Matrix(rest.tolist()).inverted_safe())


def _surface_of(context) -> tuple[bpy.types.Object | None, bpy.types.Object | None]:
    obj = context.active_object
    if obj is None or obj.type != "MESH" or obj.nerf_deform.role != Role.SURFACE:
        return None, None
    nerf = owning_nerf(obj)
    # The NeRF's extracted mesh itself (a duplicate or a leftover has the role but no handles).
    return (obj, nerf) if nerf is not None and nerf.nerf_deform.surface == obj else (obj, None)


def _overlaps(
    surface: bpy.types.Object, nerf: bpy.types.Object, vertices: np.ndarray, skip_group: str = ""
) -> str | None:
    """Name of a region (handle or pin) that already owns some of `vertices`, if any."""
    regions = [(h.name, h.nerf_deform.region) for h in handles_of(nerf)] + [("the pinned region", PIN_GROUP)]
    for owner, group in regions:
        if group == skip_group:
            continue
        shared = np.intersect1d(vertices, group_vertices(surface, group))
        if len(shared):
            return f"{owner} ({len(shared)} vertices)"
    return None


def _add_to_group(surface: bpy.types.Object, group_name: str, vertices: np.ndarray) -> bpy.types.VertexGroup:
    """Add vertices to a vertex group (created if missing); works from Edit Mode by leaving it briefly."""
    was_edit = surface.mode == "EDIT"
    if was_edit:
        bpy.ops.object.mode_set(mode="OBJECT")
    group = surface.vertex_groups.get(group_name) or surface.vertex_groups.new(name=group_name)
    group.add(vertices.tolist(), 1.0, "REPLACE")
    forget_regions()
    if was_edit:
        bpy.ops.object.mode_set(mode="EDIT")
    return group


def _separate(operator, nerf) -> None:
    """Where the new region and another lean on the same cage vertices, refine the cage there
    (cage_store.separate_regions): a cage vertex cannot follow two handles' transforms."""
    try:
        lines = separate_regions(nerf)
    except ValueError as error:  # a cage or embedding that no longer matches its mesh: said, region kept
        lines = [("WARNING", f"the cage was not refined where the regions meet: {error}")]
    for level, line in lines:
        operator.report({level}, line)


class _SelectionOperator:
    """Operators on the vertices selected in Edit Mode on a NeRF's extracted mesh."""

    bl_options = {"REGISTER", "UNDO"}
    _purpose = ""  # what the selection is for, in the error message

    @classmethod
    def poll(cls, context):
        surface, nerf = _surface_of(context)
        if surface is None or surface.mode != "EDIT":
            cls.poll_message_set("Select vertices of a NeRF's extracted mesh in Edit Mode")
            return False
        if nerf is None:
            cls.poll_message_set(f"{surface.name} is no longer the extracted mesh of a NeRF (its NeRF was deleted?)")
            return False
        return True

    def selection(self, context):
        """(surface, nerf, selected vertex indices), or None after reporting an empty selection."""
        surface, nerf = _surface_of(context)
        vertices = selected_vertices(surface)
        if len(vertices) == 0:
            self.report(
                {"ERROR"},
                f"No vertices selected: select the region to {self._purpose} on the extracted mesh in Edit Mode",
            )
            return None
        return surface, nerf, vertices


class NERFDEFORM_OT_add_handle(_SelectionOperator, bpy.types.Operator):
    """Make a handle (an Empty at their centroid) that moves the selected vertices of the extracted mesh"""

    bl_idname = "nerf_deform.add_handle"
    bl_label = "Add Handle"
    _purpose = "move"

    def execute(self, context):
        if (selection := self.selection(context)) is None:
            return {"CANCELLED"}
        surface, nerf, vertices = selection
        if (other := _overlaps(surface, nerf, vertices)) is not None:
            self.report(
                {"ERROR"}, f"The selection overlaps {other}: deselect those vertices or remove that region first"
            )
            return {"CANCELLED"}

        co = np.empty(3 * len(surface.data.vertices), dtype=np.float32)
        bpy.ops.object.mode_set(mode="OBJECT")  # flush the edit-mode selection and positions
        surface.data.vertices.foreach_get("co", co)
        region = co.reshape(-1, 3)[vertices]
        centroid = region.mean(axis=0)
        extent = float(np.ptp(region, axis=0).max()) if len(region) > 1 else 0.1

        handle = bpy.data.objects.new(f"{nerf.name} Handle", None)
        handle.empty_display_type = "SPHERE"
        handle.empty_display_size = max(0.5 * extent, 0.05)
        for collection in nerf.users_collection:
            collection.objects.link(handle)
        handle.parent = nerf
        handle.matrix_parent_inverse = Matrix.Identity(4)
        handle.location = centroid.tolist()  # surface's local frame is the NeRF's frame

        # A new group even when a handle renamed since took this name's group: regions never merge.
        group_name, n = f"NeRF Handle {handle.name}", 1
        while group_name in surface.vertex_groups:
            group_name, n = f"NeRF Handle {handle.name}.{n:03d}", n + 1
        group = _add_to_group(surface, group_name, vertices)
        s = handle.nerf_deform
        # Parented with an identity inverse, its matrix in the NeRF's frame is its local matrix.
        # Rest first, role last: a depsgraph update in between must not see a handle without its rest.
        s.rest_matrix = [x for row in Matrix.Translation(centroid.tolist()) for x in row]
        s.nerf, s.region = nerf, group.name
        s.role = Role.HANDLE

        select_only(context, handle)  # ready to grab with its gizmos
        self.report({"INFO"}, f"{handle.name} moves {len(vertices)} vertices")
        part = part_labels(surface.data)
        spanned = np.unique(part[vertices]) if part is not None else np.zeros(0)
        if len(spanned) > 1:
            self.report(
                {"WARNING"},
                f"{handle.name}'s vertices span the objects of {len(spanned)} edit regions "
                f"(parts {', '.join(str(int(i) + 1) for i in spanned)}): it moves each of them",
            )
        _separate(self, nerf)
        return {"FINISHED"}


class NERFDEFORM_OT_pin_selection(_SelectionOperator, bpy.types.Operator):
    """Pin the selected vertices of the extracted mesh: they stay where they are"""

    bl_idname = "nerf_deform.pin_selection"
    bl_label = "Pin Selection"
    _purpose = "pin"

    def execute(self, context):
        if (selection := self.selection(context)) is None:
            return {"CANCELLED"}
        surface, nerf, vertices = selection
        if (other := _overlaps(surface, nerf, vertices, skip_group=PIN_GROUP)) is not None:
            self.report({"ERROR"}, f"The selection overlaps {other}: a vertex cannot be both pinned and moved")
            return {"CANCELLED"}
        _add_to_group(surface, PIN_GROUP, vertices)
        self.report({"INFO"}, f"Pinned {len(vertices)} vertices")
        _separate(self, nerf)
        return {"FINISHED"}


class NERFDEFORM_OT_remove_handle(bpy.types.Operator):
    """Remove the active handle and its region"""

    bl_idname = "nerf_deform.remove_handle"
    bl_label = "Remove Handle"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        obj = context.active_object
        if obj is None or obj.nerf_deform.role != Role.HANDLE:
            cls.poll_message_set("Make a handle of a NeRF the active object")
            return False
        return True

    def execute(self, context):
        handle = context.active_object
        nerf = alive(handle.nerf_deform.nerf)
        surface = alive(nerf.nerf_deform.surface) if nerf is not None else None
        if surface is not None and (group := surface.vertex_groups.get(handle.nerf_deform.region)) is not None:
            surface.vertex_groups.remove(group)
            forget_regions()
        name = handle.name
        bpy.data.objects.remove(handle)
        self.report({"INFO"}, f"Removed {name}")
        return {"FINISHED"}


class NERFDEFORM_OT_reset_pose(OnNeRF, bpy.types.Operator):
    """Move every handle of the active NeRF back to where it was made"""

    bl_idname = "nerf_deform.reset_pose"
    bl_label = "Reset Pose"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        nerf = owning_nerf(context.active_object)
        try:
            to_nerf_frame(nerf)  # a NeRF scaled to zero would leave every handle scaled to zero
        except ValueError as error:
            self.report({"ERROR"}, f"{self.bl_label}: {error}")
            return {"CANCELLED"}
        handles = handles_of(nerf, with_regions=False)
        for handle in handles:
            rest = Matrix(np.reshape(handle.nerf_deform.rest_matrix, (4, 4)).tolist())
            handle.matrix_world = nerf.matrix_world @ rest
        self.report({"INFO"}, f"Reset {len(handles)} handles of {nerf.name}")
        return {"FINISHED"}


_classes = (
    NERFDEFORM_OT_add_handle,
    NERFDEFORM_OT_pin_selection,
    NERFDEFORM_OT_remove_handle,
    NERFDEFORM_OT_reset_pose,
)
_register_classes, _unregister_classes = bpy.utils.register_classes_factory(_classes)


def register():
    _register_classes()
    add_app_handlers(_handlers())


def unregister():
    remove_app_handlers(_handlers())
    forget_regions()
    _unregister_classes()
