"""Geometry at the bottom of the pipeline: transforms, meshes, slicing, planes, voxelisation and
label maps."""
