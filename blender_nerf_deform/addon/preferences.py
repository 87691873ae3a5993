"""Add-on preferences: which Python (one that has torch) runs the engine worker, and how
"Set Up Worker" (worker_setup.py) makes one."""

import bpy
from bpy.props import EnumProperty, StringProperty

from . import worker_setup
from .paths import ADDON_PACKAGE  # the name Blender knows the add-on's preferences by


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
        items=(("CPU", "CPU", "torch for the CPU (smaller download)"),
               ("CUDA", "CUDA", "torch with CUDA, for an NVIDIA GPU")),
        default="CPU",
    )
    torch_source: EnumProperty(
        name="Torch Source",
        items=(("AUTO", "PyTorch Index", "PyTorch's own index for the chosen build where PyPI's torch is another build "
                                         "(CPU on Linux and Windows, CUDA on Windows), else PyPI"),
               ("PIP", "pip's Configuration", "The index or mirror pip is configured with, as for every other package"),
               ("CUSTOM", "Custom Index", "The index URL below")),
        default="AUTO",
    )
    torch_index_url: StringProperty(name="Torch Index", description="Package index URL that torch is installed from")
    base_python: StringProperty(
        name="Base Python", subtype="FILE_PATH", default="",
        description="Python 3.11 the worker environment is made from (empty: Blender's own when it is 3.11, "
                    "else a python3.11 found on the system)",
    )

    def draw(self, context):
        layout = self.layout
        layout.prop(self, "worker_python")
        layout.label(text="A Python 3.11 with torch (CPU or CUDA): set one up below, or see the README.")
        worker_setup.draw_setup(layout, context)


_classes = (NERFDEFORM_AddonPreferences,)
register, unregister = bpy.utils.register_classes_factory(_classes)
