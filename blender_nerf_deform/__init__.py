"""blender_nerf_deform: edit the geometry of a trained NeRF and render it.

This file is the extension's entry point for Blender and nothing else: it
imports nothing heavy at module level, so that `python -m
blender_nerf_deform.engine` (no Blender) and Blender (no torch) can both
import the package. See docs/ARCHITECTURE.md: `engine/` never imports bpy, `addon/`
never imports torch.
"""


def register():
    from . import addon

    addon.register()


def unregister():
    from . import addon

    addon.unregister()
