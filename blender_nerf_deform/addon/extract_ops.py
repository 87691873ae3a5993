"""Extract Mesh: the NeRF's filtered surface as a mesh object with the NeRF's colours."""

from __future__ import annotations

import bpy
import numpy as np

from .cage_store import set_triangles
from .jobs import WorkerOperator
from .nerf_ops import checkpoint_path
from .properties import handles_of, owning_nerf
from .frame_render import srgb_to_linear

COLOR_ATTRIBUTE = "NeRF Color"


def fill_mesh(mesh: bpy.types.Mesh, vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray) -> None:
    set_triangles(mesh, vertices, faces)
    attribute = mesh.color_attributes.get(COLOR_ATTRIBUTE) or mesh.color_attributes.new(COLOR_ATTRIBUTE, "FLOAT_COLOR", "POINT")
    # The NeRF's colours are display (sRGB) values; colour attributes hold scene-linear ones.
    linear = srgb_to_linear(np.clip(colors, 0.0, 1.0))
    attribute.data.foreach_set("color", np.c_[linear, np.ones(len(linear))].astype(np.float32).ravel())
    mesh.color_attributes.active_color = attribute


class NERFDEFORM_OT_extract_mesh(WorkerOperator, bpy.types.Operator):
    """Extract the NeRF's surface (marching cubes at the density threshold), drop small floaters, and import it"""

    bl_idname = "nerf_deform.extract_mesh"
    bl_label = "Extract Mesh"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        return owning_nerf(context.active_object) is not None

    def request(self, context):
        nerf = owning_nerf(context.active_object)
        s = nerf.nerf_deform
        if s.cage is not None or handles_of(nerf):
            raise ValueError(
                f"{nerf.name} already has a cage or handles made on its mesh; a new mesh would not match them: "
                "delete the cage object and the handles first"
            )
        self._nerf = nerf
        params = {"checkpoint": checkpoint_path(nerf), "threshold": s.threshold, "resolution": s.resolution, "min_volume": s.min_volume}
        return "extract", params, None

    def apply(self, context, result, arrays):
        nerf = self._nerf
        s = nerf.nerf_deform
        surface = s.surface
        if surface is None:
            surface = bpy.data.objects.new(f"{nerf.name} Mesh", bpy.data.meshes.new(f"{nerf.name} Mesh"))
            for collection in nerf.users_collection:
                collection.objects.link(surface)
            surface.parent = nerf
            surface.nerf_deform.role = "SURFACE"
            surface.hide_render = True  # the NeRF renders itself; the mesh is the artist's proxy
            s.surface = surface
        fill_mesh(surface.data, arrays["vertices"], arrays["faces"], arrays["colors"])
        for line in result["report"].splitlines():
            self.report({"INFO"}, f"{surface.name}: {line}")
        return {"FINISHED"}


_classes = (NERFDEFORM_OT_extract_mesh,)
register, unregister = bpy.utils.register_classes_factory(_classes)
