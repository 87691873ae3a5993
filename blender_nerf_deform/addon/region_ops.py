"""Edit regions: a box Empty, parented to the NeRF, that limits extraction and the cage.

A real capture never holds the object alone (a statue on a floor, a fox on a
wall). "Add Edit Region" puts a cube Empty around the object; the artist moves,
rotates and scales it with the usual gizmos. Extract Mesh then samples only
inside it (optionally only the part connected to the 3D cursor), closes the
surface where the box cuts the scene and flags that cut, and Build Cage pins
the cage there so the object stays attached to the rest of the scene.

The region the engine gets (REGION.json, engine/geometry/region.py) is the
Empty's box in the NeRF's frame: `nerf.matrix_world⁻¹ @ region.matrix_world`,
decomposed into a centre, an XYZ Euler rotation and a scale. A cube Empty of
display size s and scale k spans ±s·k in its local units, so the box's side
lengths are 2·s·k; new regions get s = 0.5, so their Scale *is* their size.
One region per NeRF for now.
"""

from __future__ import annotations

import json

import bpy
import numpy as np
from mathutils import Matrix, Vector

from .properties import alive, owning_nerf, select_only, to_nerf_frame

REGION_DISPLAY_SIZE = 0.5  # a new region's Scale is its size
# The region a surface was extracted with (JSON of the REGION dict; "" for the whole box), on its
# mesh: Build Cage says when the region has changed since.
SURFACE_REGION_KEY = "nerf_deform_extracted_region"


def nerf_box(nerf: bpy.types.Object) -> tuple[np.ndarray, np.ndarray]:
    """(min, max) of the NeRF's scene box in its own frame; a clear error when it has none."""
    aabb = np.array(nerf.nerf_deform.aabb, dtype=np.float64)
    lo, hi = aabb[:3], aabb[3:]
    if not np.all(hi > lo):
        raise ValueError(f"NeRF object '{nerf.name}' has no scene box (Bounds {aabb.tolist()}): load it with Load NeRF")
    return lo, hi


def region_dict(region: bpy.types.Object, nerf: bpy.types.Object) -> dict:
    """The edit region as the engine takes it (center, size, rotation_euler in the NeRF's frame).

    ValueError naming the region when it has no box: a zero size (scale or display size), or axes
    that are not at right angles in the NeRF's frame (skewed, by a non-uniform scale on a rotated
    parent). A mirrored box (a negative scale) is the same box and is taken as it is."""
    m = np.array(to_nerf_frame(nerf) @ region.matrix_world, dtype=np.float64)
    axes, center = m[:3, :3], m[:3, 3]
    lengths = np.linalg.norm(axes, axis=0)
    size = 2.0 * region.empty_display_size * lengths
    try:
        lo, hi = nerf_box(nerf)
        tiny = 1e-6 * float(np.max(hi - lo))
    except ValueError:
        tiny = 1e-9
    if not np.all(size > tiny):
        raise ValueError(
            f"edit region '{region.name}' has zero size ({' x '.join(f'{x:.3g}' for x in size)} in the NeRF's frame): "
            "give it a non-zero scale and display size"
        )
    rotation = axes / lengths
    if np.linalg.det(rotation) < 0:  # mirrored: flip an axis back, the box is symmetric
        rotation[:, 0] = -rotation[:, 0]
    skew = float(np.abs(rotation.T @ rotation - np.eye(3)).max())
    if skew > 1e-4:
        raise ValueError(
            f"edit region '{region.name}' is skewed (its axes are not at right angles in the NeRF's frame: "
            "a non-uniform scale on a rotated parent); parent it to the NeRF object alone"
        )
    euler = Matrix(rotation.tolist()).to_euler("XYZ")
    return {"center": [float(x) for x in center], "size": [float(x) for x in size],
            "rotation_euler": [float(x) for x in euler]}


def edit_region_of(nerf: bpy.types.Object) -> dict | None:
    """The NeRF's live edit region as a REGION dict, None without one (or once it was deleted);
    ValueError when it has no box (`region_dict`)."""
    region = alive(nerf.nerf_deform.edit_region)
    return None if region is None else region_dict(region, nerf)


def encode_region(region: dict | None) -> str:
    return "" if region is None else json.dumps(region, sort_keys=True)


def same_region(a: dict | None, b: dict | None, tol: float = 1e-6) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return all(np.allclose(a[k], b[k], atol=tol) for k in ("center", "size", "rotation_euler"))


def extracted_region(surface: bpy.types.Object) -> dict | None:
    """The region the surface was extracted with (None: the whole box, or not recorded)."""
    text = surface.data.get(SURFACE_REGION_KEY, "")
    try:
        return json.loads(text) if isinstance(text, str) and text else None
    except json.JSONDecodeError:
        return None


def default_placement(nerf: bpy.types.Object, cursor_world) -> tuple[np.ndarray, np.ndarray, bool]:
    """(centre, size, around_cursor) of a new region in the NeRF's frame: around the 3D cursor,
    a third of the box, when the cursor is in the box; else the whole box."""
    lo, hi = nerf_box(nerf)
    cursor = np.array(to_nerf_frame(nerf) @ Vector(cursor_world), dtype=np.float64)
    if np.all(cursor >= lo) and np.all(cursor <= hi):
        return cursor, (hi - lo) / 3.0, True
    return 0.5 * (lo + hi), hi - lo, False


class NERFDEFORM_OT_add_edit_region(bpy.types.Operator):
    """Add a box that limits extraction and the cage to the object being edited (around the 3D cursor when it is in the NeRF's box); selects the NeRF's region when it has one"""

    bl_idname = "nerf_deform.add_edit_region"
    bl_label = "Add Edit Region"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        if owning_nerf(context.active_object) is None:
            cls.poll_message_set("Select a NeRF object, or its mesh, cage or handles")
            return False
        return True

    def execute(self, context):
        nerf = owning_nerf(context.active_object)
        s = nerf.nerf_deform
        if (existing := alive(s.edit_region)) is not None:
            select_only(context, existing)
            self.report({"INFO"}, f"{nerf.name} already has an edit region, {existing.name}: selected it "
                                  "(one region per NeRF; move, rotate and scale it)")
            return {"FINISHED"}
        try:
            center, size, around_cursor = default_placement(nerf, context.scene.cursor.location)
        except ValueError as error:  # no box, or a NeRF scaled to zero
            self.report({"ERROR"}, f"{self.bl_label}: {error}")
            return {"CANCELLED"}

        region = bpy.data.objects.new(f"{nerf.name} Region", None)
        region.empty_display_type = "CUBE"
        region.empty_display_size = REGION_DISPLAY_SIZE
        region.show_in_front = True  # seen through the extracted mesh
        for collection in nerf.users_collection:
            collection.objects.link(region)
        region.parent = nerf
        region.matrix_parent_inverse = Matrix.Identity(4)  # its local matrix is in the NeRF's frame
        region.location = center.tolist()
        region.scale = (size / (2.0 * REGION_DISPLAY_SIZE)).tolist()
        region.nerf_deform.nerf = nerf
        region.nerf_deform.role = "REGION"
        s.edit_region = region

        select_only(context, region)  # ready for its gizmos
        where = "around the 3D cursor" if around_cursor else "over the NeRF's whole box"
        self.report({"INFO"}, f"{region.name} {where}: move, rotate and scale it around the object, then Extract Mesh")
        return {"FINISHED"}


_classes = (NERFDEFORM_OT_add_edit_region,)
register, unregister = bpy.utils.register_classes_factory(_classes)
