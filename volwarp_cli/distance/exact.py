"""Exact signed Euclidean distance of a binary shape, with voxel spacing.

The field is the distance between voxel *centres*: for a voxel outside the
shape, the distance to the nearest inside voxel; for a voxel inside, minus the
distance to the nearest outside voxel (negative inside, positive outside,
world units). It equals ``edt(~mask, sampling) - edt(mask, sampling)`` with
``scipy.ndimage.distance_transform_edt``, the reference the tests use. The
zero level set of a trilinear interpolation of it lies half-way between the
inside and outside voxel centres.

Algorithm: the separable lower-envelope-of-parabolas transform of Felzenszwalb
and Huttenlocher (2012), one pass per axis, done for both sides at once. The
first pass (along x) finds, per row, the distance to the nearest voxel of the
*other* label; each later pass builds two lower envelopes per line (one for
the inside field, one for the outside field). A voxel of the inside needs the
"distance to the outside" function only, and that function is 0 on every
outside voxel, so one float32 array holds both half-fields: the value stored
at a voxel is its distance to the other label, the other half-field being 0
there by definition. Peak memory is the mask plus one float32 array.

The paper (Dinh & Carvalho 2004, §0.5) computes its fields with the min-norm
scheme of :mod:`.minnorm`; the Euclidean transform is what their software
comparison and Payne & Toga's interpolation (§0.3.1) assume.

References
----------
P. F. Felzenszwalb, D. P. Huttenlocher, "Distance Transforms of Sampled
Functions", Theory of Computing 8 (2012) 415-428.
"""

from __future__ import annotations

import numpy as np

from ..errors import VolwarpError
from ._edtkernels import x_pass, y_pass, z_pass  # noqa: F401 (the passes, below)

# The three passes, serial, on a block of whole lines along the pass's axis (the
# other two axes may be any part of the volume): :class:`.passes.ExactDistance`
# runs them on the blocks of its passes, in memory over the threads or as block
# tasks. The mask is uint8 (0/1); between the passes the field is float32 squared
# distances negated inside (the mask as their sign: a squared distance to the
# other side is never 0), until the last pass's signed square root. They are C
# (``_edtkernels.c``, its header says why): x_pass(mask, hx, out),
# y_pass(field, mask, hy), z_pass(field, hz).


def signed_edt(mask: np.ndarray, spacing_zyx=(1.0, 1.0, 1.0)) -> np.ndarray:
    """Signed Euclidean distance between voxel centres, negative inside.

    Parameters
    ----------
    mask : (Z, Y, X) array
        The shape (nonzero inside).
    spacing_zyx : sequence of 3 floats
        Sample spacing along the array axes, in world units.

    Returns
    -------
    (Z, Y, X) float32 array
        ``+inf`` everywhere (resp. ``-inf``) when the shape is empty (resp. fills
        the grid); callers check for that first.

    The passes of :class:`.passes.ExactDistance` in memory, on the threads.
    """
    from .passes import MaskSource, field_in_memory

    mask = np.asarray(mask)
    if mask.ndim != 3:
        raise VolwarpError(f"signed_edt needs a 3-D mask, got shape {mask.shape}")
    if mask.dtype not in (np.uint8, np.bool_):
        mask = mask != 0
    return field_in_memory(MaskSource(mask, 0.5, "above", check=False), spacing_zyx)
