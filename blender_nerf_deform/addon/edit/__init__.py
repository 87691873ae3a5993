"""Edit stage: Load NeRF, edit regions, Place 3D Cursor on NeRF, Extract Mesh, Build Cage."""
