"""The checkpoint path the .blend stores survives every way of saving it, as a farm finds it.

- The first save of a file made unsaved (Load NeRF, then Save As) stores the path relative to it.
- Save As into another folder re-bases a relative path on the new folder (Blender's own relative
  remap rewrites its images' paths, not add-on properties).
- Save Copy writes the copy's paths into the copy and leaves the open file's alone.

Each saved file is then opened in a fresh process, from another working directory, after the whole
project folder moved, and renders a frame with the NeRF Deform engine: it must find the checkpoint.
"""

import shutil

import pytest
from fixtures.processes import SCENE_HELPERS, assert_clean, run_blender

_AUTHOR = """
project = {project!r}
assert not bpy.data.filepath
assert bpy.ops.nerf_deform.load_nerf(filepath=project + "/run/nerf.ckpt") == {{"FINISHED"}}
nerf = bpy.context.active_object
camera()


def stored(label):
    print(label, nerf.nerf_deform.checkpoint.replace("\\\\", "/"))


stored("UNSAVED")
bpy.ops.wm.save_as_mainfile(filepath=project + "/shot.blend")  # the first save
stored("SHOT")
bpy.ops.wm.save_as_mainfile(filepath=project + "/versions/shot_v2.blend")  # another folder
stored("V2")
bpy.ops.wm.save_as_mainfile(filepath=project + "/deep/er/copy.blend", copy=True)
stored("COPIED")
bpy.ops.wm.save_mainfile()  # again where it is
stored("RESAVED")
"""

_FARM = """
for name in ("shot.blend", "versions/shot_v2.blend", "deep/er/copy.blend"):
    bpy.ops.wm.open_mainfile(filepath={project!r} + "/" + name)
    (nerf,) = [o for o in bpy.data.objects if o.nerf_deform.role == "NERF"]
    image = render({out!r} + "/" + name.replace("/", "_") + ".png")
    print("RENDERED", name, nerf.nerf_deform.checkpoint.replace("\\\\", "/"), image[..., 3].max())
"""


@pytest.mark.slow
def test_saved_checkpoint_paths_render_on_a_farm_after_the_project_folder_moved(sphere_nerf, tmp_path):
    ckpt, _ = sphere_nerf
    project = tmp_path / "project"
    shutil.copytree(ckpt.parent, project / "run")
    for folder in ("versions", "deep/er", "elsewhere", "farm_cwd", "frames"):
        (tmp_path / folder if folder in ("elsewhere", "farm_cwd", "frames") else project / folder).mkdir(parents=True)

    out = assert_clean(run_blender(SCENE_HELPERS + _AUTHOR.format(project=str(project)), cwd=tmp_path / "elsewhere"))
    lines = dict(
        line.split(" ", 1)
        for line in out.splitlines()
        if line.split(" ", 1)[0] in ("UNSAVED", "SHOT", "V2", "COPIED", "RESAVED")
    )
    assert lines["UNSAVED"] == str(project / "run" / "nerf.ckpt")  # no file yet: nothing to be relative to
    assert lines["SHOT"] == "//run/nerf.ckpt"
    assert lines["V2"] == "//../run/nerf.ckpt"
    assert lines["COPIED"] == "//../run/nerf.ckpt"  # the open file is still versions/shot_v2.blend
    assert lines["RESAVED"] == "//../run/nerf.ckpt"

    moved = tmp_path / "moved" / "project"
    shutil.move(project, moved)
    out = assert_clean(
        run_blender(
            SCENE_HELPERS + _FARM.format(project=str(moved), out=str(tmp_path / "frames")), cwd=tmp_path / "farm_cwd"
        )
    )
    rendered = [line.split()[1:] for line in out.splitlines() if line.startswith("RENDERED")]
    assert {name: path for name, path, _alpha in rendered} == {
        "shot.blend": "//run/nerf.ckpt",
        "versions/shot_v2.blend": "//../run/nerf.ckpt",
        "deep/er/copy.blend": "//../../run/nerf.ckpt",
    }
    assert all(float(alpha) > 0.5 for _name, _path, alpha in rendered)  # the sphere, found and rendered


def test_rebased_path_resolves_against_the_old_file_and_relates_to_the_new_one(addon, tmp_path):
    from blender_nerf_deform.addon.edit.load_nerf import rebased_path

    a, b = tmp_path / "a", tmp_path / "a" / "versions"
    assert rebased_path(str(a / "run" / "nerf.ckpt"), "", str(a / "shot.blend")) == "//run/nerf.ckpt"
    assert rebased_path("//run/nerf.ckpt", str(a / "shot.blend"), str(b / "v2.blend")) == "//../run/nerf.ckpt"
    assert rebased_path("//../run/nerf.ckpt", str(b / "v2.blend"), str(a / "shot.blend")) == "//run/nerf.ckpt"
    assert rebased_path("//run/nerf.ckpt", str(a / "shot.blend"), str(a / "again.blend")) == "//run/nerf.ckpt"
    assert rebased_path("//run/nerf.ckpt", "", str(a / "shot.blend")) == "//run/nerf.ckpt"  # relative to nothing
    # Absolute paths kept where the artist turned off Preferences > File Paths > Default Relative Paths.
    absolute = str(tmp_path / "mount" / "nerf.ckpt")
    assert rebased_path(absolute, str(a / "shot.blend"), str(b / "v2.blend"), make_relative=False) == absolute
    assert (
        rebased_path("//run/nerf.ckpt", str(a / "shot.blend"), str(b / "v2.blend"), make_relative=False)
        == "//../run/nerf.ckpt"
    )


def test_save_copy_and_a_failed_save_leave_the_open_files_paths_alone(addon, sphere_nerf, tmp_path):
    bpy = addon
    ckpt, _ = sphere_nerf
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "shot.blend"))
    assert bpy.ops.nerf_deform.load_nerf(filepath=str(ckpt)) == {"FINISHED"}
    nerf = bpy.context.active_object
    stored = nerf.nerf_deform.checkpoint
    assert stored.startswith("//")
    (tmp_path / "copies").mkdir()
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "copies" / "copy.blend"), copy=True)
    assert nerf.nerf_deform.checkpoint == stored and bpy.data.filepath == str(tmp_path / "shot.blend")

    blocked = tmp_path / "not_a_folder"
    blocked.write_text("a file where a folder should be")
    with pytest.raises(RuntimeError):
        bpy.ops.wm.save_as_mainfile(filepath=str(blocked / "sub" / "x.blend"))
    assert nerf.nerf_deform.checkpoint == stored
