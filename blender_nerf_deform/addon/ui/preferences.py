"""Add-on preferences: which Python (one that has torch) runs the engine worker, and how
"Set Up Worker" (worker/setup.py) makes one, drawn here."""

import bpy
from bpy.props import BoolProperty, EnumProperty, StringProperty

from ..data.paths import ADDON_PACKAGE, addon_preferences  # the name Blender knows the add-on's preferences by
from ..worker import setup as worker_setup


class NERFDEFORM_AddonPreferences(bpy.types.AddonPreferences):
    bl_idname = ADDON_PACKAGE

    worker_python: StringProperty(
        name="Worker Python",
        description="Python interpreter with torch installed that runs the NeRF engine "
        "(extraction, cage building, ARAP solves and rendering) in a separate process; "
        "Set Up Worker makes one and sets it here",
        subtype="FILE_PATH",
        default="",
    )
    worker_build: EnumProperty(
        name="Build",
        items=(
            ("CPU", "CPU", "torch for the CPU (smaller download)"),
            ("CUDA", "CUDA", "torch with CUDA, for an NVIDIA GPU"),
        ),
        default="CPU",
    )
    torch_source: EnumProperty(
        name="Torch Source",
        items=(
            (
                "AUTO",
                "PyTorch Index",
                "PyTorch's own index for the chosen build where PyPI's torch is another build "
                "(CPU on Linux and Windows, CUDA on Windows), else PyPI",
            ),
            ("PIP", "pip's Configuration", "The index or mirror pip is configured with, as for every other package"),
            ("CUSTOM", "Custom Index", "The index URL below"),
        ),
        default="AUTO",
    )
    torch_index_url: StringProperty(name="Torch Index", description="Package index URL that torch is installed from")
    base_python: StringProperty(
        name="Base Python",
        subtype="FILE_PATH",
        default="",
        description="Python 3.11 the worker environment is made from (empty: Blender's own when it is 3.11, "
        "else a python3.11 found on the system)",
    )

    start_worker_on_open: BoolProperty(
        name="Start Worker on Open",
        description="When a file with NeRFs opens, start the worker and load its NeRFs in the background, so that "
        "the first render waits for neither (the worker then holds their memory)",
        default=True,
    )

    def draw(self, context):
        layout = self.layout
        layout.prop(self, "worker_python")
        layout.prop(self, "start_worker_on_open")
        layout.label(text="A Python 3.11 with torch (CPU or CUDA): set one up below, or see the README.")
        draw_worker_environment(layout, context)


def draw_worker_environment(layout, context) -> None:
    """The preferences' "Worker environment" box."""
    box = layout.box()
    box.label(text="Worker Environment", icon="CONSOLE")
    job = worker_setup.running_job()
    if job is not None:
        box.label(text=f"{100 * job.progress:.0f}%  {job.message}")
        for line in list(job.log)[-3:]:
            box.label(text=line[:120])
        box.operator(worker_setup.NERFDEFORM_OT_cancel_worker_setup.bl_idname, icon="CANCEL")
        return
    prefs = addon_preferences(context)
    row = box.row()
    row.prop(prefs, "worker_build", expand=True)
    box.prop(prefs, "torch_source")
    if prefs.torch_source == "CUSTOM":
        box.prop(prefs, "torch_index_url")
    box.prop(prefs, "base_python")
    env = worker_setup.existing_environment()
    if env is None:
        box.operator(worker_setup.NERFDEFORM_OT_setup_worker.bl_idname, icon="IMPORT").mode = "AUTO"
    else:
        box.label(text=f"Found: {env}")
        row = box.row()
        row.operator(worker_setup.NERFDEFORM_OT_setup_worker.bl_idname, text="Reuse", icon="CHECKMARK").mode = "REUSE"
        row.operator(
            worker_setup.NERFDEFORM_OT_setup_worker.bl_idname, text="Rebuild", icon="FILE_REFRESH"
        ).mode = "REBUILD"
    last = worker_setup.last_job()
    if last is not None and last.done == "error":
        box.label(text=f"Last setup failed: {last.error}"[:160], icon="ERROR")


_classes = (NERFDEFORM_AddonPreferences,)
register, unregister = bpy.utils.register_classes_factory(_classes)
