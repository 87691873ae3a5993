"""The materials of a baked NeRF volume (its `density` and `color` grids, read by Attribute nodes).

- Emission-Absorption (the default): what the NeRF renders. A NeRF's colour
  along a ray is the integral of T(t) sigma(t) c(t) dt, T the transmittance:
  exactly a volume that absorbs with coefficient sigma (Volume Absorption, black:
  all wavelengths alike) and emits sigma * c per unit length (Emission in the
  Volume output). Scene lights do not light it; it hides what is behind it.
- Lit: Principled Volume with the colour as its albedo and the density as
  baked: the scene's lights light it, it casts shadows on meshes and is
  reflected, at the price of looking like the NeRF only where the scene's
  lighting matches the capture's.

One material per kind, made once per file and reused by every baked volume.
"""

from __future__ import annotations

import bpy

MATERIAL_NAMES = {"EMISSION": "NeRF Volume (Emission-Absorption)", "LIT": "NeRF Volume (Lit)"}


def volume_material(shading: str) -> bpy.types.Material:
    name = MATERIAL_NAMES[shading]
    material = bpy.data.materials.get(name)
    if material is not None and material.library is None and material.node_tree is not None:
        return material
    material = bpy.data.materials.new(name)
    if bpy.app.version < (5, 0, 0):
        material.use_nodes = True  # always on (and deprecated) from Blender 5.0
    tree = material.node_tree
    tree.nodes.clear()
    nodes, links = tree.nodes, tree.links
    output = nodes.new("ShaderNodeOutputMaterial")
    output.location = (400, 0)
    density = nodes.new("ShaderNodeAttribute")
    density.attribute_name, density.label, density.location = "density", "Density", (-400, 100)
    color = nodes.new("ShaderNodeAttribute")
    color.attribute_name, color.label, color.location = "color", "Colour", (-400, -150)
    if shading == "EMISSION":
        absorb = nodes.new("ShaderNodeVolumeAbsorption")
        absorb.inputs["Color"].default_value = (0.0, 0.0, 0.0, 1.0)
        absorb.location = (-100, 150)
        emit = nodes.new("ShaderNodeEmission")
        emit.location = (-100, -100)
        both = nodes.new("ShaderNodeAddShader")
        both.location = (150, 0)
        links.new(density.outputs["Fac"], absorb.inputs["Density"])
        links.new(color.outputs["Color"], emit.inputs["Color"])
        links.new(density.outputs["Fac"], emit.inputs["Strength"])
        links.new(absorb.outputs[0], both.inputs[0])
        links.new(emit.outputs[0], both.inputs[1])
        links.new(both.outputs[0], output.inputs["Volume"])
    else:
        principled = nodes.new("ShaderNodeVolumePrincipled")
        principled.location = (-100, 0)
        principled.inputs["Absorption Color"].default_value = (0.0, 0.0, 0.0, 1.0)
        # Its own attribute inputs would multiply the linked grids in again ("density" by default).
        principled.inputs["Density Attribute"].default_value = ""
        principled.inputs["Color Attribute"].default_value = ""
        links.new(density.outputs["Fac"], principled.inputs["Density"])
        links.new(color.outputs["Color"], principled.inputs["Color"])
        links.new(principled.outputs[0], output.inputs["Volume"])
    return material
