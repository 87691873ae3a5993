#!/usr/bin/env python3
"""The project's embedded default scene, built procedurally with bpy (no external assets).

    python tools/default_scene.py --out default_scene.blend

A toy "signpost" that an artist would want to bend: a flat chequered BASE
block, a tall striped ARM standing on it, and a FLAG on the arm's top that
points along +X. The arm (with its flag) is the part worth deforming: bend it
over, lift it, stretch it, while the base stays pinned.

World frame (Blender's, Z up; metres):

    object  role                     bounding box (min, max)
    Base    pinned                   (-0.9, -0.6, -1.0) .. (0.9, 0.6, -0.5)
    Arm     deformable               (-0.2, -0.2, -0.5) .. (0.2, 0.2, 1.0)   6 colour bands, 0.25 high
    Flag    deformable, rides on Arm ( 0.2, -0.1,  0.55) .. (0.85, 0.1, 0.95)

`REGIONS` below holds these boxes for scripts (the demo places its pin and
handles with them): "base" (pin), "arm" (Arm + Flag: the deformable part),
"arm_root" (the bottom band of the arm, next to the base) and "arm_tip" (the
top of the arm with the flag: where a handle goes). The Arm mesh also carries
the vertex groups "root" and "tip" for the same bands. The regions are saved in
the .blend as the scene's custom property "nerf_deform_regions" (JSON).

Appearance is view-independent and needs no lights: every surface is an
Emission shader (strength 1) whose colour is a face-corner colour attribute
"Col" = a flat colour times a baked Lambert shade of the face's normal (key
light from front-right-above). So the scene looks solid, a NeRF learns it
exactly (no speculars), and Cycles converges in a few samples. The world is
black with zero strength; render with a transparent film. View transform
"Standard" so the stored colours come out as plain sRGB.

All of it sits inside [-1.5, 1.5]^3, centred near the origin, for cameras about
4 units away with a 50 mm lens on a 36 mm sensor (NeRF-synthetic-like).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

# Boxes as ((min x, min y, min z), (max x, max y, max z)), world frame.
BASE_BOUNDS = ((-0.9, -0.6, -1.0), (0.9, 0.6, -0.5))
ARM_BOUNDS = ((-0.2, -0.2, -0.5), (0.2, 0.2, 1.0))
FLAG_BOUNDS = ((0.2, -0.1, 0.55), (0.85, 0.1, 0.95))
ARM_BANDS = 6  # colour bands along the arm, 0.25 high each

REGIONS = {
    "base": {"objects": ["Base"], "bounds": BASE_BOUNDS, "role": "pin"},
    "arm": {"objects": ["Arm", "Flag"], "bounds": ((-0.2, -0.2, -0.5), (0.85, 0.2, 1.0)), "role": "deformable"},
    "arm_root": {
        "objects": ["Arm"],
        "vertex_group": "root",
        "bounds": ((-0.2, -0.2, -0.5), (0.2, 0.2, -0.25)),
        "role": "pin (keeps the arm attached to the base)",
    },
    "arm_tip": {
        "objects": ["Arm", "Flag"],
        "vertex_group": "tip",
        "bounds": ((-0.2, -0.2, 0.5), (0.85, 0.2, 1.0)),
        "role": "handle",
    },
}
SCENE_BOUNDS = ((-0.9, -0.6, -1.0), (0.9, 0.6, 1.0))

# Flat colours (linear RGB); shaded per face by `_shade`.
BASE_COLOURS = ((0.05, 0.20, 0.65), (0.80, 0.80, 0.75))  # blue / cream chequer on the top
BASE_SIDE = (0.08, 0.30, 0.55)
ARM_COLOURS = (
    (0.85, 0.05, 0.03),
    (0.95, 0.35, 0.02),
    (0.95, 0.80, 0.05),
    (0.10, 0.60, 0.08),
    (0.03, 0.55, 0.75),
    (0.45, 0.10, 0.70),
)  # red, orange, yellow, green, cyan, violet
FLAG_COLOURS = ((0.90, 0.10, 0.45), (0.95, 0.95, 0.92))  # magenta with a white stripe
KEY_LIGHT = (0.45, -0.65, 0.62)


def _shade(normal) -> float:
    length = math.sqrt(sum(c * c for c in KEY_LIGHT))
    lambert = max(0.0, sum(n * light / length for n, light in zip(normal, KEY_LIGHT)))
    return 0.45 + 0.55 * lambert


def closed_box_bmesh(bounds, divisions):
    """A closed box as a bmesh (the caller frees it): each side a grid of divisions (nx, ny, nz) quads,
    shared edges welded, normals outward."""
    import bmesh  # noqa: PLC0415

    (x0, y0, z0), (x1, y1, z1) = bounds
    nx, ny, nz = divisions
    bm = bmesh.new()

    def grid(origin, u_axis, v_axis, nu, nv):
        verts = [
            [
                bm.verts.new(tuple(origin[c] + u_axis[c] * i / nu + v_axis[c] * j / nv for c in range(3)))
                for j in range(nv + 1)
            ]
            for i in range(nu + 1)
        ]
        for i in range(nu):
            for j in range(nv):
                bm.faces.new((verts[i][j], verts[i + 1][j], verts[i + 1][j + 1], verts[i][j + 1]))

    dx, dy, dz = x1 - x0, y1 - y0, z1 - z0
    grid((x0, y0, z0), (0, dy, 0), (dx, 0, 0), ny, nx)  # bottom (-Z)
    grid((x0, y0, z1), (dx, 0, 0), (0, dy, 0), nx, ny)  # top (+Z)
    grid((x0, y0, z0), (dx, 0, 0), (0, 0, dz), nx, nz)  # front (-Y)
    grid((x0, y1, z0), (0, 0, dz), (dx, 0, 0), nz, nx)  # back (+Y)
    grid((x0, y0, z0), (0, 0, dz), (0, dy, 0), nz, ny)  # left (-X)
    grid((x1, y0, z0), (0, dy, 0), (0, 0, dz), ny, nz)  # right (+X)
    bmesh.ops.remove_doubles(bm, verts=bm.verts, dist=1e-6)
    bmesh.ops.recalc_face_normals(bm, faces=bm.faces)
    return bm


def _box(bpy, name: str, bounds, divisions, colour_of, material):
    """A closed box mesh object, each side a grid of divisions (nx, ny, nz); colour_of(centre, normal) per face."""
    bm = closed_box_bmesh(bounds, divisions)
    layer = bm.loops.layers.float_color.new("Col")
    for face in bm.faces:
        centre = tuple(face.calc_center_median())
        normal = tuple(face.normal)
        r, g, b = colour_of(centre, normal)
        s = _shade(normal)
        for loop in face.loops:
            loop[layer] = (r * s, g * s, b * s, 1.0)
    obj = object_from_bmesh(bpy, name, bm, material)
    obj.data.color_attributes.active_color = obj.data.color_attributes["Col"]
    return obj


def object_from_bmesh(bpy, name: str, bm, material):
    """A mesh object linked to the scene, made from (and freeing) a bmesh, with one material."""
    mesh = bpy.data.meshes.new(name)
    bm.to_mesh(mesh)
    bm.free()
    mesh.materials.append(material)
    obj = bpy.data.objects.new(name, mesh)
    bpy.context.scene.collection.objects.link(obj)
    return obj


def empty_node_material(bpy, name: str):
    """A new material with an empty node tree: (material, nodes, links)."""
    mat = bpy.data.materials.new(name)
    if mat.node_tree is None:  # Blender < 5.0 (5.0 always has node trees; use_nodes is deprecated)
        mat.use_nodes = True
    mat.node_tree.nodes.clear()
    return mat, mat.node_tree.nodes, mat.node_tree.links


def _emission_material(bpy):
    mat, nodes, links = empty_node_material(bpy, "DefaultSceneEmission")
    attribute = nodes.new("ShaderNodeVertexColor")
    attribute.layer_name = "Col"
    emission = nodes.new("ShaderNodeEmission")
    emission.inputs["Strength"].default_value = 1.0
    output = nodes.new("ShaderNodeOutputMaterial")
    output.target = "ALL"
    links.new(attribute.outputs["Color"], emission.inputs["Color"])
    links.new(emission.outputs["Emission"], output.inputs["Surface"])
    attribute.location, emission.location, output.location = (-400, 0), (-150, 0), (100, 0)
    return mat


def black_world(bpy, scene, name: str) -> None:
    """A black, zero-strength world for the scene (it lights nothing)."""
    world = bpy.data.worlds.new(name)
    if world.node_tree is None:
        world.use_nodes = True
    background = world.node_tree.nodes.get("Background")
    if background is not None:
        background.inputs["Color"].default_value = (0.0, 0.0, 0.0, 1.0)
        background.inputs["Strength"].default_value = 0.0
    scene.world = world


def camera_at(bpy, scene, position, lens: float) -> None:
    """The scene's camera: at `position`, looking at the origin (+Z up), a 36 mm sensor."""
    from mathutils import Matrix, Vector  # noqa: PLC0415

    cam = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    scene.collection.objects.link(cam)
    position = Vector(position)
    cam.matrix_world = Matrix.Translation(position) @ (-position).to_track_quat("-Z", "Y").to_matrix().to_4x4()
    cam.data.lens, cam.data.sensor_width = lens, 36.0
    scene.camera = cam


def _add_vertex_group(obj, name, zmin, zmax):
    group = obj.vertex_groups.new(name=name)
    indices = [v.index for v in obj.data.vertices if zmin - 1e-6 <= v.co.z <= zmax + 1e-6]
    group.add(indices, 1.0, "REPLACE")


def build(bpy) -> dict:
    """Build the scene into the current (ideally empty) Blender file; returns REGIONS."""
    scene = bpy.context.scene
    material = _emission_material(bpy)

    (bx0, by0, _), (bx1, by1, _) = BASE_BOUNDS

    def base_colour(centre, normal):
        if normal[2] > 0.5:  # chequered top, 4 x 3 tiles
            i = int((centre[0] - bx0) / (bx1 - bx0) * 4)
            j = int((centre[1] - by0) / (by1 - by0) * 3)
            return BASE_COLOURS[(i + j) % 2]
        return BASE_SIDE

    (_, _, az0), (_, _, az1) = ARM_BOUNDS

    def arm_colour(centre, normal):
        band = min(ARM_BANDS - 1, max(0, int((centre[2] - az0) / (az1 - az0) * ARM_BANDS)))
        return ARM_COLOURS[band]

    (_, _, fz0), (_, _, fz1) = FLAG_BOUNDS

    def flag_colour(centre, normal):
        return FLAG_COLOURS[1 if abs(centre[2] - 0.5 * (fz0 + fz1)) < 0.125 * (fz1 - fz0) else 0]  # white middle stripe

    _box(bpy, "Base", BASE_BOUNDS, (4, 3, 1), base_colour, material)
    arm = _box(bpy, "Arm", ARM_BOUNDS, (2, 2, ARM_BANDS * 2), arm_colour, material)
    _box(bpy, "Flag", FLAG_BOUNDS, (4, 1, 8), flag_colour, material)
    band = (az1 - az0) / ARM_BANDS
    _add_vertex_group(arm, "root", az0, az0 + band)
    _add_vertex_group(arm, "tip", REGIONS["arm_tip"]["bounds"][0][2], az1)

    # A black, zero-strength world: nothing lights the scene, the emission is the look.
    black_world(bpy, scene, "DefaultSceneWorld")
    # A camera so that opening the file (or `blender -b file -f 1`) shows the toy.
    camera_at(bpy, scene, (2.6, -2.9, 1.3), lens=50.0)

    render = scene.render
    render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = 16
    scene.cycles.use_denoising = False
    scene.cycles.max_bounces = 0  # emission seen directly: no bounces needed
    render.film_transparent = True
    render.resolution_x = render.resolution_y = 200
    render.resolution_percentage = 100
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene["nerf_deform_regions"] = json.dumps(REGIONS)
    return REGIONS


def check(bpy) -> None:
    """Assert the built objects fill exactly the documented boxes (guards the REGIONS table)."""
    for name, bounds in (("Base", BASE_BOUNDS), ("Arm", ARM_BOUNDS), ("Flag", FLAG_BOUNDS)):
        obj = bpy.data.objects[name]
        coords = [obj.matrix_world @ v.co for v in obj.data.vertices]
        lo = tuple(min(c[i] for c in coords) for i in range(3))
        hi = tuple(max(c[i] for c in coords) for i in range(3))
        for got, want in zip(lo + hi, bounds[0] + bounds[1]):
            if abs(got - want) > 1e-5:
                raise AssertionError(f"{name}: bounds {lo}..{hi}, documented {bounds}")


def save_scene(path, build_scene, check_scene, bpy=None) -> Path:
    """Build a procedural scene (`build_scene(bpy)`, checked by `check_scene(bpy)`) in a fresh, empty
    Blender file and save it to `path` (.blend). What every scene tool here writes with."""
    if bpy is None:
        import bpy  # noqa: PLC0415
    path = Path(path).resolve()
    path.parent.mkdir(parents=True, exist_ok=True)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    build_scene(bpy)
    check_scene(bpy)
    # Blender writes to "<file>@" and renames, so the .blend is never half-written.
    bpy.ops.wm.save_as_mainfile(filepath=str(path), compress=False)
    return path


def scene_main(argv, prog: str, doc: str, save_to) -> int:
    """The scene tools' command line: `--out FILE.blend`, checked, then `save_to(path)`."""
    parser = argparse.ArgumentParser(prog=prog, description=doc.split("\n\n")[0])
    parser.add_argument("--out", required=True, type=Path, help="the .blend to write")
    args = parser.parse_args(argv)
    if args.out.suffix != ".blend":
        print(f"error: --out must end in .blend, got {args.out}", file=sys.stderr)
        return 2
    if args.out.exists() and args.out.is_dir():
        print(f"error: --out is a folder: {args.out}", file=sys.stderr)
        return 2
    print(f"wrote {save_to(args.out)}", flush=True)
    return 0


def save(path, bpy=None) -> Path:
    """Build the default scene in a fresh, empty Blender file and save it to `path` (.blend)."""
    return save_scene(path, build, check, bpy)


def main(argv=None) -> int:
    return scene_main(argv, "default_scene.py", __doc__, save)


if __name__ == "__main__":
    raise SystemExit(main())
