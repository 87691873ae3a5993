"""The Blender half: bpy and numpy only, never torch (DESIGN.md).

Properties, operators, panels and the RenderEngine live here; heavy work is
sent to the engine in a worker process.
"""

from . import handles, panel, preferences, properties, render_engine

_modules = (preferences, properties, handles, render_engine, panel)


def register():
    for module in _modules:
        module.register()


def unregister():
    for module in reversed(_modules):
        module.unregister()
