"""A small Python API over the operators, for scripts and `blender -b --python` pipelines.

    from blender_nerf_deform.addon import api          # (bl_ext.<repo>.blender_nerf_deform.addon as an extension)

    nerf = api.train("/data/fox", seconds=600)          # or api.load("run/nerf.ckpt"),
                                                        # or api.train(api.capture_dataset(objects=[cube]))
                                                        # or api.import_photos("/photos/statue", seconds=600)
    region = api.add_edit_region(nerf, center=(1.6, -0.5, 0.1), size=(4, 5, 3), rotation_euler=(1.66, 0, 1.08))
    surface = api.extract(nerf, resolution=192, pick=(1.7, -1.5, 0.55))
    cage = api.build_cage(nerf)
    head = api.vertices_near(surface, (1.7, -1.5, 0.55), 0.75)
    handle = api.add_handle(nerf, head)
    handle.rotation_euler.z = 0.5                       # then render: bpy.ops.render.render(write_still=True)
    volume = api.bake_volume(nerf, "/out/vdb", frames=(1, 24))  # or as OpenVDB, for Cycles and EEVEE

Every function runs the add-on's operator (so a script does exactly what the buttons do), blocks
until the worker answers, and raises `RuntimeError` with the operator's own message when it
fails (a bad path, a region outside the box, ...). Coordinates are in the NeRF's frame (its
transforms.json's world), as the engine's command line takes them.
"""

from __future__ import annotations

import bpy

import numpy as np
from mathutils import Euler, Vector

from .data.properties import Role, owning_nerf
from .export.bake_volume import volume_of


def _run(operator, what: str, **kwargs):
    result = operator(**kwargs)
    if result != {"FINISHED"}:
        raise RuntimeError(f"{what} did not finish ({', '.join(sorted(result))})")


def _activate(obj) -> None:
    view_layer = bpy.context.view_layer
    if view_layer.objects.active is not None and view_layer.objects.active.mode != "OBJECT":
        bpy.ops.object.mode_set(mode="OBJECT")
    for other in bpy.context.selected_objects:
        other.select_set(False)
    obj.select_set(True)
    view_layer.objects.active = obj


def _nerf(obj) -> bpy.types.Object:
    nerf = owning_nerf(obj)
    if nerf is None:
        raise RuntimeError(f"{getattr(obj, 'name', obj)!r} is not a NeRF object or one of its parts")
    return nerf


def load(checkpoint: str) -> bpy.types.Object:
    """Load NeRF: the NeRF object of a checkpoint."""
    _run(bpy.ops.nerf_deform.load_nerf, "Load NeRF", filepath=str(checkpoint))
    return bpy.context.active_object


def capture_dataset(
    out: str = "",
    objects=None,
    count: int = 100,
    test_count: int = 0,
    radius: float = 0.0,
    resolution=(200, 200),
    lens: float = 50.0,
    seed: int = 0,
    hemisphere: bool = False,
    min_elevation: float | None = None,
    engine: str = "KEEP",
    samples: int = 16,
    transparent: bool = True,
    selected_only: bool = True,
) -> str:
    """Capture Dataset of `objects` (None: the selected objects), blocking: the dataset folder.

    Cameras around the objects (radius 0: automatic), rendered by the scene's engine (engine="KEEP")
    or Cycles on the CPU ("CYCLES", with `samples`); `min_elevation` (degrees) keeps the cameras
    above it. `out` empty: //nerf_datasets/<scene name>. The folder is then the Train panel's
    Dataset, so `train(capture_dataset(...))` is the whole way from a scene to a NeRF."""
    if objects is not None:
        objects = list(objects)
        if not objects:
            raise RuntimeError("Capture Dataset: no objects given")
        _activate(objects[0])
        for obj in objects[1:]:
            obj.select_set(True)
    _run(
        bpy.ops.nerf_deform.capture_dataset,
        "Capture Dataset",
        output=str(out),
        count=count,
        test_count=test_count,
        radius=radius,
        resolution=tuple(resolution),
        lens=lens,
        seed=seed,
        hemisphere=hemisphere,
        use_min_elevation=min_elevation is not None,
        min_elevation=0.0 if min_elevation is None else float(min_elevation),
        engine=engine,
        samples=samples,
        transparent=transparent,
        selected_only=selected_only,
    )
    import os

    return os.path.normpath(bpy.path.abspath(bpy.context.scene.nerf_deform_training.data))


def train(
    data: str,
    run_folder: str = "",
    seconds: float = 300.0,
    steps: int = 0,
    device: str = "auto",
    downscale: int = 1,
    resume: bool = False,
    masks: str = "auto",
) -> bpy.types.Object:
    """Train NeRF on a dataset folder (blocking), then the NeRF object that shows it. `masks`: what the dataset's
    masks mean ("object": the object alone, "ignore": pixels to skip, "auto": by their shape)."""
    _run(
        bpy.ops.nerf_deform.train_nerf,
        "Train NeRF",
        data=str(data),
        run_folder=str(run_folder),
        seconds=seconds,
        steps=steps,
        device=device,
        downscale=downscale,
        resume=resume,
        masks=masks,
    )
    import os

    from .data.paths import default_run_folder

    ckpt = os.path.join(
        os.path.abspath(bpy.path.abspath(run_folder))
        if run_folder
        else default_run_folder(os.path.abspath(bpy.path.abspath(data))),
        "nerf.ckpt",
    )
    return _showing(ckpt, "Train NeRF")


def _showing(ckpt: str, what: str) -> bpy.types.Object:
    """The NeRF object that shows the checkpoint `ckpt`."""
    from .data.paths import same_file

    for obj in bpy.data.objects:
        if (
            obj.nerf_deform.role == Role.NERF
            and obj.nerf_deform.checkpoint
            and same_file(bpy.path.abspath(obj.nerf_deform.checkpoint), ckpt)
        ):
            return obj
    raise RuntimeError(f"{what} finished but no NeRF object shows {ckpt}")


def import_photos(
    photos: str,
    run_folder: str = "",
    seconds: float = 300.0,
    steps: int = 0,
    device: str = "auto",
    downscale: int = 1,
    matcher: str = "exhaustive",
) -> bpy.types.Object:
    """Import Photos (blocking): the photos' cameras by structure from motion into <run folder>/dataset,
    a NeRF trained on them (run folder default: //nerf_runs/<photos folder name>), then its NeRF object."""
    import os

    from .data.paths import default_run_folder

    _run(
        bpy.ops.nerf_deform.import_photos,
        "Import Photos",
        photos=str(photos),
        run_folder=str(run_folder),
        seconds=seconds,
        steps=steps,
        device=device,
        downscale=downscale,
        matcher=matcher,
    )
    run = (
        os.path.abspath(bpy.path.abspath(str(run_folder)))
        if run_folder
        else default_run_folder(os.path.abspath(bpy.path.abspath(str(photos))))
    )
    return _showing(os.path.join(run, "nerf.ckpt"), "Import Photos")


def add_edit_region(nerf, center, size, rotation_euler=(0.0, 0.0, 0.0)) -> bpy.types.Object:
    """Add Edit Region, placed at `center` with side lengths `size` and an XYZ Euler rotation (NeRF frame)."""
    nerf = _nerf(nerf)
    _activate(nerf)
    _run(bpy.ops.nerf_deform.add_edit_region, "Add Edit Region")
    region = bpy.context.active_object
    region.location = Vector(center)
    region.rotation_euler = Euler(rotation_euler, "XYZ")
    region.scale = Vector(size) * (0.5 / region.empty_display_size)  # a cube Empty spans +-display size
    bpy.context.view_layer.update()
    return region


def extract(nerf, resolution: int | None = None, threshold: float | None = None, pick=None) -> bpy.types.Object:
    """Extract Mesh (inside the NeRF's edit region when it has one; with `pick`, a point in the NeRF's
    frame, only the part connected to it): the surface mesh object."""
    nerf = _nerf(nerf)
    s = nerf.nerf_deform
    if resolution is not None:
        s.resolution = int(resolution)
    if threshold is not None:
        s.threshold = float(threshold)
    s.pick_object = pick is not None
    if pick is not None:
        bpy.context.scene.cursor.location = nerf.matrix_world @ Vector(pick)
    _activate(nerf)
    _run(bpy.ops.nerf_deform.extract_mesh, "Extract Mesh")
    return s.surface


def build_cage(nerf, pin_cut: bool = True) -> bpy.types.Object:
    """Build Cage (pinned where the edit region cut the scene, unless `pin_cut` is False): the cage object."""
    nerf = _nerf(nerf)
    nerf.nerf_deform.pin_cut = pin_cut
    _activate(nerf)
    _run(bpy.ops.nerf_deform.build_cage, "Build Cage")
    return nerf.nerf_deform.cage


def vertices_near(surface, point, radius: float) -> np.ndarray:
    """Indices of the surface mesh's vertices within `radius` of `point` (NeRF frame)."""
    co = np.empty(3 * len(surface.data.vertices))
    surface.data.vertices.foreach_get("co", co)
    return np.flatnonzero(np.linalg.norm(co.reshape(-1, 3) - np.asarray(point, dtype=np.float64), axis=1) <= radius)


def _select(surface, indices) -> None:
    import bmesh

    _activate(surface)
    bpy.ops.object.mode_set(mode="EDIT")
    bm = bmesh.from_edit_mesh(surface.data)
    bm.verts.ensure_lookup_table()
    for element in (*bm.faces, *bm.edges, *bm.verts):
        element.select = False
    count = len(bm.verts)
    for i in np.asarray(indices, dtype=np.int64).ravel():
        if not 0 <= i < count:
            bpy.ops.object.mode_set(mode="OBJECT")
            raise RuntimeError(f"vertex {i} is not a vertex of {surface.name} (0..{count - 1})")
        bm.verts[int(i)].select = True
    bmesh.update_edit_mesh(surface.data)


def _on_surface(nerf, indices, operator, what):
    nerf = _nerf(nerf)
    surface = nerf.nerf_deform.surface
    if surface is None:
        raise RuntimeError(f"{nerf.name} has no extracted mesh: run extract() first")
    _select(surface, indices)
    try:
        _run(operator, what)
        made = bpy.context.active_object
    finally:
        if surface.mode == "EDIT":
            bpy.context.view_layer.objects.active = surface
            bpy.ops.object.mode_set(mode="OBJECT")
    return made


def add_handle(nerf, vertex_indices) -> bpy.types.Object:
    """Add Handle on these vertices of the NeRF's extracted mesh: the handle Empty (move, turn, key it)."""
    return _on_surface(nerf, vertex_indices, bpy.ops.nerf_deform.add_handle, "Add Handle")


def pin(nerf, vertex_indices) -> None:
    """Pin Selection: these vertices of the extracted mesh stay where they are."""
    _on_surface(nerf, vertex_indices, bpy.ops.nerf_deform.pin_selection, "Pin Selection")


def place_cursor_on_nerf(nerf, origin, direction) -> Vector:
    """Place 3D Cursor on NeRF along a world-space ray; returns the cursor's location."""
    _activate(_nerf(nerf))
    _run(
        bpy.ops.nerf_deform.place_cursor_on_nerf,
        "Place 3D Cursor on NeRF",
        origin=tuple(origin),
        direction=tuple(direction),
    )
    return bpy.context.scene.cursor.location.copy()


def bake_volume(
    nerf,
    folder: str,
    resolution: int = 256,
    extent: str = "NERF",
    region=None,
    frames=None,
    shading: str = "EMISSION",
    supersample: int = 1,
) -> bpy.types.Object:
    """Bake Volume: the NeRF as posed, sampled on a grid of `resolution` voxels along the longest side of
    its box ("NERF"), of the cage as posed ("CAGE") or of an edit region ("REGION": `region`, the Empty or
    its name, needed when the NeRF has several), written to `folder` as <NeRF>_<frame>.vdb: the current
    frame, or each of `frames` = (start, end) (a farm bakes ranges in parallel: a frame's file is the same
    whichever process bakes it). `shading`: "EMISSION" (as the NeRF renders) or "LIT" (scene lights light
    it, it casts shadows). Returns the Volume object that plays the files."""
    nerf = _nerf(nerf)
    _activate(nerf)
    kwargs = {
        "directory": str(folder),
        "resolution": int(resolution),
        "extent": extent,
        "shading": shading,
        "supersample": int(supersample),
        "region": getattr(region, "name", region) or "",
    }
    if frames is not None:
        start, end = frames
        kwargs.update(frames="RANGE", frame_start=int(start), frame_end=int(end))
    _run(bpy.ops.nerf_deform.bake_volume, "Bake Volume", **kwargs)
    return volume_of(nerf)
