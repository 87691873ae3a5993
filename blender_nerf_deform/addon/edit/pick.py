"""Place 3D Cursor on NeRF: a click in the viewport puts the 3D cursor where the ray first meets the
NeRF's density, the pick point of Extract Mesh's "Pick at 3D Cursor".

A NeRF has no geometry for Blender's own cursor snapping (shift + right click snaps to meshes,
and there is no mesh before Extract Mesh), so the worker marches the clicked ray through the
NeRF's density (`first_surface`). From the UI the operator waits for a left click in a 3D View
(Esc or right click cancels); from Python it takes the ray as `origin` and `direction` (world
space), blocking, for scripts and tests.
"""

from __future__ import annotations

import bpy
from bpy.props import FloatVectorProperty

import numpy as np
from mathutils import Vector

from ...engine.service.requests import FirstSurfaceRequest
from ..data.paths import checkpoint_path
from ..data.properties import OnNeRF, owning_nerf, to_nerf_frame
from ..worker.client import WorkerError
from ..worker.jobs import worker


class NERFDEFORM_OT_place_cursor_on_nerf(OnNeRF, bpy.types.Operator):
    """Click on the NeRF in the viewport: the 3D cursor goes where the ray first meets its surface (the pick point of "Pick at 3D Cursor")"""  # noqa: E501 (the tooltip: one line)

    bl_idname = "nerf_deform.place_cursor_on_nerf"
    bl_label = "Place 3D Cursor on NeRF"
    bl_options = {"REGISTER", "UNDO"}

    origin: FloatVectorProperty(name="Ray Origin", size=3, description="World-space start of the ray (scripts)")
    direction: FloatVectorProperty(
        name="Ray Direction", size=3, description="World-space direction of the ray (scripts)"
    )

    def execute(self, context):
        nerf = owning_nerf(context.active_object)
        try:
            return self._place(context, nerf, np.array(self.origin), np.array(self.direction))
        except (WorkerError, ValueError) as error:
            self.report({"ERROR"}, f"{self.bl_label}: {error}")
            return {"CANCELLED"}

    def _place(self, context, nerf, origin_world: np.ndarray, direction_world: np.ndarray):
        if (
            not np.isfinite(origin_world).all()
            or not np.isfinite(direction_world).all()
            or np.linalg.norm(direction_world) < 1e-12
        ):
            raise ValueError("the ray needs a finite origin and a non-zero direction")
        to_nerf = to_nerf_frame(nerf)
        origin = to_nerf @ Vector(origin_world.tolist())
        direction = to_nerf.to_3x3() @ Vector(direction_world.tolist())
        request = FirstSurfaceRequest(
            checkpoint_path(nerf), tuple(origin), tuple(direction), float(nerf.nerf_deform.threshold)
        )
        result, _ = worker(context).call("first_surface", *request.to_wire())
        if not result["hit"]:
            raise ValueError(
                f"the ray meets no density above the threshold {result['threshold']:g} in "
                f"{nerf.name}'s box (the largest on it is {result['max_density']:.3g}): click on the object"
            )
        point = nerf.matrix_world @ Vector(result["point"])
        context.scene.cursor.location = point
        self.report({"INFO"}, f"3D cursor on {nerf.name} at ({point.x:.3g}, {point.y:.3g}, {point.z:.3g})")
        return {"FINISHED"}

    def invoke(self, context, event):
        if owning_nerf(context.active_object) is None:
            return {"CANCELLED"}
        context.window_manager.modal_handler_add(self)
        context.workspace.status_text_set("Place 3D Cursor on NeRF: click on the NeRF in a 3D View (Esc to cancel)")
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        if event.type in {"ESC", "RIGHTMOUSE"}:
            context.workspace.status_text_set(None)
            return {"CANCELLED"}
        if event.type != "LEFTMOUSE" or event.value != "PRESS":
            return {"PASS_THROUGH"}
        ray = _ray_under_mouse(context, event)
        if ray is None:
            return {"PASS_THROUGH"}  # a click outside a 3D View's main region: keep waiting
        context.workspace.status_text_set(None)
        self.origin, self.direction = ray
        return self.execute(context)


def _ray_under_mouse(context, event):
    """(origin, direction) in world space of the click, in whichever 3D View's main region it fell."""
    from bpy_extras import view3d_utils

    for area in context.window.screen.areas:
        if area.type != "VIEW_3D":
            continue
        for region in area.regions:
            if region.type != "WINDOW":
                continue
            x, y = event.mouse_x - region.x, event.mouse_y - region.y
            if 0 <= x < region.width and 0 <= y < region.height:
                rv3d = area.spaces.active.region_3d
                origin = view3d_utils.region_2d_to_origin_3d(region, rv3d, (x, y))
                direction = view3d_utils.region_2d_to_vector_3d(region, rv3d, (x, y))
                return tuple(origin), tuple(direction)
    return None


_classes = (NERFDEFORM_OT_place_cursor_on_nerf,)
register, unregister = bpy.utils.register_classes_factory(_classes)
