"""Bake Volume: the NeRF as posed at a frame (or each frame of a range) written as OpenVDB, and a
Volume object that plays it, so Cycles and EEVEE render the edited NeRF with the scene's lights,
meshes and shadows, and other applications read it.

Each frame is one worker request (`bake_volume`, with the same pose a render sends: handles, the
modifier-deformed cage, or rest), answered with the voxels that hold anything; `volume_file`
writes them. All or nothing: every frame's file is written to a temporary file beside its place
(engine/files.py, StagedFiles), and they take their places together when every frame is done;
Esc, an error of any kind, or the NeRF deleted or renamed meanwhile leave the output folder as it
was (a previous bake included, no folder made) and the frame shown restored. Before any work, each
frame's file must be free or this NeRF's own earlier bake (its grids name their NeRF): a folder
there, another NeRF's bake or anything else is left alone, with an error saying so.

`<NeRF>_<frame>.vdb`, four digits, so Blender reads a range as a sequence. <NeRF> is the object's
name where a file name can keep it whole (letters, digits, spaces, `-_.`); otherwise the characters
it cannot keep become `_` and a short hash of the exact name follows, so two objects never share a
file ("Statue/A" and "Statue_A"). A frame's file is the same bytes whichever process baked it, so a
farm can bake ranges in parallel (`-s/-e` with `api.bake_volume`). Frames run from 0 to Blender's last
(a volume sequence reads no minus sign); the folder starts with `//` (the .blend's) or is absolute,
never relative to Blender's working directory. The Volume object is marked as the bake's and follows
its NeRF through renames, so a re-bake never adds a second one.

Units: the grids' transform is in the NeRF's frame and the Volume object is a child of the NeRF
object with no offset; density is written per unit length of the Blender world (the NeRF's density
divided by the NeRF object's scale at that frame), so a scaled NeRF renders the same. Colour is
scene-linear (the NeRF's sRGB colours decoded), as Blender's renders are.
"""

from __future__ import annotations

import hashlib
import os
import re
from pathlib import Path

import bpy

import numpy as np

from ...engine.bend.baked_volume import MAX_RESOLUTION
from ...engine.errors import EngineError
from ...engine.files import StagedFiles, check_writable
from ...engine.memory import available_memory, gib
from ...engine.service.requests import BakeVolumeRequest, PoseKind
from ..data.cage_store import has_cage, load_cage
from ..data.images import srgb_to_linear
from ..data.properties import VOLUME_EXTENTS, VOLUME_FRAMES, VOLUME_SHADINGS, OnNeRF, alive, is_deleted, owning_nerf
from ..edit.regions import region_dict, regions_of
from ..render.frame import nerf_pose, render_warnings
from ..worker.jobs import WorkerOperator, WorkerRequest
from .volume_file import VolumeFileError, check_vdb_replaceable, openvdb_module, scaled_density, write_vdb
from .volume_material import volume_material


def volume_file_stem(nerf_name: str) -> str:
    """The file-name part of a NeRF's volumes: its name when a file name keeps it whole, else the name
    with `_` for what a file name cannot keep, and a hash of the exact name (never two NeRFs alike)."""
    safe = "".join(c if c.isalnum() or c in "-_. " else "_" for c in nerf_name)
    # A name kept whole never ends as a hashed one does ("a_b-3ec69c85" is "a/b"'s): that one is hashed too.
    if safe == nerf_name and safe.strip(" .") == safe and safe and not re.search(r"-[0-9a-f]{8}$", safe):
        return safe
    digest = hashlib.sha1(nerf_name.encode("utf-8", "surrogatepass")).hexdigest()[:8]
    return f"{safe.strip(' .') or 'NeRF'}-{digest}"


def volume_file_name(nerf_name: str, frame: int) -> str:
    return f"{volume_file_stem(nerf_name)}_{frame:04d}.vdb"


def world_scale(matrix_world) -> float:
    """World units per NeRF unit (the cube root of the volume scale: a non-uniform scale has no single
    factor; this one keeps the volume's total optical mass)."""
    m = np.array(matrix_world, dtype=np.float64)[:3, :3]
    return float(abs(np.linalg.det(m)) ** (1.0 / 3.0))


class NERFDEFORM_OT_bake_volume(WorkerOperator, OnNeRF, bpy.types.Operator):
    """Bake the NeRF as posed (handles, cage modifiers, or rest) to OpenVDB and add a Volume object that
    plays it, so Cycles and EEVEE render it with the scene's lights, meshes and shadows"""

    bl_idname = "nerf_deform.bake_volume"
    bl_label = "Bake Volume"
    bl_options = {"REGISTER", "UNDO"}

    directory: bpy.props.StringProperty(
        name="Folder",
        subtype="DIR_PATH",
        default="//nerf_volume/",
        description="Where the .vdb files go (// is the .blend's folder); one file per frame, <NeRF>_<frame>.vdb",
    )
    resolution: bpy.props.IntProperty(
        name="Resolution",
        default=256,
        soft_min=16,
        soft_max=512,
        description="Voxels along the longest side of the baked box (cubic voxels)",
    )
    extent: bpy.props.EnumProperty(name="Box", items=VOLUME_EXTENTS, default="NERF")
    region: bpy.props.StringProperty(
        name="Region", default="", description="The edit region to bake (Box: Edit Region)"
    )
    frames: bpy.props.EnumProperty(name="Frames", items=VOLUME_FRAMES, default="CURRENT")
    frame_start: bpy.props.IntProperty(
        name="Start", default=1, description="First frame of the range (Frames: Frame Range); default the scene's"
    )
    frame_end: bpy.props.IntProperty(
        name="End", default=250, description="Last frame of the range (Frames: Frame Range); default the scene's"
    )
    shading: bpy.props.EnumProperty(name="Material", items=VOLUME_SHADINGS, default="EMISSION")
    supersample: bpy.props.IntProperty(
        name="Supersample",
        default=1,
        min=1,
        max=4,
        description="Points averaged per voxel along each axis (1: its centre)",
    )

    # The chain: one request per frame; apply stages the frame's file and asks for the next.
    def request(self, context):
        nerf = owning_nerf(context.active_object)
        self._nerf_name, self._nerf_uid = nerf.name, nerf.session_uid
        if not 1 <= self.resolution <= MAX_RESOLUTION:
            raise ValueError(
                f"the resolution must be from 1 to {MAX_RESOLUTION} voxels along the box's longest side, "
                f"got {self.resolution}"
            )
        scene = context.scene
        if self.frames == "RANGE":
            # Unset (a script's call), the range is the scene's, as the Frame Range panel shows it.
            if not self.properties.is_property_set("frame_start"):
                self.frame_start = scene.frame_start
            if not self.properties.is_property_set("frame_end"):
                self.frame_end = scene.frame_end
            if self.frame_end < self.frame_start:
                raise ValueError(f"the frame range ends ({self.frame_end}) before it starts ({self.frame_start})")
            self._frames = list(range(self.frame_start, self.frame_end + 1))
        else:
            self._frames = [scene.frame_current]
        # Blender reads no minus sign in a volume sequence's frame numbers (frame -1's file would play at
        # frame 1), and a scene goes to no frame beyond MAXFRAME (frame_set would bake that one instead).
        last = scene.bl_rna.properties["frame_current"].hard_max
        for frame in (self._frames[0], self._frames[-1]):
            if frame < 0:
                raise ValueError(
                    f"frame {frame} cannot be baked: Blender reads no negative frame number in a volume "
                    f"sequence (its file would play at frame {-frame}); bake frames from 0 to {last}"
                )
            if frame > last:
                raise ValueError(
                    f"frame {frame} cannot be baked: Blender's frames end at {last}; bake frames from 0 to {last}"
                )
        self._region = self._chosen_region(nerf) if self.extent == "REGION" else None
        if not self.directory or (self.directory.startswith("//") and not bpy.data.filepath):
            raise ValueError("save the .blend first, or give the bake an absolute folder: // is the .blend's folder")
        if not self.directory.startswith("//") and not os.path.isabs(os.path.expanduser(self.directory)):
            # Relative to Blender's working directory, which the artist neither sees nor chose.
            raise ValueError(
                f"the folder {self.directory!r} is relative: start it with // for the .blend's folder "
                "(//" + self.directory.lstrip("./") + "), or give an absolute folder"
            )
        self._out = Path(os.path.expanduser(bpy.path.abspath(self.directory)))
        self._check_memory()
        openvdb_module()  # no OpenVDB: say so before any work
        self._targets = {frame: self._out / volume_file_name(nerf.name, frame) for frame in self._frames}
        self._check_output()
        self._staged = StagedFiles()
        self._frame_before = scene.frame_current
        self._written: list[int] = []
        self._warnings: list[str] = []
        self._next = 0
        return self._frame_request(context)

    def _check_output(self) -> None:
        """Every frame's file must be free or this NeRF's own earlier bake, and the folder writable."""
        if self._out.exists() and not self._out.is_dir():
            raise ValueError(f"cannot write to {self._out}: it is a file, not a folder")
        existing = self._out
        while not existing.exists() and existing.parent != existing:
            existing = existing.parent
        if not existing.is_dir():
            raise ValueError(f"cannot write to {self._out}: {existing} is not a folder")
        try:
            check_writable(self._out, folder=True)  # a read-only folder: said before any frame is baked
            for target in self._targets.values():
                check_vdb_replaceable(target, owner=self._nerf_name)
        except (VolumeFileError, EngineError) as error:
            raise ValueError(str(error)) from None

    def _nerf(self) -> bpy.types.Object:
        """The NeRF being baked; ValueError when it was deleted or renamed since the bake started (its
        files are named after it)."""
        obj = bpy.data.objects.get(self._nerf_name)
        if obj is not None and obj.session_uid == self._nerf_uid and not is_deleted(obj):
            return obj
        renamed = next((o for o in bpy.data.objects if o.session_uid == self._nerf_uid and not is_deleted(o)), None)
        if renamed is not None:
            raise ValueError(
                f"NeRF object '{self._nerf_name}' was renamed to '{renamed.name}' while it was baked; "
                "nothing was written: bake it again"
            )
        raise ValueError(f"NeRF object '{self._nerf_name}' was deleted while it was baked; nothing was written")

    def _chosen_region(self, nerf) -> dict:
        regions = regions_of(nerf)
        if not regions:
            raise ValueError(f"{nerf.name} has no edit region: add one, or bake the NeRF's box or the posed cage")
        if self.region:
            named = [r for r in regions if r.name == self.region]
            if not named:
                raise ValueError(
                    f"{self.region!r} is not an edit region of {nerf.name} "
                    f"(its regions: {', '.join(r.name for r in regions)})"
                )
            return region_dict(named[0], nerf)
        active = bpy.context.active_object
        if len(regions) > 1 and active in regions:
            return region_dict(active, nerf)
        if len(regions) > 1:
            raise ValueError(
                f"{nerf.name} has {len(regions)} edit regions ({', '.join(r.name for r in regions)}): "
                "select the one to bake, or name it (Region)"
            )
        return region_dict(regions[0], nerf)

    def _check_memory(self) -> None:
        """Blender's side of a frame (the worker checks its own): the sparse voxels it receives and the
        dense slabs and grids it writes from them, at worst every voxel; refused before any work."""
        voxels = float(self.resolution) ** 3
        need = voxels * (28 + 16)
        free = available_memory()
        if free is not None and need > free:
            raise ValueError(
                f"a {self.resolution}^3 volume needs about {gib(need)} of memory, but only {gib(free)} "
                "is available: bake it at a lower resolution, or over a smaller box (an edit region, "
                "or the posed cage)"
            )

    def _frame_request(self, context) -> WorkerRequest:
        frame = self._frames[self._next]
        self.current_request = None  # a frame that cannot be posed is reported as itself, not the one before
        try:
            scene = context.scene
            scene.frame_set(frame)  # its handlers, drivers and scripts may delete or rename the NeRF
            nerf = self._nerf()
            depsgraph = context.evaluated_depsgraph_get()
            posed = nerf_pose(depsgraph, nerf)
            extent: object = "nerf"
            if self.extent == "REGION":
                extent = self._region
            elif self.extent == "CAGE":
                extent = "cage" if posed.pose.kind != PoseKind.REST else self._rest_cage_box(nerf)
            self._scale = world_scale(nerf.evaluated_get(depsgraph).matrix_world)
        except ValueError as error:
            raise ValueError(f"frame {frame}: {error}") from None
        request = BakeVolumeRequest(posed.checkpoint, posed.pose, extent, self.resolution, self.supersample)
        params, arrays = request.to_wire()
        stage = (
            f"frame {frame} ({self._next + 1} of {len(self._frames)})" if len(self._frames) > 1 else f"frame {frame}"
        )
        return WorkerRequest("bake_volume", params, arrays, stage, posed.shared)

    def _rest_cage_box(self, nerf) -> dict:
        cage = alive(nerf.nerf_deform.cage)
        if cage is None or not has_cage(cage.data):
            raise ValueError(f"{nerf.name} has no cage: build one, or bake the NeRF's box or an edit region")
        vertices, _tets = load_cage(cage.data)
        lo, hi = vertices.min(0), vertices.max(0)
        return {
            "center": [float(x) for x in 0.5 * (lo + hi)],
            "size": [float(x) for x in hi - lo],
            "rotation_euler": [0.0, 0.0, 0.0],
        }

    def apply(self, context, result, arrays):
        frame = self._frames[self._next]
        try:
            self._nerf()
            self._warnings.extend(render_warnings(self._nerf_name, frame, result))
            write_vdb(
                self._staged.temporary(self._targets[frame]),
                result["shape"],
                np.asarray(result["index_to_nerf"], dtype=np.float64),
                arrays["index"],
                scaled_density(arrays["density"], self._scale, f"frame {frame}: NeRF object '{self._nerf_name}'"),
                srgb_to_linear(np.clip(arrays["color"], 0.0, 1.0)),
                where=f"frame {frame}",
                owner=self._nerf_name,
            )
        except (ValueError, EngineError) as error:  # VolumeFileError is a ValueError
            return self._fail(error)
        self._written.append(frame)
        print(f"{self.bl_label}: frame {frame}: {result['active_voxels']} voxels, {result['seconds']:.1f} s")
        self._next += 1
        if self._next < len(self._frames):
            try:
                return self._frame_request(context)
            except ValueError as error:  # the next frame cannot be posed (a zero scale keyed on the NeRF, ...)
                return self._fail(error)
        return self._finish_bake(context)

    def _finish_bake(self, context) -> set[str]:
        try:
            nerf = self._nerf()
            self._staged.commit()
        except (ValueError, EngineError) as error:
            return self._fail(error)
        context.scene.frame_set(self._frame_before)
        first = self._targets[self._written[0]]
        volume = volume_object(context, nerf, first, self._written, self.shading)
        for line in self._warnings:
            self.report({"WARNING"}, line)
        self.report(
            {"INFO"},
            f"{volume.name}: baked {len(self._written)} frame{'s' if len(self._written) > 1 else ''} to {self._out}",
        )
        return {"FINISHED"}

    def _fail(self, error: Exception) -> set[str]:
        self._abandon()
        return super()._fail(error)

    def abandon(self, context) -> None:
        self._abandon()

    def _abandon(self) -> None:
        """Nothing of a bake that did not finish stays: its staged files (and any folder it made) go, the
        frame shown comes back."""
        staged = getattr(self, "_staged", None)
        if staged is not None:
            staged.discard()
            self._staged = None
        before = getattr(self, "_frame_before", None)
        if before is not None and bpy.context.scene.frame_current != before:
            bpy.context.scene.frame_set(before)


VOLUME_MARK = "nerf_deform_volume"  # object ID property: made by Bake Volume for its parent NeRF


def volume_of(nerf) -> bpy.types.Object | None:
    """The Volume object an earlier bake made for `nerf`, if any: a child of it that Bake Volume marked
    (whatever either is named now: a NeRF renamed since keeps one volume, not two that render it twice),
    or, from before the mark, one named after it."""
    name = f"{nerf.name} Volume"
    children = [o for o in nerf.children if o.type == "VOLUME" and o.library is None and not is_deleted(o)]
    mine = [o for o in children if o.get(VOLUME_MARK)] or [o for o in children if o.name.startswith(name)]
    return min(mine, key=lambda o: (o.name != name, o.name)) if mine else None


def volume_object(context, nerf, first_file: Path, frames: list[int], shading: str) -> bpy.types.Object:
    """The NeRF's Volume object (made once, then reused), reading `first_file` (and its sequence),
    a child of the NeRF with no offset, with the material `shading` asks for; the NeRF's own render
    hidden from other engines' renders is left to the artist."""
    name = f"{nerf.name} Volume"
    obj = volume_of(nerf)  # an object of that name that is not this NeRF's volume is left alone
    if obj is None:
        volume = bpy.data.volumes.new(name)
        obj = bpy.data.objects.new(name, volume)
        for collection in nerf.users_collection:
            collection.objects.link(obj)
    elif obj.name != name and name not in bpy.data.objects:  # the NeRF was renamed: its volume follows
        obj.name = name
    obj[VOLUME_MARK] = True
    volume = obj.data
    path = bpy.path.relpath(str(first_file)) if bpy.data.filepath else str(first_file)
    volume.filepath = path  # setting it (even to the same path) unloads the grids: a re-bake shows
    volume.is_sequence = len(frames) > 1
    if volume.is_sequence:
        volume.frame_start, volume.frame_duration, volume.frame_offset = frames[0], len(frames), frames[0] - 1
        volume.sequence_mode = "CLIP"
    else:
        volume.frame_offset = 0
    obj.parent = nerf
    obj.matrix_parent_inverse.identity()
    obj.matrix_basis.identity()
    material = volume_material(shading)
    if volume.materials:
        volume.materials[0] = material
    else:
        volume.materials.append(material)
    return obj


_classes = (NERFDEFORM_OT_bake_volume,)
register, unregister = bpy.utils.register_classes_factory(_classes)
