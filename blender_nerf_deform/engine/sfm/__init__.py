"""Photos with no poses → cameras: structure from motion with pycolmap (COLMAP itself), the
reconstruction oriented upright and scaled, written as a transforms.json dataset (`prepare`)."""

# The photo files `prepare` reads: plain data here, so that the add-on can count a folder's photos
# before it asks the worker (prepare.py reaches PIL, which Blender's Python lacks).
IMAGE_SUFFIXES = frozenset({".jpg", ".jpeg", ".png", ".JPG", ".JPEG", ".PNG"})


def photo_names(folder) -> list[str]:
    """The names of the photos `prepare` would read in a folder (sorted; an unreadable folder has none)."""
    import os

    try:
        return sorted(
            e.name for e in os.scandir(folder) if e.is_file() and os.path.splitext(e.name)[1] in IMAGE_SUFFIXES
        )
    except OSError:
        return []
