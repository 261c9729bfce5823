"""Signed distance fields: exact Euclidean, sub-voxel, the paper's min-norm, updates.

See :func:`.field.signed_distance` for the entry point the commands use, and
:mod:`.labels` for what ``volwarp distance`` takes the field of (a label map's
labels' voxels, or the samples on one side of an iso level).
"""
