"""Shared by both halves of the suite: the repository on sys.path, Blender's user folders kept
private, and the session fixtures both use (imported by name, not with a star).

    engine/   the engine without Blender: no test there imports bpy
    addon/    the add-on in real headless Blender (the `bpy` module), factory settings reset
              around every test (addon/conftest.py)

Blender's user folders are pointed at a temporary directory before bpy is ever imported, so the
suite never reads or writes the developer's own Blender preferences or extensions.
"""

from __future__ import annotations

import os
import sys
import tempfile

_user_resources = tempfile.mkdtemp(prefix="nerf_deform_blender_user_")
os.environ["BLENDER_USER_RESOURCES"] = _user_resources

from fixtures import REPO  # noqa: E402

if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from fixtures.trained import sphere_nerf  # noqa: E402,F401  (a small trained NeRF, session-scoped)
from fixtures.floor_data import floor_nerf  # noqa: E402,F401  (a statue on a floor, rendered by Blender, trained)
