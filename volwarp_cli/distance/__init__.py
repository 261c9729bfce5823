"""Signed distance fields: exact Euclidean, sub-voxel, the paper's min-norm, updates.

See :func:`.field.signed_distance` for the entry point the commands use.
"""
