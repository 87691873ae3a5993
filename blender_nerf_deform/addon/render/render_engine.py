"""The "NeRF Deform" render engine: F12, Render Animation, `blender -b file.blend -a / -s -e`, and
the 3D View's Rendered shading.

Thin, as Cycles' engine class is: `render/frame.py` builds the requests from the
depsgraph, renders them in the worker and converts the passes; this class
registers the passes, hands the frame over and writes what comes back. In the
viewport, `viewport.ViewportRender` keeps the progressive render of the view
and this class draws its latest image with `gpu`, through Blender's display
colour management (bind_display_space_shader, as Blender's RenderEngine
template does). Render results and GPU textures are stored bottom row first;
the engine's rows run top-down.
"""

import weakref

import bpy

import numpy as np

from ..data.camera import CameraError
from ..data.properties import RENDER_ENGINE_ID
from .frame import render_frame
from .viewport import ViewportRender, viewport_pinhole


class NERFDEFORM_RenderEngine(bpy.types.RenderEngine):
    bl_idname = RENDER_ENGINE_ID
    bl_label = "NeRF Deform"
    bl_use_preview = False
    bl_use_postprocess = True

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._viewport: ViewportRender | None = None
        self._texture = None  # (image version, GPUTexture) drawn by view_draw

    def __del__(self):
        # Blender frees the engine when the view leaves Rendered shading: stop its requests.
        try:
            viewport = self._viewport
        except (AttributeError, ReferenceError):  # never initialized, or its Blender data already gone
            return
        if viewport is not None:
            viewport.stop()

    def update_render_passes(self, scene=None, renderlayer=None):
        self.register_pass(scene, renderlayer, "Combined", 4, "RGBA", "COLOR")
        if renderlayer.use_pass_z:
            self.register_pass(scene, renderlayer, "Depth", 1, "Z", "VALUE")
        self.register_pass(scene, renderlayer, "Alpha", 1, "A", "VALUE")

    def render(self, depsgraph):
        scale = depsgraph.scene.render.resolution_percentage / 100.0
        width, height = (
            int(depsgraph.scene.render.resolution_x * scale),
            int(depsgraph.scene.render.resolution_y * scale),
        )
        self.add_pass("Alpha", 1, "A")
        frame = render_frame(
            depsgraph,
            width,
            height,
            on_progress=lambda f, _m: self.update_progress(f),
            should_cancel=self.test_break,
            on_status=lambda text: self.update_stats("", text),
        )
        if frame.cancelled:
            return
        for warning in frame.warnings:
            self.report({"WARNING"}, warning)
        if frame.error:
            self.report({"ERROR"}, frame.error)
            self.error_set(frame.error)
        self._write(width, height, frame.rgba, frame.depth)

    def _write(self, width, height, rgba, depth):
        result = self.begin_result(0, 0, width, height)
        layer = result.layers[0]
        # Blender stores rows bottom-up.
        layer.passes["Combined"].rect.foreach_set(np.ascontiguousarray(rgba[::-1], dtype=np.float32).ravel())
        if "Depth" in layer.passes:
            layer.passes["Depth"].rect.foreach_set(np.ascontiguousarray(depth[::-1], dtype=np.float32).ravel())
        if "Alpha" in layer.passes:
            layer.passes["Alpha"].rect.foreach_set(np.ascontiguousarray(rgba[::-1, :, 3], dtype=np.float32).ravel())
        self.end_result(result)

    # -- viewport (Rendered shading) ------------------------------------------------

    def _viewport_render(self) -> ViewportRender:
        if self._viewport is None:
            engine = weakref.ref(self)

            def redraw():
                alive = engine()
                if alive is not None:
                    alive.tag_redraw()  # ReferenceError once Blender freed it: ViewportRender ignores that

            self._viewport = ViewportRender(redraw)
        return self._viewport

    def view_update(self, context, depsgraph):
        self._viewport_render().update_scene(depsgraph)

    def view_draw(self, context, depsgraph):
        viewport = self._viewport_render()
        try:
            viewport.update_view(viewport_pinhole(context))
        except CameraError as error:
            viewport.refuse_view(str(error))
        self.update_stats("", viewport.status)
        if viewport.image is None:
            return
        import gpu
        from gpu_extras.presets import draw_texture_2d

        if self._texture is None or self._texture[0] != viewport.image_version:
            self._texture = (viewport.image_version, image_texture(viewport.image))
        region = context.region
        # Premultiplied scene-linear pixels, stretched over the region (coarse steps are smaller).
        gpu.state.blend_set("ALPHA_PREMULT")
        self.bind_display_space_shader(depsgraph.scene)
        draw_texture_2d(self._texture[1], (0, 0), region.width, region.height)
        self.unbind_display_space_shader()
        gpu.state.blend_set("NONE")


def image_texture(image: np.ndarray):
    """A GPU texture of an (H, W, 4) image whose first row is the top one (GPU textures start at the bottom)."""
    import gpu

    height, width = image.shape[:2]
    pixels = np.ascontiguousarray(image[::-1], dtype=np.float32).ravel()
    return gpu.types.GPUTexture((width, height), format="RGBA16F", data=gpu.types.Buffer("FLOAT", pixels.size, pixels))


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
