"""The "NeRF Deform" render engine: F12, Render Animation, `blender -b file.blend -a / -s -e`.

Thin, as Cycles' add-on is: it turns the scene at the frame being rendered
into one engine request (camera in the NeRF's frame, checkpoint), waits for
the worker's answer while Blender's progress bar and Esc (`test_break`) work,
and writes the passes:

- Combined: RGBA, premultiplied as Blender's render buffers are, in scene
  linear (the NeRF's sRGB colours decoded), so the "Standard" view transform
  gives back exactly the colours the NeRF learnt.
- Depth (when the view layer's Z pass is on): distance from the camera plane
  in world units, as Cycles writes it; 1e10 where nothing was hit.
- Alpha: coverage, one channel.

Render results are stored bottom row first; the engine's rows run top-down.
"""

import bpy
import numpy as np

from . import jobs
from .cage_store import deformed_cage_in_nerf_frame, has_cage, load_cage
from .camera import CameraError, pinhole_from_blender
from .nerf_ops import checkpoint_path
from .deformation import solve_request
from .worker_client import WorkerError

NO_HIT_DEPTH = 1e10


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def nerfs_to_render(scene) -> list:
    return sorted(
        (o for o in scene.objects if o.nerf_deform.role == "NERF" and not o.hide_render), key=lambda o: o.name
    )


def frame_request(depsgraph, nerf, downscale: int = 1) -> tuple[dict, dict, np.ndarray]:
    """The worker request that renders `nerf` from the scene camera, and the per-pixel factor
    that turns the engine's depth (NeRF units along unit rays) into Blender's planar depth."""
    scene = depsgraph.scene
    if scene.camera is None:
        raise CameraError(f"scene '{scene.name}' has no active camera")
    camera = scene.camera.evaluated_get(depsgraph)
    nerf_eval = nerf.evaluated_get(depsgraph)
    pinhole = pinhole_from_blender(scene, camera).downscaled(downscale)
    to_nerf = np.linalg.inv(np.array(nerf_eval.matrix_world, dtype=np.float64))
    c2w = to_nerf @ np.array(pinhole.camera_to_world, dtype=np.float64)
    # Camera-space ray of each pixel has z = -1: its planar depth is 1 per unit of that vector.
    i = np.arange(pinhole.width) + 0.5
    j = np.arange(pinhole.height) + 0.5
    jj, ii = np.meshgrid(j, i, indexing="ij")
    d_cam = np.stack([(ii - pinhole.cx) / pinhole.fx, -(jj - pinhole.cy) / pinhole.fy, -np.ones_like(ii)], -1)
    length_in_nerf = np.linalg.norm(d_cam @ c2w[:3, :3].T, axis=-1)
    params = {
        "checkpoint": checkpoint_path(nerf),
        "camera": {**pinhole.as_dict(), "camera_to_world": c2w.tolist()},
    }
    return params, deformation_arrays(nerf, depsgraph), 1.0 / length_in_nerf


def deformation_arrays(nerf, depsgraph) -> dict:
    """The rest cage and its pose at this frame, for ray bending; empty when there is nothing to bend."""
    s = nerf.nerf_deform
    if s.cage is None or not has_cage(s.cage.data):
        return {}
    rest, tets = load_cage(s.cage.data)
    if s.deformation_mode == "MODIFIERS":
        deformed = deformed_cage_in_nerf_frame(nerf, s.cage, depsgraph)
    else:
        request = solve_request(nerf, depsgraph)
        if request is None:
            return {}  # no handle: the rest pose
        _stats, out = jobs.worker(bpy.context).call("solve", *request)
        deformed = out["deformed_vertices"]
    return {"rest_vertices": rest, "tets": tets, "deformed_vertices": deformed}


class NERFDEFORM_RenderEngine(bpy.types.RenderEngine):
    bl_idname = "NERF_DEFORM"
    bl_label = "NeRF Deform"
    bl_use_preview = False
    bl_use_postprocess = True

    def update_render_passes(self, scene=None, renderlayer=None):
        self.register_pass(scene, renderlayer, "Combined", 4, "RGBA", "COLOR")
        if renderlayer.use_pass_z:
            self.register_pass(scene, renderlayer, "Depth", 1, "Z", "VALUE")
        self.register_pass(scene, renderlayer, "Alpha", 1, "A", "VALUE")

    def render(self, depsgraph):
        scene = depsgraph.scene
        scale = scene.render.resolution_percentage / 100.0
        width, height = int(scene.render.resolution_x * scale), int(scene.render.resolution_y * scale)
        self.add_pass("Alpha", 1, "A")
        rgba = np.zeros((height, width, 4), dtype=np.float32)
        depth = np.full((height, width), NO_HIT_DEPTH, dtype=np.float32)
        try:
            nerfs = nerfs_to_render(scene)
            if not nerfs:
                raise ValueError("no NeRF object in the scene to render: use Load NeRF first")
            if len(nerfs) > 1:
                self.report({"WARNING"}, f"NeRF Deform renders one NeRF per scene; rendering {nerfs[0].name}")
            params, arrays, depth_factor = frame_request(depsgraph, nerfs[0])
            self.update_stats("", f"NeRF Deform: rendering {nerfs[0].name}, frame {scene.frame_current}")
            result, out = jobs.worker(bpy.context).call(
                "render", params, arrays, on_progress=lambda f, _m: self.update_progress(f), should_cancel=self.test_break
            )
            if result.get("inverted_tets") or result.get("degenerate_tets"):
                self.report({"WARNING"}, f"NeRF Deform: frame {scene.frame_current}: {result['inverted_tets']} inverted and "
                            f"{result['degenerate_tets']} degenerate cage tets (folds show the folded content)")
            rgba = out["rgba"]
            alpha = rgba[..., 3]
            hit = alpha > 1e-6
            depth = np.where(hit, out["depth"] * depth_factor, NO_HIT_DEPTH).astype(np.float32)
            rgba = np.concatenate([srgb_to_linear(rgba[..., :3]) * alpha[..., None], alpha[..., None]], axis=-1)
        except (CameraError, ValueError, WorkerError) as error:
            if isinstance(error, WorkerError) and error.kind == "cancelled":
                if self.test_break():
                    return  # Esc: Blender asked, and stops the render itself
                # Cancelled without Blender asking (the worker was stopped or restarted): an empty
                # frame must not pass for a rendered one.
                error = f"the render of frame {scene.frame_current} was cancelled in the NeRF worker ({error})"
            self.report({"ERROR"}, f"NeRF Deform: {error}")
            self.error_set(f"NeRF Deform: {error}")
        self._write(width, height, rgba, depth)

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
