"""Worker layer: the client of the engine worker process, the operators whose work runs there,
and Set Up Worker, which makes the Python environment it runs in. Above data, below the stages."""
