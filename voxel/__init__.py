"""Information-rich voxel grid: storage, integration, queries, history, deltas and file formats."""
