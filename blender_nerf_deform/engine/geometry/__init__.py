"""The geometry stages: mesh extraction from the NeRF's density, the tetrahedral cage built
once, barycentric maps, point location in the cage, the surface embedding, cage poses on
disk, and the deformers (affine regions, ARAP). embedding, barycentric, mesh_io and poses
are pure numpy (the add-on imports the first)."""
