"""Data layer: what the add-on stores on objects, meshes and files, and the helpers every stage reads
(the object settings, the cage and embedding store, mesh attributes, cameras, paths, images).
Imports nothing above it. Docstring only: capture/runner.py loads modules of this package without
Blender's add-on machinery."""
