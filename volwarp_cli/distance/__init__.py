"""Signed distance fields: exact Euclidean, sub-voxel, the paper's min-norm, updates.

:mod:`.labels` says what ``volwarp distance`` takes the field of (a label map's
labels' voxels, or the samples on one side of an iso level) and :mod:`.scan`
what the whole input says before any block; :class:`.band.BandedDistance` is
the euclidean field as an operation of the executor (within a band, or
sub-voxel), :func:`.field.signed_distance` the whole field of every metric
in memory, and :mod:`.chunked` its passes by blocks.
"""
