#!/usr/bin/env python3
"""Build the installable extension zip and validate it with Blender's own tool.

The repository keeps `blender_manifest.toml` at its root beside the package
folder `blender_nerf_deform/`; an extension zip wants the manifest beside the
package's `__init__.py`. This stages that layout in a temporary folder and
hands it to Blender's `blender_ext.py build`, then runs `blender_ext.py
validate` on the zip. Blender's tool ships inside the `bpy` module wheel (and
every Blender install); pass --blender-ext to use another copy.

    python tools/build_extension.py [--out-dir dist] [--blender-ext PATH]

Prints the path of the zip. Install it in Blender with Preferences → Get
Extensions → Install from Disk.
"""

from __future__ import annotations

import argparse
import importlib.util
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
PACKAGE = REPO / "blender_nerf_deform"
MANIFEST = REPO / "blender_manifest.toml"
ARCHITECTURE = REPO / "docs" / "ARCHITECTURE.md"
_IGNORE = shutil.ignore_patterns("__pycache__", "*.pyc", ".*")


def find_blender_ext() -> Path:
    """Locate Blender's extension command-line tool inside the installed bpy module."""
    spec = importlib.util.find_spec("bpy")
    if spec is None or not spec.submodule_search_locations:
        raise SystemExit("error: the bpy module is not installed; run `make setup` or pass --blender-ext PATH")
    bpy_dir = Path(next(iter(spec.submodule_search_locations)))
    found = sorted(bpy_dir.glob("*/scripts/addons_core/bl_pkg/cli/blender_ext.py"))
    if not found:
        raise SystemExit(f"error: no blender_ext.py under {bpy_dir}; pass --blender-ext PATH")
    return found[-1]


def run_blender_ext(blender_ext: Path, *args: str) -> str:
    proc = subprocess.run([sys.executable, str(blender_ext), *args], capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"error: blender_ext {args[0]} failed:\n{proc.stdout}{proc.stderr}")
    return proc.stdout


def manifest_version() -> tuple[str, str]:
    import tomllib

    with MANIFEST.open("rb") as f:
        data = tomllib.load(f)
    return data["id"], data["version"]


def stage(dest: Path, manifest: Path = MANIFEST) -> Path:
    """Lay out the extension's source as Blender wants it: the manifest beside the package's files."""
    shutil.copytree(PACKAGE, dest, ignore=_IGNORE)
    shutil.copy2(manifest, dest / "blender_manifest.toml")
    # The docstrings send readers to docs/ARCHITECTURE.md: an installed extension carries it too, and the
    # pages it links (the command line, the datasets, ...); not the benchmark notebook, history only.
    (dest / "docs").mkdir()
    shutil.copy2(ARCHITECTURE, dest / "docs" / "ARCHITECTURE.md")
    for page in sorted(ARCHITECTURE.parent.glob("*.md")):
        if page.name != "benchmarks-history.md":
            shutil.copy2(page, dest / "docs" / page.name)
    return dest


def build(out_dir: Path, blender_ext: Path | None = None) -> Path:
    blender_ext = blender_ext or find_blender_ext()
    ext_id, version = manifest_version()
    out_dir.mkdir(parents=True, exist_ok=True)
    zip_path = out_dir / f"{ext_id}-{version}.zip"
    with tempfile.TemporaryDirectory(prefix="nerf_deform_ext_") as tmp:
        staged = stage(Path(tmp) / ext_id)
        # Build into the temporary folder, then rename: an interrupted build
        # never leaves a half-written zip where an artist would pick it up.
        tmp_zip = Path(tmp) / zip_path.name
        run_blender_ext(blender_ext, "build", "--source-dir", str(staged), "--output-filepath", str(tmp_zip))
        run_blender_ext(blender_ext, "validate", str(tmp_zip))
        shutil.move(str(tmp_zip), zip_path)
    return zip_path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out-dir", type=Path, default=REPO / "dist", help="where the zip goes (default: dist/)")
    parser.add_argument(
        "--blender-ext", type=Path, help="path to Blender's blender_ext.py (default: from the bpy module)"
    )
    args = parser.parse_args(argv)
    print(build(args.out_dir, args.blender_ext))
    return 0


if __name__ == "__main__":
    sys.exit(main())
