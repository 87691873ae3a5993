"""Shared fixtures: real headless Blender (the `bpy` module), reset around every test.

Blender's user folders are pointed at a temporary directory before bpy is
imported, so the suite never reads or writes the developer's own Blender
preferences or extensions.
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
SHARED_DATASETS = REPO.parent / "shared" / "datasets"

_user_resources = tempfile.mkdtemp(prefix="nerf_deform_blender_user_")
os.environ["BLENDER_USER_RESOURCES"] = _user_resources

if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from dataset_fixtures import *  # noqa: E402,F401,F403  (default scene + procedural_dataset, session-scoped)
from addon_fixtures import *  # noqa: E402,F401,F403  (sphere_nerf: a small trained NeRF, session-scoped)


@pytest.fixture
def blender():
    """Factory settings before and after the test, as well-kept add-ons' suites do."""
    import bpy

    bpy.ops.wm.read_factory_settings(use_empty=True)
    yield bpy
    bpy.ops.wm.read_factory_settings(use_empty=True)


@pytest.fixture
def addon(blender):
    """The add-on registered by direct import, in factory settings; unregistered after."""
    import blender_nerf_deform

    blender_nerf_deform.register()
    yield blender
    blender_nerf_deform.unregister()


@pytest.fixture(scope="session")
def extension_zip(tmp_path_factory) -> Path:
    """The extension zip built by tools/build_extension.py (validated by Blender's tool)."""
    from tools.build_extension import build

    return build(tmp_path_factory.mktemp("dist"))
