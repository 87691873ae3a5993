#!/usr/bin/env python3
"""A small capture scene for edit regions: a statue standing on a textured floor slab.

    python tools/make_floor_scene.py --out floor.blend
    python tools/make_dataset.py --blend floor.blend --out DIR --min-elevation 15 ...

Built procedurally with bpy (no external assets). It is the smallest case of
issue 14's "a statue stands on a floor": the object touches the rest of the
scene, so an edit region around it must cut through its foot, and the cage
must stay pinned there or the floor around the foot moves with the object.
Unlike tools/make_room_scene.py everything lies inside the NeRF-synthetic box,
and the film is transparent (make_dataset's default): a bounded NeRF, RGBA
views composited on white in training, cameras above the floor only.

World frame (Blender's, Z up; metres):

    what                       extent (min, max)
    floor slab (FLOOR_BOUNDS)  checker tiles (TILE wide), top at FLOOR_TOP:
                               (-1.3, -1.3, -1.0) .. (1.3, 1.3, -0.9)
    statue (OBJECT_BOUNDS)     a round plinth, a column and Suzanne on top,
                               standing on the floor: (-0.3, -0.3, -0.9) .. (0.3, 0.3, 0.1)
      plinth                   a cylinder, radius PLINTH_RADIUS, z -0.9 .. PLINTH_TOP (-0.78)
      column                   a cylinder, radius 0.12, z -0.78 .. -0.36 (seen)
      head                     Suzanne (0.57 across, facing -Y), z about -0.4 .. 0.0

So the statue's axis is the Z axis, the floor reaches 1 unit beyond the plinth
on every side, and the whole scene lies in [-1.5, 1.5]^3 (0.2 to spare at the
floor's corners). Cameras of make_dataset at radius 4 with --min-elevation 15
see the floor from above only (its underside is never seen).

Appearance: diffuse (Lambertian) surfaces only, textured so that multi-view
geometry has detail to lock on to and a moved part is visibly moved: the floor
a high-contrast checker (dark slate and sand, tiles TILE = 0.26 wide, lightly
varied), the plinth a red / white checker, the column wavy green / yellow
stripes, the head blotchy orange / dark red. Lighting: a sun from above one
side (soft shadow of the statue on the floor) and a bright bluish-white world
(fill; the world itself is not seen with a transparent film). Cycles settings
saved in the file: 4 bounces (2 diffuse), no glossy / transmission.

The scene's custom property "nerf_floor" (JSON) holds the boxes above.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

# bpy is passed in, not imported: the constants below import without Blender.
from tools.default_scene import camera_at, save_scene, scene_main  # noqa: E402
from tools.make_room_scene import _link, _smooth, checker_material, diffuse_material, noise_material, wave_material  # noqa: E402

FLOOR_TOP = -0.9
FLOOR_BOUNDS = ((-1.3, -1.3, -1.0), (1.3, 1.3, FLOOR_TOP))
TILE = 0.26  # checker square side on the floor
PLINTH_RADIUS = 0.3
PLINTH_TOP = -0.78
COLUMN_RADIUS = 0.12
COLUMN_TOP = -0.36
OBJECT_BOUNDS = ((-0.3, -0.3, FLOOR_TOP), (0.3, 0.3, 0.1))  # the statue (its axis is Z)
WORLD_BOX = ((-1.5, -1.5, -1.5), (1.5, 1.5, 1.5))


def floor_material(bpy, name: str):
    """A checker in object x, y (no z: the slab's top face is one layer of tiles), lightly varied."""
    from tools.make_room_scene import _vary  # noqa: PLC0415

    def build(nodes, links):
        coord = nodes.new("ShaderNodeTexCoord")
        mapping = nodes.new("ShaderNodeMapping")
        mapping.inputs["Scale"].default_value = (1.0 / TILE, 1.0 / TILE, 0.0)
        links.new(coord.outputs["Object"], mapping.inputs["Vector"])
        checker = nodes.new("ShaderNodeTexChecker")
        checker.inputs["Color1"].default_value = (0.78, 0.70, 0.52, 1.0)
        checker.inputs["Color2"].default_value = (0.07, 0.09, 0.13, 1.0)
        checker.inputs["Scale"].default_value = 1.0  # one cell per unit of the mapped vector: TILE
        links.new(mapping.outputs["Vector"], checker.inputs["Vector"])
        coord.location, mapping.location, checker.location = (-900, 0), (-700, 0), (-450, 0)
        return _vary(nodes, links, checker.outputs["Color"], coord.outputs["Object"], 0.8, 0.2)

    return diffuse_material(bpy, name, (0.78, 0.70, 0.52), build)


def build_floor(bpy) -> None:
    (x0, y0, z0), (x1, y1, z1) = FLOOR_BOUNDS
    bpy.ops.mesh.primitive_cube_add(size=1.0, location=(0.5 * (x0 + x1), 0.5 * (y0 + y1), 0.5 * (z0 + z1)))
    slab = _link(bpy, bpy.context.active_object)
    slab.name = slab.data.name = "Floor"
    slab.scale = (x1 - x0, y1 - y0, z1 - z0)
    bpy.ops.object.transform_apply(location=False, rotation=False, scale=True)
    # Tiles meet at the statue's axis: the object origin is the slab's centre, (0, 0).
    slab.data.materials.append(floor_material(bpy, "FloorChecker"))


def build_statue(bpy) -> None:
    plinth_mat = checker_material(
        bpy, "PlinthChecker", (1.0, 1.0), (0.80, 0.08, 0.06), (0.92, 0.90, 0.86), 8.0, vary=0.05
    )
    column_mat = wave_material(bpy, "ColumnStripes", (1.0, 1.0), (0.08, 0.45, 0.12), (0.85, 0.80, 0.15), 5.0, vary=0.05)
    head_mat = noise_material(bpy, "HeadBlotches", (0.95, 0.45, 0.05), (0.45, 0.05, 0.05), 6.0)

    h = PLINTH_TOP - FLOOR_TOP
    bpy.ops.mesh.primitive_cylinder_add(
        vertices=64, radius=PLINTH_RADIUS, depth=h, location=(0.0, 0.0, FLOOR_TOP + 0.5 * h)
    )
    plinth = _link(bpy, bpy.context.active_object)
    plinth.name = "Plinth"
    plinth.data.materials.append(plinth_mat)

    # From 2 cm inside the plinth to 10 cm inside the head: no gaps.
    lo, hi = PLINTH_TOP - 0.02, COLUMN_TOP + 0.1
    bpy.ops.mesh.primitive_cylinder_add(
        vertices=48, radius=COLUMN_RADIUS, depth=hi - lo, location=(0.0, 0.0, 0.5 * (lo + hi))
    )
    column = _link(bpy, bpy.context.active_object)
    column.name = "Column"
    column.data.materials.append(column_mat)
    _smooth(column)

    bpy.ops.mesh.primitive_monkey_add(size=2.0, location=(0.0, 0.0, 0.0))
    head = _link(bpy, bpy.context.active_object)
    head.name = "Head"
    head.scale = (0.21, 0.21, 0.21)  # Suzanne is 2.73 x 1.7 x 1.97 at size 2: 0.57 across
    head.rotation_euler = (math.radians(-10.0), 0.0, 0.0)
    bpy.ops.object.transform_apply(location=False, rotation=True, scale=True)
    mod = head.modifiers.new("subdivision", "SUBSURF")
    mod.levels = mod.render_levels = 1
    _smooth(head)
    head.data.materials.append(head_mat)
    lowest = min(v.co.z for v in head.data.vertices)
    highest = max(v.co.z for v in head.data.vertices)
    # Sits on the column, 4 cm into it; the top stays under OBJECT_BOUNDS.
    head.location.z = min(COLUMN_TOP - 0.04 - lowest, OBJECT_BOUNDS[1][2] - highest)


def build_lights(bpy, scene) -> None:
    sun = bpy.data.lights.new("Sun", "SUN")
    sun.energy = 2.2
    sun.angle = math.radians(8.0)  # a soft-edged shadow
    obj = bpy.data.objects.new("Sun", sun)
    obj.rotation_euler = (math.radians(35.0), 0.0, math.radians(40.0))
    scene.collection.objects.link(obj)
    world = bpy.data.worlds.new("FloorWorld")
    if world.node_tree is None:
        world.use_nodes = True
    background = world.node_tree.nodes.get("Background")
    background.inputs["Color"].default_value = (0.80, 0.86, 1.0, 1.0)
    background.inputs["Strength"].default_value = 0.5
    scene.world = world


def build(bpy) -> dict:
    """Build the floor scene into the current (ideally empty) Blender file; returns its boxes."""
    scene = bpy.context.scene
    build_floor(bpy)
    build_statue(bpy)
    build_lights(bpy, scene)
    camera_at(bpy, scene, (2.4, -2.9, 1.6), lens=50.0)

    render = scene.render
    render.engine = "CYCLES"
    cycles = scene.cycles
    cycles.device = "CPU"
    cycles.samples = 32
    cycles.max_bounces = 4
    cycles.diffuse_bounces = 2
    cycles.glossy_bounces = 0
    cycles.transmission_bounces = 0
    cycles.volume_bounces = 0
    cycles.transparent_max_bounces = 2
    cycles.caustics_reflective = cycles.caustics_refractive = False
    render.film_transparent = True
    render.resolution_x = render.resolution_y = 200
    render.resolution_percentage = 100
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    info = {
        "floor_bounds": FLOOR_BOUNDS,
        "floor_top": FLOOR_TOP,
        "tile": TILE,
        "object_bounds": OBJECT_BOUNDS,
        "plinth": {"radius": PLINTH_RADIUS, "top": PLINTH_TOP},
        "world_box": WORLD_BOX,
        "note": "statue on a floor slab, all inside world_box; transparent film",
    }
    scene["nerf_floor"] = json.dumps(info)
    return info


def check(bpy) -> None:
    """The statue fills OBJECT_BOUNDS at most, stands on the floor, and everything is in WORLD_BOX."""
    from mathutils import Vector  # noqa: PLC0415

    depsgraph = bpy.context.evaluated_depsgraph_get()
    lowest = math.inf
    for ob in bpy.context.scene.objects:
        if ob.type != "MESH":
            continue
        box = OBJECT_BOUNDS if ob.name != "Floor" else FLOOR_BOUNDS
        ev = ob.evaluated_get(depsgraph)
        for corner in ev.bound_box:
            p = ev.matrix_world @ Vector(corner)
            if ob.name != "Floor":
                lowest = min(lowest, p.z)
            for i in range(3):
                if not box[0][i] - 1e-6 <= p[i] <= box[1][i] + 1e-6:
                    raise AssertionError(f"{ob.name} reaches {tuple(p)}, outside {box}")
                if not WORLD_BOX[0][i] <= p[i] <= WORLD_BOX[1][i]:
                    raise AssertionError(f"{ob.name} reaches {tuple(p)}, outside the NeRF box {WORLD_BOX}")
    if abs(lowest - FLOOR_TOP) > 1e-6:
        raise AssertionError(f"the statue's foot is at z = {lowest}, not on the floor top {FLOOR_TOP}")


def save(path, bpy=None) -> Path:
    """Build the floor scene in a fresh, empty Blender file and save it to `path` (.blend)."""
    return save_scene(path, build, check, bpy)


def main(argv=None) -> int:
    return scene_main(argv, "make_floor_scene.py", __doc__, save)


if __name__ == "__main__":
    from blender_nerf_deform.engine.errors import run_command  # an error nobody foresaw: one line naming its log

    sys.exit(run_command("make_floor_scene.py", main))
