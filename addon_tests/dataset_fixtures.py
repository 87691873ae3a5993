"""Session fixtures: the embedded default scene and a small dataset rendered from it.

For tests that need real training data without ../shared (the NeRF engine's
CI-sized training test, the reduced demo). Both are made once per session by
running the project's tools as a user would (subprocesses of the .venv
Python), so no Blender state leaks into the in-process `blender` fixture.

    procedural_dataset      Path of a folder holding transforms.json (PROCEDURAL_VIEWS
                            training views, images/r_<k>.png, RGBA straight alpha,
                            PROCEDURAL_RESOLUTION px square) and test/transforms.json
                            (PROCEDURAL_TEST_VIEWS other views, for PSNR).
                            Cameras on the whole sphere, radius 4, 50 mm on 36 mm
                            (camera_angle_x = 0.6911), NeRF-synthetic form (composite on white).
                            About 2-3 s on 2 cores, default scene included.
    make_procedural_dataset Session-cached factory for other sizes:
                            make_procedural_dataset(count=100, resolution=100, test_count=10,
                            samples=16, hemisphere=False, seed=0) -> Path (same arguments, same folder).
    default_scene_blend     Path of the default scene's .blend (tools/default_scene.py);
                            its deformable part and pin are in tools.default_scene.REGIONS.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent

PROCEDURAL_VIEWS = 40
PROCEDURAL_TEST_VIEWS = 8
PROCEDURAL_RESOLUTION = 64
PROCEDURAL_SAMPLES = 16

__all__ = ["default_scene_blend", "procedural_dataset", "make_procedural_dataset", "run_tool",
           "PROCEDURAL_VIEWS", "PROCEDURAL_TEST_VIEWS", "PROCEDURAL_RESOLUTION"]


def run_tool(script: str, *args, check: bool = True) -> subprocess.CompletedProcess:
    """Run tools/<script> with this interpreter, as a user would; output captured as text."""
    result = subprocess.run([sys.executable, str(REPO / "tools" / script), *map(str, args)],
                            capture_output=True, text=True, cwd=REPO, timeout=600)
    if check and result.returncode != 0:
        raise AssertionError(f"tools/{script} {' '.join(map(str, args))} exited {result.returncode}:\n"
                             f"{result.stdout[-2000:]}\n{result.stderr[-2000:]}")
    return result


@pytest.fixture(scope="session")
def default_scene_blend(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("default_scene") / "default_scene.blend"
    run_tool("default_scene.py", "--out", path)
    assert path.is_file()
    return path


@pytest.fixture(scope="session")
def make_procedural_dataset(default_scene_blend, tmp_path_factory):
    """A function rendering a dataset of the default scene, cached per argument set for the session."""
    made: dict[tuple, Path] = {}

    def make(count: int = PROCEDURAL_VIEWS, resolution: int = PROCEDURAL_RESOLUTION,
             test_count: int = PROCEDURAL_TEST_VIEWS, samples: int = PROCEDURAL_SAMPLES,
             hemisphere: bool = False, seed: int = 0) -> Path:
        key = (count, resolution, test_count, samples, hemisphere, seed)
        if key not in made:
            out = tmp_path_factory.mktemp("procedural_dataset")
            run_tool("make_dataset.py", "--blend", default_scene_blend, "--out", out,
                     "--count", count, "--test-count", test_count, "--resolution", resolution,
                     "--samples", samples, "--radius", 4.0, "--seed", seed, "--threads", 2,
                     *(["--hemisphere"] if hemisphere else []))
            assert (out / "transforms.json").is_file()
            made[key] = out
        return made[key]

    return make


@pytest.fixture(scope="session")
def procedural_dataset(make_procedural_dataset) -> Path:
    return make_procedural_dataset()
