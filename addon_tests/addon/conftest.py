"""Fixtures of the add-on's tests: real headless Blender (the `bpy` module), reset around every test.

Every test in this folder starts and ends in Blender's factory settings (an empty scene), whether
it asks for `blender` or not, as MolecularNodes' and other well-kept add-ons' suites do: no scene,
handler or registered class leaks from one test into the next.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from fixtures.scenes import default_scene_blend, make_procedural_dataset, procedural_dataset  # noqa: F401


@pytest.fixture(autouse=True)
def blender():
    """Factory settings before and after the test (automatic for every add-on test)."""
    import bpy

    bpy.ops.wm.read_factory_settings(use_empty=True)
    yield bpy
    bpy.ops.wm.read_factory_settings(use_empty=True)


@pytest.fixture(scope="module")
def module_worker():
    """The worker the module's `addon` tests share: starting one costs a torch import and a kernel
    load (3-4 s), which dozens of tests paid each. A test that stops or kills it gets a new one on its
    next request, as a user would; the module's last test leaves it stopped."""
    held = {"client": None}
    yield held
    if held["client"] is not None:
        held["client"].stop()


@pytest.fixture
def addon(blender, module_worker):
    """The add-on registered by direct import, in factory settings; unregistered after (the worker is
    kept for the module's next test: module_worker)."""
    import blender_nerf_deform
    from blender_nerf_deform.addon.worker import client as worker_client

    blender_nerf_deform.register()
    worker_client.adopt_client(module_worker["client"])
    yield blender
    client = worker_client.detach_client()
    if client is not None and client.busy:  # a job left running (a test that failed midway): the next starts clean
        client.stop()
        client = None
    module_worker["client"] = client
    blender_nerf_deform.unregister()


@pytest.fixture(scope="session")
def extension_zip(tmp_path_factory) -> Path:
    """The extension zip built by tools/build_extension.py (validated by Blender's tool)."""
    from fixtures.shared_build import built_once

    from tools.build_extension import build

    (zip_path,) = built_once(tmp_path_factory, "dist", build).glob("*.zip")
    return zip_path
