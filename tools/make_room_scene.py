#!/usr/bin/env python3
"""A shareable 360-degree capture scene with a background: an object inside a textured room.

    python tools/make_room_scene.py --out room.blend
    python tools/make_dataset.py --blend room.blend --out DIR --opaque --radius 2.7 ...

Built procedurally with bpy (no external assets), so the scene and any dataset
rendered from it can be shipped and shared. It is the "real capture" case of
issue 13 made synthetic: cameras on a ring / hemisphere inside the room look at
the object, and the room is visible behind it in every view. Render with
`make_dataset.py --opaque` (no transparent film: the background is part of the
capture, images are RGB).

World frame (Blender's, Z up; metres):

    what                     extent (min, max)
    object (OBJECT_BOUNDS)   Suzanne, a cube, a sphere and a cone on a round
                             plate, about 1.3 across:  (-0.7, -0.7, -0.55) .. (0.7, 0.7, 0.55)
    pedestal column          a cylinder from the floor up to the plate:  z -2.0 .. -0.55, radius 0.28
    room (ROOM_BOUNDS)       a closed box, inner faces: (-4.5, -4.5, -2.0) .. (4.5, 4.5, 4.0)

So the object lies well inside the NeRF-synthetic world box [-1.5, 1.5]^3,
while the walls, floor and ceiling are 2 to 4.5 units beyond it: a NeRF
bounded to [-1.5, 1.5]^3 cannot model them (only the pedestal column crosses
the box's bottom face, as a table would in a real capture). Cameras at radius
about 2.7 around the origin, from a little below the horizon up to the zenith,
are inside the room (the lowest, at -15 degrees, is 1.3 above the floor; the
highest 1.3 below the ceiling).

Appearance: diffuse (Lambertian) surfaces only, no speculars, so every surface
looks the same from every view (learnable by a view-dependent or independent
NeRF alike). Each wall has its own procedural texture and colour (brick,
checker, wave stripes, noise plaster) with colour variation, and a few
distinct features (a framed picture, a door, a shelf with boxes, a poster), so
multi-view geometry has something to lock on to. The floor is a large tile
pattern, the ceiling a light plaster. Lighting: an emissive panel and an area
light in the ceiling, an emissive "window" on one wall and a weak fill, with
diffuse bounces, so no corner is black. Cycles settings saved in the file:
4 bounces (3 diffuse), no glossy / transmission, no caustics; make_dataset
sets samples and denoising itself.

The scene's custom property "nerf_room" (JSON) holds the boxes above.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from tools.default_scene import black_world, camera_at, save_scene, scene_main  # noqa: E402  (bpy is passed in, not imported)

OBJECT_BOUNDS = ((-0.7, -0.7, -0.55), (0.7, 0.7, 0.55))  # everything above the pedestal column
ROOM_BOUNDS = ((-4.5, -4.5, -2.0), (4.5, 4.5, 4.0))  # inner faces of walls, floor, ceiling
WORLD_BOX = ((-1.5, -1.5, -1.5), (1.5, 1.5, 1.5))  # the NeRF-synthetic box the object lies in
PLATE_TOP = -0.45
PLATE_RADIUS = 0.7
COLUMN_RADIUS = 0.28


# --------------------------------------------------------------------------- materials


def _material(bpy, name: str):
    mat = bpy.data.materials.new(name)
    if mat.node_tree is None:  # Blender < 5.0
        mat.use_nodes = True
    nodes, links = mat.node_tree.nodes, mat.node_tree.links
    nodes.clear()
    out = nodes.new("ShaderNodeOutputMaterial")
    out.location = (400, 0)
    return mat, nodes, links, out


def diffuse_material(bpy, name: str, colour, colour_socket_builder=None):
    """A Diffuse BSDF (view-independent); colour_socket_builder(nodes, links) -> a colour output socket."""
    mat, nodes, links, out = _material(bpy, name)
    bsdf = nodes.new("ShaderNodeBsdfDiffuse")
    bsdf.location = (150, 0)
    bsdf.inputs["Color"].default_value = (*colour, 1.0)
    bsdf.inputs["Roughness"].default_value = 0.0
    if colour_socket_builder is not None:
        links.new(colour_socket_builder(nodes, links), bsdf.inputs["Color"])
    links.new(bsdf.outputs["BSDF"], out.inputs["Surface"])
    return mat


def emission_material(bpy, name: str, colour, strength: float):
    mat, nodes, links, out = _material(bpy, name)
    em = nodes.new("ShaderNodeEmission")
    em.inputs["Color"].default_value = (*colour, 1.0)
    em.inputs["Strength"].default_value = strength
    links.new(em.outputs["Emission"], out.inputs["Surface"])
    return mat


def _uv(nodes, scale):
    """UV coordinates scaled by (sx, sy): texture repeats per unit of the face."""
    coord = nodes.new("ShaderNodeTexCoord")
    mapping = nodes.new("ShaderNodeMapping")
    mapping.inputs["Scale"].default_value = (scale[0], scale[1], 1.0)
    coord.location, mapping.location = (-900, 0), (-700, 0)
    nodes.id_data.links.new(coord.outputs["UV"], mapping.inputs["Vector"])
    return mapping.outputs["Vector"]


def _vary(nodes, links, colour_socket, vector, scale, amount):
    """colour x (1 - amount/2 + amount * noise): low-frequency colour variation (no two patches alike)."""
    noise = nodes.new("ShaderNodeTexNoise")
    noise.inputs["Scale"].default_value = scale
    noise.inputs["Detail"].default_value = 3.0
    links.new(vector, noise.inputs["Vector"])
    ramp = nodes.new("ShaderNodeMapRange")
    ramp.inputs["To Min"].default_value = 1.0 - amount
    ramp.inputs["To Max"].default_value = 1.0 + amount
    ramp.inputs["From Min"].default_value = 0.3
    ramp.inputs["From Max"].default_value = 0.7
    links.new(noise.outputs["Fac"], ramp.inputs["Value"])
    mix = nodes.new("ShaderNodeMix")
    mix.data_type = "RGBA"
    mix.blend_type = "MULTIPLY"
    mix.inputs["Factor"].default_value = 1.0
    links.new(colour_socket, mix.inputs["A"])
    links.new(ramp.outputs["Result"], mix.inputs["B"])
    noise.location, ramp.location, mix.location = (-450, -300), (-250, -300), (-50, 0)
    return mix.outputs["Result"]


def brick_material(bpy, name, size, colour1, colour2, mortar, brick_width=0.5, row_height=0.25, vary=0.25):
    def build(nodes, links):
        vec = _uv(nodes, size)
        brick = nodes.new("ShaderNodeTexBrick")
        brick.location = (-450, 0)
        brick.inputs["Color1"].default_value = (*colour1, 1.0)
        brick.inputs["Color2"].default_value = (*colour2, 1.0)
        brick.inputs["Mortar"].default_value = (*mortar, 1.0)
        brick.inputs["Scale"].default_value = 1.0
        brick.inputs["Mortar Size"].default_value = 0.025
        brick.inputs["Brick Width"].default_value = brick_width
        brick.inputs["Row Height"].default_value = row_height
        brick.offset, brick.squash = 0.5, 1.0
        links.new(vec, brick.inputs["Vector"])
        return _vary(nodes, links, brick.outputs["Color"], vec, 0.6, vary)

    return diffuse_material(bpy, name, colour1, build)


def checker_material(bpy, name, size, colour1, colour2, squares, vary=0.2):
    def build(nodes, links):
        vec = _uv(nodes, size)
        checker = nodes.new("ShaderNodeTexChecker")
        checker.location = (-450, 0)
        checker.inputs["Color1"].default_value = (*colour1, 1.0)
        checker.inputs["Color2"].default_value = (*colour2, 1.0)
        checker.inputs["Scale"].default_value = squares
        links.new(vec, checker.inputs["Vector"])
        return _vary(nodes, links, checker.outputs["Color"], vec, 0.5, vary)

    return diffuse_material(bpy, name, colour1, build)


def wave_material(bpy, name, size, colour1, colour2, scale, vary=0.2):
    """Wavy vertical stripes between two colours."""

    def build(nodes, links):
        vec = _uv(nodes, size)
        wave = nodes.new("ShaderNodeTexWave")
        wave.wave_type, wave.bands_direction = "BANDS", "X"
        wave.inputs["Scale"].default_value = scale
        wave.inputs["Distortion"].default_value = 2.0
        wave.inputs["Detail"].default_value = 1.0
        links.new(vec, wave.inputs["Vector"])
        mix = nodes.new("ShaderNodeMix")
        mix.data_type = "RGBA"
        mix.inputs["A"].default_value = (*colour1, 1.0)
        mix.inputs["B"].default_value = (*colour2, 1.0)
        links.new(wave.outputs["Fac"], mix.inputs["Factor"])
        wave.location, mix.location = (-450, 0), (-250, 0)
        return _vary(nodes, links, mix.outputs["Result"], vec, 0.7, vary)

    return diffuse_material(bpy, name, colour1, build)


def noise_material(bpy, name, colour1, colour2, scale):
    """Blotchy plaster / marble between two colours (3D noise in object space: any shape)."""

    def build(nodes, links):
        coord = nodes.new("ShaderNodeTexCoord")
        noise = nodes.new("ShaderNodeTexNoise")
        noise.inputs["Scale"].default_value = scale
        noise.inputs["Detail"].default_value = 6.0
        links.new(coord.outputs["Object"], noise.inputs["Vector"])
        mix = nodes.new("ShaderNodeMix")
        mix.data_type = "RGBA"
        mix.inputs["A"].default_value = (*colour1, 1.0)
        mix.inputs["B"].default_value = (*colour2, 1.0)
        ramp = nodes.new("ShaderNodeMapRange")
        ramp.inputs["From Min"].default_value = 0.35
        ramp.inputs["From Max"].default_value = 0.65
        links.new(noise.outputs["Fac"], ramp.inputs["Value"])
        links.new(ramp.outputs["Result"], mix.inputs["Factor"])
        coord.location, noise.location, ramp.location, mix.location = (-900, 0), (-650, 0), (-450, 0), (-250, 0)
        return mix.outputs["Result"]

    return diffuse_material(bpy, name, colour1, build)


# --------------------------------------------------------------------------- geometry


def _link(bpy, obj):
    if obj.name not in bpy.context.scene.collection.objects:
        for coll in list(obj.users_collection):
            coll.objects.unlink(obj)
        bpy.context.scene.collection.objects.link(obj)
    return obj


def _plane(bpy, name, centre, size, rotation, material):
    """A rectangle of size (u, v) with UVs over [0, 1]^2, rotated (Euler XYZ, radians) and moved to centre."""
    bpy.ops.mesh.primitive_plane_add(size=1.0, location=centre, rotation=rotation)
    obj = bpy.context.active_object
    obj.name = obj.data.name = name
    obj.scale = (size[0], size[1], 1.0)
    bpy.ops.object.transform_apply(location=False, rotation=False, scale=True)
    obj.data.materials.append(material)
    return _link(bpy, obj)


def _box(bpy, name, lo, hi, material):
    centre = tuple(0.5 * (a + b) for a, b in zip(lo, hi))
    bpy.ops.mesh.primitive_cube_add(size=1.0, location=centre)
    obj = bpy.context.active_object
    obj.name = obj.data.name = name
    obj.scale = tuple(b - a for a, b in zip(lo, hi))
    bpy.ops.object.transform_apply(location=False, rotation=False, scale=True)
    obj.data.materials.append(material)
    return _link(bpy, obj)


def _smooth(obj):
    for poly in obj.data.polygons:
        poly.use_smooth = True


def build_object(bpy) -> None:
    """Suzanne, a cube, a sphere and a cone on a checker plate atop a marble column."""
    red = diffuse_material(bpy, "Red", (0.75, 0.06, 0.04))
    blue = diffuse_material(bpy, "Blue", (0.04, 0.18, 0.75))
    green = diffuse_material(bpy, "Green", (0.08, 0.55, 0.10))
    orange = diffuse_material(bpy, "Orange", (0.90, 0.40, 0.05))
    plate = checker_material(bpy, "PlateChecker", (1.0, 1.0), (0.85, 0.82, 0.75), (0.08, 0.08, 0.10), 8.0, vary=0.05)
    marble = noise_material(bpy, "Marble", (0.75, 0.74, 0.70), (0.45, 0.45, 0.50), 3.0)

    floor_z = ROOM_BOUNDS[0][2]
    bpy.ops.mesh.primitive_cylinder_add(
        vertices=48,
        radius=COLUMN_RADIUS,
        depth=(PLATE_TOP - 0.1) - floor_z,
        location=(0.0, 0.0, 0.5 * (floor_z + PLATE_TOP - 0.1)),
    )
    column = _link(bpy, bpy.context.active_object)
    column.name = "Pedestal"
    column.data.materials.append(marble)
    _smooth(column)
    bpy.ops.mesh.primitive_cylinder_add(
        vertices=64, radius=PLATE_RADIUS, depth=0.1, location=(0.0, 0.0, PLATE_TOP - 0.05)
    )
    top = _link(bpy, bpy.context.active_object)
    top.name = "Plate"
    top.data.materials.append(plate)

    # Suzanne facing -Y (Blender's front view), standing on the plate.
    bpy.ops.mesh.primitive_monkey_add(size=2.0, location=(0.0, 0.05, 0.0))
    monkey = _link(bpy, bpy.context.active_object)
    monkey.name = "Suzanne"
    monkey.scale = (0.33, 0.33, 0.33)
    monkey.rotation_euler = (math.radians(-10.0), 0.0, math.radians(-15.0))
    bpy.ops.object.transform_apply(location=False, rotation=True, scale=True)
    mod = monkey.modifiers.new("subdivision", "SUBSURF")
    mod.levels = mod.render_levels = 2
    _smooth(monkey)
    monkey.data.materials.append(orange)
    lowest = min(v.co.z for v in monkey.data.vertices)
    monkey.location.z = PLATE_TOP - lowest - 0.02  # sinks 2 cm into the plate: no floating gap

    bpy.ops.mesh.primitive_cube_add(size=0.3, location=(0.45, -0.25, PLATE_TOP + 0.15), rotation=(0.0, 0.0, 0.5))
    cube = _link(bpy, bpy.context.active_object)
    cube.name = "Cube"
    cube.data.materials.append(red)
    bpy.ops.mesh.primitive_uv_sphere_add(
        radius=0.16, location=(-0.45, -0.3, PLATE_TOP + 0.16), segments=48, ring_count=24
    )
    sphere = _link(bpy, bpy.context.active_object)
    sphere.name = "Sphere"
    sphere.data.materials.append(blue)
    _smooth(sphere)
    bpy.ops.mesh.primitive_cone_add(vertices=48, radius1=0.16, depth=0.45, location=(-0.2, 0.45, PLATE_TOP + 0.225))
    cone = _link(bpy, bpy.context.active_object)
    cone.name = "Cone"
    cone.data.materials.append(green)


def build_room(bpy) -> None:
    (x0, y0, z0), (x1, y1, z1) = ROOM_BOUNDS
    w, d, h = x1 - x0, y1 - y0, z1 - z0
    cz = 0.5 * (z0 + z1)
    half = math.pi / 2
    # Each wall: its own pattern and colour (UV v runs up the wall). Scale = repeats per wall.
    walls = [
        (
            "WallNorth",
            (0.0, y1, cz),
            (w, h),
            (half, 0.0, math.pi),  # +Y: red brick
            brick_material(
                bpy, "BrickRed", (w / 1.0, h / 1.0), (0.55, 0.12, 0.07), (0.40, 0.16, 0.08), (0.75, 0.72, 0.65)
            ),
        ),
        (
            "WallSouth",
            (0.0, y0, cz),
            (w, h),
            (half, 0.0, 0.0),  # -Y: blue / cream checker
            checker_material(bpy, "CheckerBlue", (w / 1.5, h / 1.5), (0.10, 0.22, 0.55), (0.80, 0.76, 0.62), 2.0),
        ),
        (
            "WallEast",
            (x1, 0.0, cz),
            (d, h),
            (half, 0.0, half),  # +X: green wavy stripes
            wave_material(bpy, "WaveGreen", (d / 3.0, h / 3.0), (0.12, 0.42, 0.20), (0.70, 0.78, 0.45), 4.0),
        ),
        (
            "WallWest",
            (x0, 0.0, cz),
            (d, h),
            (half, 0.0, -half),  # -X: yellow / grey stone brick
            brick_material(
                bpy,
                "StoneYellow",
                (d / 1.5, h / 1.5),
                (0.70, 0.58, 0.25),
                (0.45, 0.45, 0.42),
                (0.20, 0.18, 0.16),
                brick_width=0.6,
                row_height=0.3,
                vary=0.35,
            ),
        ),
    ]
    for name, centre, size, rotation, mat in walls:
        _plane(bpy, name, centre, size, rotation, mat)
    floor = brick_material(
        bpy,
        "FloorTiles",
        (w / 2.0, d / 2.0),
        (0.50, 0.35, 0.22),
        (0.30, 0.20, 0.13),
        (0.85, 0.82, 0.75),
        brick_width=0.5,
        row_height=0.5,
        vary=0.3,
    )
    _plane(bpy, "Floor", (0.0, 0.0, z0), (w, d), (0.0, 0.0, 0.0), floor)
    ceiling = noise_material(bpy, "Ceiling", (0.80, 0.78, 0.74), (0.62, 0.62, 0.66), 1.2)
    _plane(bpy, "Ceiling", (0.0, 0.0, z1), (w, d), (math.pi, 0.0, 0.0), ceiling)

    # Features: things that stand out from their wall (a picture, a door, a poster, a shelf with boxes).
    eps = 0.02
    frame = diffuse_material(bpy, "Frame", (0.12, 0.07, 0.03))
    picture = checker_material(bpy, "Picture", (1.0, 1.0), (0.90, 0.75, 0.10), (0.60, 0.05, 0.30), 4.0, vary=0.1)
    _box(bpy, "PictureFrame", (-1.6, y1 - 0.06, 0.6), (0.2, y1 - eps, 2.2), frame)  # on the red brick wall
    _plane(bpy, "Picture", (-0.7, y1 - 0.07, 1.4), (1.5, 1.4), (half, 0.0, math.pi), picture)
    door = diffuse_material(bpy, "Door", (0.30, 0.15, 0.06))
    _box(bpy, "Door", (1.5, y0 + eps, z0), (2.7, y0 + 0.08, z0 + 2.3), door)  # on the checker wall
    knob = diffuse_material(bpy, "Knob", (0.85, 0.75, 0.20))
    _box(bpy, "DoorKnob", (2.45, y0 + 0.08, z0 + 1.05), (2.55, y0 + 0.15, z0 + 1.15), knob)
    poster = wave_material(bpy, "Poster", (1.0, 1.0), (0.05, 0.05, 0.08), (0.95, 0.45, 0.60), 6.0, vary=0.05)
    _plane(bpy, "Poster", (x1 - eps, -1.5, 0.8), (1.2, 1.8), (half, 0.0, half), poster)  # on the green wall
    shelf = diffuse_material(bpy, "Shelf", (0.55, 0.40, 0.25))
    _box(bpy, "Shelf", (x0 + eps, -1.2, 0.2), (x0 + 0.45, 1.6, 0.28), shelf)  # on the stone wall
    for k, (colour, y, size) in enumerate(
        (
            ((0.75, 0.06, 0.04), -0.9, 0.35),
            ((0.05, 0.35, 0.70), -0.3, 0.5),
            ((0.90, 0.85, 0.80), 0.3, 0.25),
            ((0.10, 0.50, 0.15), 0.9, 0.4),
        )
    ):
        _box(
            bpy,
            f"ShelfBox{k}",
            (x0 + 0.08, y, 0.28),
            (x0 + 0.08 + min(size, 0.35), y + 0.35, 0.28 + size),
            diffuse_material(bpy, f"ShelfBox{k}", colour),
        )
    _box(
        bpy,
        "Rug",
        (-2.8, 1.4, z0),
        (-0.8, 3.2, z0 + 0.02),
        checker_material(bpy, "Rug", (1.0, 1.0), (0.55, 0.10, 0.10), (0.85, 0.70, 0.30), 6.0, vary=0.05),
    )


def build_lights(bpy) -> None:
    (x0, y0, z0), (x1, y1, z1) = ROOM_BOUNDS
    # An emissive panel in the ceiling (seen in upward views) with an area light just below it.
    _plane(
        bpy,
        "CeilingPanel",
        (0.0, 0.0, z1 - 0.01),
        (2.0, 2.0),
        (math.pi, 0.0, 0.0),
        emission_material(bpy, "PanelLight", (1.0, 0.97, 0.90), 3.0),
    )
    light = bpy.data.lights.new("CeilingLight", "AREA")
    light.shape, light.size = "SQUARE", 2.0
    light.energy = 380.0
    light.color = (1.0, 0.96, 0.90)
    obj = bpy.data.objects.new("CeilingLight", light)
    obj.location = (0.0, 0.0, z1 - 0.05)
    bpy.context.scene.collection.objects.link(obj)
    # A "window" on the stone wall: a bright bluish emitter, lights the room from the side.
    _plane(
        bpy,
        "Window",
        (x0 + 0.01, 2.8, 1.6),
        (1.6, 1.4),
        (math.pi / 2, 0.0, -math.pi / 2),
        emission_material(bpy, "WindowLight", (0.75, 0.85, 1.0), 2.0),
    )
    window = bpy.data.lights.new("WindowLight", "AREA")
    window.shape, window.size, window.size_y = "RECTANGLE", 1.6, 1.4
    window.energy = 110.0
    window.color = (0.80, 0.88, 1.0)
    wobj = bpy.data.objects.new("WindowLight", window)
    wobj.location = (x0 + 0.05, 2.8, 1.6)
    wobj.rotation_euler = (0.0, math.pi / 2, 0.0)  # faces +X, into the room
    bpy.context.scene.collection.objects.link(wobj)
    # A weak warm fill from the other corner (no black corners).
    fill = bpy.data.lights.new("Fill", "POINT")
    fill.energy, fill.shadow_soft_size = 90.0, 0.5
    fill.color = (1.0, 0.85, 0.7)
    fobj = bpy.data.objects.new("Fill", fill)
    fobj.location = (3.2, -3.2, 3.0)
    bpy.context.scene.collection.objects.link(fobj)


def build(bpy) -> dict:
    """Build the room scene into the current (ideally empty) Blender file; returns its boxes."""
    scene = bpy.context.scene
    build_object(bpy)
    build_room(bpy)
    build_lights(bpy)

    black_world(bpy, scene, "RoomWorld")  # never seen: the room is closed
    camera_at(bpy, scene, (1.6, -2.1, 0.6), lens=35.0)

    render = scene.render
    render.engine = "CYCLES"
    cycles = scene.cycles
    cycles.device = "CPU"
    cycles.samples = 32
    cycles.max_bounces = 4
    cycles.diffuse_bounces = 3
    cycles.glossy_bounces = 0
    cycles.transmission_bounces = 0
    cycles.volume_bounces = 0
    cycles.transparent_max_bounces = 2
    cycles.caustics_reflective = cycles.caustics_refractive = False
    cycles.sample_clamp_indirect = 10.0  # no fireflies from the emissive panels
    render.film_transparent = False
    render.resolution_x = render.resolution_y = 200
    render.resolution_percentage = 100
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    info = {
        "object_bounds": OBJECT_BOUNDS,
        "room_bounds": ROOM_BOUNDS,
        "world_box": WORLD_BOX,
        "pedestal": {"radius": COLUMN_RADIUS, "z": (ROOM_BOUNDS[0][2], PLATE_TOP - 0.1)},
        "note": "object inside world_box; walls, floor and ceiling outside it; render with --opaque",
    }
    scene["nerf_room"] = json.dumps(info)
    return info


def check(bpy) -> None:
    """The object parts fill OBJECT_BOUNDS at most and every mesh stays inside the room."""
    from mathutils import Vector  # noqa: PLC0415

    depsgraph = bpy.context.evaluated_depsgraph_get()
    for name in ("Suzanne", "Cube", "Sphere", "Cone", "Plate"):
        ob = bpy.data.objects[name].evaluated_get(depsgraph)
        for corner in ob.bound_box:
            p = ob.matrix_world @ Vector(corner)
            for i in range(3):
                if not OBJECT_BOUNDS[0][i] - 1e-6 <= p[i] <= OBJECT_BOUNDS[1][i] + 1e-6:
                    raise AssertionError(f"{name} reaches {tuple(p)}, outside OBJECT_BOUNDS {OBJECT_BOUNDS}")
    for ob in bpy.context.scene.objects:
        if ob.type != "MESH":
            continue
        for corner in ob.bound_box:
            p = ob.matrix_world @ Vector(corner)
            for i in range(3):
                if not ROOM_BOUNDS[0][i] - 1e-3 <= p[i] <= ROOM_BOUNDS[1][i] + 1e-3:
                    raise AssertionError(f"{ob.name} reaches {tuple(p)}, outside the room {ROOM_BOUNDS}")


def save(path, bpy=None) -> Path:
    """Build the room scene in a fresh, empty Blender file and save it to `path` (.blend)."""
    return save_scene(path, build, check, bpy)


def main(argv=None) -> int:
    return scene_main(argv, "make_room_scene.py", __doc__, save)


if __name__ == "__main__":
    from blender_nerf_deform.engine.errors import run_command  # an error nobody foresaw: one line naming its log

    raise SystemExit(run_command("make_room_scene.py", main))
