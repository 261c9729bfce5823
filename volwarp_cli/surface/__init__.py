"""Isosurfaces, triangle meshes, mesh files and mesh operations."""
