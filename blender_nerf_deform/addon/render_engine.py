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


# Blender's own properties panels that make sense for this engine: output format,
# frame range, output path, camera lens, colour management, mesh, object and
# view layer. Panels list the engines they show for in COMPAT_ENGINES, and
# external engines add themselves there (properties_output.py says so).
_PANEL_MODULES = (
    "bl_ui.properties_output",
    "bl_ui.properties_data_camera",
    "bl_ui.properties_data_mesh",
    "bl_ui.properties_object",
    "bl_ui.properties_view_layer",
)
_PANEL_PREFIXES = {"bl_ui.properties_render": "RENDER_PT_color_management"}


def compatible_panels():
    for panel in bpy.types.Panel.__subclasses__():
        engines = getattr(panel, "COMPAT_ENGINES", None)
        if engines is None or "BLENDER_RENDER" not in engines:
            continue
        module = panel.__module__
        if module in _PANEL_MODULES or panel.__name__.startswith(_PANEL_PREFIXES.get(module, "\0")):
            yield panel


_classes = (NERFDEFORM_RenderEngine,)
_register_classes, _unregister_classes = bpy.utils.register_classes_factory(_classes)


def register():
    _register_classes()
    for panel in compatible_panels():
        panel.COMPAT_ENGINES.add(NERFDEFORM_RenderEngine.bl_idname)


def unregister():
    for panel in compatible_panels():
        panel.COMPAT_ENGINES.discard(NERFDEFORM_RenderEngine.bl_idname)
    _unregister_classes()
