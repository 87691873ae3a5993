"""Photos with no poses → cameras: structure from motion with pycolmap (COLMAP itself), the
reconstruction oriented upright and scaled, written as a transforms.json dataset (`prepare`)."""
