"""Cost against the voxel count and the photons, and scale-out on Dask workers."""
