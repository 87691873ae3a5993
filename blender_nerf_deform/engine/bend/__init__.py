"""Ray bending: render a NeRF through a deformed cage (each sample located in its deformed
tet and mapped back to the rest cage), and one posed frame as the CLI and the worker render it."""
