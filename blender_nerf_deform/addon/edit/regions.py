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

A NeRF may own several regions (two objects of one scene edited separately):
every REGION Empty whose `nerf` is the NeRF, in name order (`regions_of`).
Extract Mesh sends them all; each region's object becomes one *part* of the
one extracted mesh (its INT point attribute "NeRF Part" holds the index of the
region, in that order) and Build Cage gives each part its own cage, in the one
cage object, so a handle on one object moves that object alone. The NeRF's
`edit_region` pointer is the region added last (files saved when a NeRF had
one region set only that pointer: that region counts too).
"""

from __future__ import annotations

import json

import bpy

import numpy as np
from mathutils import Matrix, Vector

from ...engine.geometry.region import region_from_dict
from ..data.properties import OnNeRF, Role, alive, owning_nerf, select_only, to_nerf_frame

REGION_DISPLAY_SIZE = 0.5  # a new region's Scale is its size
# The regions a surface was extracted with (JSON list of REGION dicts, in the order of its parts;
# "" for the whole box; one REGION dict in files of the single-region version), on its mesh:
# Build Cage says when the regions have changed since.
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
    return {
        "center": [float(x) for x in center],
        "size": [float(x) for x in size],
        "rotation_euler": [float(x) for x in euler],
    }


def regions_of(nerf: bpy.types.Object) -> list[bpy.types.Object]:
    """The NeRF's live edit regions in a stable order (by name): every REGION Empty whose `nerf`
    is this NeRF, and the one its `edit_region` pointer names (all a single-region file set)."""
    found = {
        o.name: o
        for o in bpy.data.objects
        if o.nerf_deform.role == Role.REGION and o.nerf_deform.nerf == nerf and alive(o) is not None
    }
    if (pointed := alive(nerf.nerf_deform.edit_region)) is not None:
        found[pointed.name] = pointed
    return [found[name] for name in sorted(found)]


def edit_regions_of(nerf: bpy.types.Object) -> list[dict]:
    """The NeRF's live edit regions as REGION dicts, in `regions_of` order ([]: the whole box);
    ValueError naming a region without a box (`region_dict`)."""
    return [region_dict(region, nerf) for region in regions_of(nerf)]


def edit_region_of(nerf: bpy.types.Object) -> dict | None:
    """The NeRF's active edit region (the one added last, its `edit_region`) as a REGION dict,
    None without one (or once it was deleted); ValueError when it has no box (`region_dict`)."""
    region = alive(nerf.nerf_deform.edit_region)
    return None if region is None else region_dict(region, nerf)


def encode_regions(regions: list[dict]) -> str:
    return json.dumps(list(regions), sort_keys=True) if regions else ""


def same_region(a: dict | None, b: dict | None, tol: float = 1e-6) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return all(np.allclose(a[k], b[k], atol=tol) for k in ("center", "size", "rotation_euler"))


def same_regions(a: list[dict], b: list[dict], tol: float = 1e-6) -> bool:
    return len(a) == len(b) and all(same_region(x, y, tol) for x, y in zip(a, b))


def extracted_regions(surface: bpy.types.Object) -> list[dict]:
    """The regions the surface was extracted with, in the order of its parts ([]: the whole box,
    or not recorded). Reads the single-region form too (one REGION dict)."""
    text = surface.data.get(SURFACE_REGION_KEY, "")
    try:
        value = json.loads(text) if isinstance(text, str) and text else None
    except json.JSONDecodeError:
        return []
    if isinstance(value, dict):
        value = [value]
    if not isinstance(value, list) or not all(isinstance(r, dict) for r in value):
        return []
    return value


def _overlaps(a: dict, b: dict) -> bool:
    return region_from_dict(a).overlaps(region_from_dict(b))


def default_placement(
    nerf: bpy.types.Object, cursor_world, others: list[dict] = ()
) -> tuple[np.ndarray, np.ndarray, str]:
    """(centre, size, where) of a new region in the NeRF's frame: around the 3D cursor, a third of
    the box, when the cursor is in the box; else the whole box, or (when the NeRF has regions
    already, which the whole box would overlap) a third of it at its centre."""
    lo, hi = nerf_box(nerf)
    cursor = np.array(to_nerf_frame(nerf) @ Vector(cursor_world), dtype=np.float64)
    if np.all(cursor >= lo) and np.all(cursor <= hi):
        return cursor, (hi - lo) / 3.0, "around the 3D cursor"
    if others:
        return 0.5 * (lo + hi), (hi - lo) / 3.0, "at the middle of the NeRF's box"
    return 0.5 * (lo + hi), hi - lo, "over the NeRF's whole box"


class NERFDEFORM_OT_add_edit_region(OnNeRF, bpy.types.Operator):
    """Add a box that limits extraction and the cage to an object being edited (around the 3D cursor when it is in the NeRF's box); each region's object gets its own cage"""  # noqa: E501 (the tooltip: one line)

    bl_idname = "nerf_deform.add_edit_region"
    bl_label = "Add Edit Region"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        nerf = owning_nerf(context.active_object)
        s = nerf.nerf_deform
        context.view_layer.update()  # the regions as a script just placed them
        others = []
        for other in regions_of(nerf):
            try:
                others.append((other.name, region_dict(other, nerf)))
            except ValueError:  # a region without a box: Extract Mesh reports it
                pass
        try:
            center, size, where = default_placement(nerf, context.scene.cursor.location, [d for _n, d in others])
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
        region.nerf_deform.role = Role.REGION
        # The pointer moves to the new region: an Empty that only it named (set by a script) stays a region.
        if (pointed := alive(s.edit_region)) is not None and pointed.nerf_deform.role == Role.NONE:
            pointed.nerf_deform.role, pointed.nerf_deform.nerf = Role.REGION, nerf
        s.edit_region = region  # the active one

        select_only(context, region)  # ready for its gizmos
        n = len(regions_of(nerf))
        count = f" ({nerf.name} has {n} edit regions: one cage each)" if n > 1 else ""
        self.report(
            {"INFO"}, f"{region.name} {where}{count}: move, rotate and scale it around the object, then Extract Mesh"
        )
        mine = {"center": center.tolist(), "size": size.tolist(), "rotation_euler": [0.0, 0.0, 0.0]}
        overlapped = [name for name, d in others if _overlaps(mine, d)]
        if overlapped:
            self.report(
                {"WARNING"},
                f"{region.name} overlaps {', '.join(overlapped)}: regions must not overlap, "
                "move it apart before Extract Mesh",
            )
        return {"FINISHED"}


class NERFDEFORM_OT_select_edit_region(bpy.types.Operator):
    """Select this edit region (the only selected and the active object), ready for its gizmos"""

    bl_idname = "nerf_deform.select_edit_region"
    bl_label = "Select Edit Region"
    bl_options = {"REGISTER", "UNDO"}

    name: bpy.props.StringProperty(name="Region", description="Name of the edit region's object")

    def execute(self, context):
        region = bpy.data.objects.get(self.name)
        if region is None or region.nerf_deform.role != Role.REGION or not region.users_collection:
            self.report({"ERROR"}, f"{self.bl_label}: no edit region named '{self.name}'")
            return {"CANCELLED"}
        if context.view_layer.objects.get(region.name) != region:
            self.report(
                {"ERROR"}, f"{self.bl_label}: {region.name} is not in this view layer (an excluded collection?)"
            )
            return {"CANCELLED"}
        select_only(context, region)
        return {"FINISHED"}


_classes = (NERFDEFORM_OT_add_edit_region, NERFDEFORM_OT_select_edit_region)
register, unregister = bpy.utils.register_classes_factory(_classes)
