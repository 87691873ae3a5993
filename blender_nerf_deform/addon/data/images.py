"""Images and colours the add-on writes from more than one stage (data layer: docs/ARCHITECTURE.md).

The engine works in sRGB-encoded colours, as the photos it learnt from; Blender's render results,
images and vertex colours are scene-linear. Previews (of the scene, of a training) go into Blender
images shown in the open Image Editors.
"""

from __future__ import annotations

import bpy

import numpy as np


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """The sRGB transfer function undone (IEC 61966-2-1), elementwise on values in [0, 1]."""
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def show_in_image_editors(image: bpy.types.Image) -> None:
    """Show `image` in every open Image Editor that shows nothing or a previous preview, and redraw."""
    wm = bpy.context.window_manager
    for window in wm.windows if wm else ():
        for area in window.screen.areas:
            if area.type != "IMAGE_EDITOR":
                continue
            space = area.spaces.active
            if space.image is None or space.image == image:
                space.image = image
            area.tag_redraw()


def write_image(rgba: np.ndarray, name: str) -> bpy.types.Image:
    """Put a premultiplied scene-linear frame (rows top-down) into the image `name` (made when missing;
    linear float, straight alpha, rows bottom-up)."""
    height, width = rgba.shape[:2]
    image = bpy.data.images.get(name)
    if image is None:
        image = bpy.data.images.new(name, width, height, alpha=True, float_buffer=True)
    elif tuple(image.size) != (width, height):
        image.scale(width, height)
    alpha = rgba[..., 3:]
    straight = np.concatenate([np.where(alpha > 0, rgba[..., :3] / np.maximum(alpha, 1e-12), 0.0), alpha], axis=-1)
    image.pixels.foreach_set(np.ascontiguousarray(straight[::-1], dtype=np.float32).ravel())
    image.update()
    return image
