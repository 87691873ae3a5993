"""The "NeRF Deform" render engine (F12, Render Animation, `blender -b -a`).

Thin, as Cycles' add-on is: it turns the scene into an engine request. Until
the rendering issue lands it writes a transparent frame and says so.
"""

import bpy
import numpy as np


class NERFDEFORM_RenderEngine(bpy.types.RenderEngine):
    bl_idname = "NERF_DEFORM"
    bl_label = "NeRF Deform"
    bl_use_preview = False
    bl_use_postprocess = True

    def render(self, depsgraph):
        scene = depsgraph.scene
        scale = scene.render.resolution_percentage / 100.0
        width = int(scene.render.resolution_x * scale)
        height = int(scene.render.resolution_y * scale)
        pixels = np.zeros((width * height, 4), dtype=np.float32)
        result = self.begin_result(0, 0, width, height)
        result.layers[0].passes["Combined"].rect.foreach_set(pixels.ravel())
        self.end_result(result)
        self.report({"WARNING"}, "NeRF Deform: rendering is not implemented yet")


_classes = (NERFDEFORM_RenderEngine,)
register, unregister = bpy.utils.register_classes_factory(_classes)
