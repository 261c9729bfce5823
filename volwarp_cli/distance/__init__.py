"""Signed distance fields: exact Euclidean, sub-voxel, the paper's min-norm, updates.

:mod:`.labels` says what ``volwarp distance`` takes the field of (a label map's
labels' voxels, or the samples on one side of an iso level) and :mod:`.scan`
what the whole input says before any block. Two operations of the executor
compute a field (:func:`.operation.field_operation` picks one):
:class:`.band.BandedDistance`, the euclidean field within a band or to a
sub-voxel surface, block by block with a halo; and :mod:`.passes`, the exact
field and the line metrics in passes over whole lines (in memory over the
threads, by blocks through scratch files). :func:`.field.signed_distance` is
the array function (any metric, in memory) on the same code.
"""
