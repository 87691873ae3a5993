"""Train stage: Train NeRF, Import Photos (photos without poses) and Preview Training."""
