"""Extract Mesh: the NeRF's filtered surface as a mesh object with the NeRF's colours.

With edit regions (edit/regions.py) only what lies inside them is extracted, and
with "Pick at 3D Cursor" only the part connected to the cursor (in the region
that holds it). Where a region (or the NeRF's box) cuts the scene the surface
is closed, and those vertices are flagged in the BOOLEAN point attribute
"NeRF Cut" (Build Cage pins the cage there). Each vertex's region (its index in
`regions_of` order; 0 without regions) is the INT point attribute "NeRF Part":
Build Cage builds one cage per part. The regions used are recorded on the mesh.
"""

from __future__ import annotations

import bpy

import numpy as np

from ...engine.service.requests import ExtractRequest
from ..data.cage_store import (
    EMBED_CONTENT_KEY,
    EMBED_COUNT_KEY,
    EMBED_TET_KEY,
    EMBED_WEIGHTS_KEY,
    set_triangles,
)
from ..data.images import srgb_to_linear
from ..data.mesh_attributes import set_cut_flags, set_part_labels
from ..data.paths import checkpoint_path
from ..data.properties import (
    OnNeRF,
    Role,
    alive,
    alive_object,
    forget_deleted,
    handles_of,
    owning_nerf,
    to_nerf_frame,
)
from ..worker.jobs import WorkerOperator
from .regions import SURFACE_REGION_KEY, edit_regions_of, encode_regions, regions_of

COLOR_ATTRIBUTE = "NeRF Color"


def fill_mesh(mesh: bpy.types.Mesh, vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray) -> None:
    set_triangles(mesh, vertices, faces)
    attribute = mesh.color_attributes.get(COLOR_ATTRIBUTE) or mesh.color_attributes.new(
        COLOR_ATTRIBUTE, "FLOAT_COLOR", "POINT"
    )
    # The NeRF's colours are display (sRGB) values; colour attributes hold scene-linear ones.
    linear = srgb_to_linear(np.clip(colors, 0.0, 1.0))
    attribute.data.foreach_set("color", np.c_[linear, np.ones(len(linear))].astype(np.float32).ravel())
    mesh.color_attributes.active_color = attribute


def forget_cage_data(surface: bpy.types.Object) -> None:
    """What a previous mesh left that would not match a new one: its embedding in a deleted cage
    and its shape keys (the preview; a key holds one point per old vertex)."""
    mesh = surface.data
    for key in (EMBED_TET_KEY, EMBED_WEIGHTS_KEY, EMBED_COUNT_KEY, EMBED_CONTENT_KEY):
        if key in mesh:
            del mesh[key]
    if mesh.shape_keys is not None:
        surface.shape_key_clear()


class NERFDEFORM_OT_extract_mesh(WorkerOperator, OnNeRF, bpy.types.Operator):
    """Extract the NeRF's surface (marching cubes at the density threshold), drop small floaters, and import it"""

    bl_idname = "nerf_deform.extract_mesh"
    bl_label = "Extract Mesh"
    bl_options = {"REGISTER", "UNDO"}

    def request(self, context):
        forget_deleted()  # a cage or handle deleted since the last update is gone
        nerf = owning_nerf(context.active_object)
        s = nerf.nerf_deform
        if alive(s.cage) is not None or handles_of(nerf, with_regions=False):
            raise ValueError(
                f"{nerf.name} already has a cage or handles made on its mesh; a new mesh would not match them: "
                "delete the cage object and the handles first"
            )
        if (surface := alive(s.surface)) is not None and surface.mode == "EDIT":
            raise ValueError(f"leave Edit Mode on {surface.name} first")
        context.view_layer.update()  # the region and the cursor as a script just placed them
        regions = edit_regions_of(nerf)  # ValueError naming a region without a box
        self._nerf, self._regions = nerf, regions
        self._region_names = [r.name for r in regions_of(nerf)]
        pick = tuple(to_nerf_frame(nerf) @ context.scene.cursor.location) if s.pick_object else None
        request = ExtractRequest(checkpoint_path(nerf), s.threshold, s.resolution, s.min_volume, tuple(regions), pick)
        return "extract", request.to_wire()[0], None

    def _fail(self, error: Exception) -> set[str]:
        # The worker numbers the regions ("edit regions 1 and 2 overlap"): say which Empties those are.
        names = getattr(self, "_region_names", [])
        if len(names) > 1 and "edit region" in str(error):
            legend = ", ".join(f"{i + 1}: {name}" for i, name in enumerate(names))
            error = ValueError(f"{error} (edit regions {legend})")
        return super()._fail(error)

    def apply(self, context, result, arrays):
        nerf = self._nerf
        if not alive_object(nerf):  # deleted while the worker extracted (from the UI)
            return self._fail(ValueError("the NeRF was deleted while its mesh was extracted"))
        s = nerf.nerf_deform
        surface = alive(s.surface)
        if surface is not None and surface.mode == "EDIT":
            return self._fail(
                ValueError(f"{surface.name} went into Edit Mode while it was extracted: run Extract Mesh again")
            )
        if surface is not None:
            forget_cage_data(surface)
        if surface is None:
            surface = bpy.data.objects.new(f"{nerf.name} Mesh", bpy.data.meshes.new(f"{nerf.name} Mesh"))
            for collection in nerf.users_collection:
                collection.objects.link(surface)
            surface.parent = nerf
            surface.nerf_deform.role = Role.SURFACE
            surface.hide_render = True  # the NeRF renders itself; the mesh is the artist's proxy
            s.surface = surface
        fill_mesh(surface.data, arrays["vertices"], arrays["faces"], arrays["colors"])
        set_cut_flags(surface.data, arrays.get("cut"))
        part = arrays.get("part")
        set_part_labels(surface.data, part if part is not None and len(part) == len(surface.data.vertices) else None)
        surface.data[SURFACE_REGION_KEY] = encode_regions(self._regions)
        for line in result["report"].splitlines():
            self.report({"INFO"}, f"{surface.name}: {line}")
        return {"FINISHED"}


_classes = (NERFDEFORM_OT_extract_mesh,)
register, unregister = bpy.utils.register_classes_factory(_classes)
