"""Where the add-on's files are: its module name and preferences (the Worker Python), a NeRF's
checkpoint, a training's run folder.

The data layer (docs/ARCHITECTURE.md, "The add-on in layers"): operators of every stage and the
worker client read these, so they live below all of them rather than in one operator's module.
"""

from __future__ import annotations

import os
import tempfile

import bpy

# The add-on's top-level module: `bl_ext.<repo>.blender_nerf_deform` as an extension (the name
# Blender's preferences and extension_path_user know it by), `blender_nerf_deform` imported directly.
ADDON_PACKAGE = __package__.rsplit(".", 2)[0]  # <package>.addon.data


def checkpoint_path(nerf: bpy.types.Object) -> str:
    """The NeRF's checkpoint as an absolute path (stored relative to the .blend when it is saved)."""
    return os.path.normpath(bpy.path.abspath(nerf.nerf_deform.checkpoint))


def project_folder(beside_blend: str, in_user_folder: str, name: str, create: bool = True) -> str:
    """Where the add-on puts what it makes for the artist (a training run, a captured dataset):
    //<beside_blend>/<name> beside a saved .blend, else <in_user_folder>/<name> in the extension's user
    folder (made only with `create`: a panel's poll asks where a run would be without making folders)."""
    if bpy.data.filepath:
        return os.path.join(os.path.dirname(bpy.data.filepath), beside_blend, name)
    try:
        root = bpy.utils.extension_path_user(ADDON_PACKAGE, path=in_user_folder, create=create)
    except (ValueError, AttributeError):  # imported directly, not enabled as an extension
        root = os.path.join(tempfile.gettempdir(), f"nerf_deform_{in_user_folder}")
    return os.path.join(root, name)


def default_run_folder(data: str, create: bool = True) -> str:
    """A training's run folder: //nerf_runs/<dataset name>, else the user folder's runs/<name>."""
    return project_folder("nerf_runs", "runs", os.path.basename(os.path.normpath(data)) or "nerf", create)


def same_file(a: str, b: str) -> bool:
    """Whether two paths name one existing file (False when either is missing)."""
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


def addon_preferences(context=None):
    """The add-on's preferences, or None when it was imported directly rather than enabled."""
    context = context or bpy.context
    addon = context.preferences.addons.get(ADDON_PACKAGE)
    return addon.preferences if addon is not None else None


def worker_python(context=None) -> str:
    """The Worker Python preference ("" when unset, or when the add-on was imported
    directly rather than enabled, so it has no preferences)."""
    prefs = addon_preferences(context)
    return prefs.worker_python if prefs is not None else ""
