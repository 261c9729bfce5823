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

import numba as nb
import numpy as np

from ..errors import VolwarpError


@nb.njit(cache=True, nogil=True, inline="always")
def new_envelope(n):
    """The arrays of a lower envelope of up to ``n`` parabolas: sites, heights, breakpoints."""
    return np.empty(n, np.int64), np.empty(n, np.float64), np.empty(n + 1, np.float64)


@nb.njit(cache=True, nogil=True, inline="always")
def add_parabola(k, q, gq, h2, v, g, zb):
    """Add the parabola ``h2 (p - q)^2 + gq`` to a lower envelope; return its new last index.

    The envelope's parabolas ``0..k`` (``k = -1``: none yet) have their sites in
    ``v``, their heights in ``g`` and the breakpoints between them in ``zb``
    (``zb[j]`` to ``zb[j + 1]`` is where parabola ``j`` is lowest; the arrays of
    :func:`new_envelope`); sites come in increasing order (Felzenszwalb &
    Huttenlocher 2012, algorithm DT(f)). Shared by the exact field and the
    sub-voxel feature transform.

    The kernels of :mod:`.subvoxel` inline it and this module's other helpers;
    numba's disk cache checks their compiled code against ``subvoxel.py``
    alone: after changing a helper here, touch that file too.
    """
    if k < 0:
        v[0] = q
        g[0] = gq
        zb[0] = -np.inf
        zb[1] = np.inf
        return 0
    s = 0.0
    while True:
        r = v[k]
        s = ((gq + h2 * q * q) - (g[k] + h2 * r * r)) / (2.0 * h2 * (q - r))
        if s <= zb[k]:
            k -= 1
            if k < 0:
                break
        else:
            break
    k += 1
    v[k] = q
    g[k] = gq
    zb[k] = -np.inf if k == 0 else s
    zb[k + 1] = np.inf
    return k


@nb.njit(cache=True, nogil=True, inline="always")
def _envelope(f, label, want, n, h2, v, g, zb, out):
    # Lower envelope of the parabolas h2 (p - q)^2 + g(q), g(q) = f[q] where
    # label[q] == want, else 0 (a voxel of the other label is at distance 0
    # from it); evaluated only at the positions p with label[p] == want.
    # A zero site inside a run of zero sites is never the nearest one for such
    # a p (its run neighbours are nearer), and infinite sites never win: both
    # are skipped.
    anywant = False
    for p in range(n):
        if label[p] == want:
            anywant = True
            break
    if not anywant:
        return
    k = -1
    for q in range(n):
        if label[q] == want:
            gq = f[q]
            if gq == np.inf:
                continue
        else:
            if 0 < q < n - 1 and label[q - 1] != want and label[q + 1] != want:
                continue
            gq = 0.0
        k = add_parabola(k, q, gq, h2, v, g, zb)
    if k < 0:
        for p in range(n):
            if label[p] == want:
                out[p] = np.inf
        return
    j = 0
    for p in range(n):
        if label[p] != want:
            continue
        while zb[j + 1] < p:
            j += 1
        r = v[j]
        out[p] = h2 * (p - r) * (p - r) + g[j]


@nb.njit(cache=True, nogil=True, inline="always")
def column(plane, other, c, f, fo):
    """Copy column ``c`` of an (n, m) plane to ``f`` and that of ``other`` to ``fo``."""
    for i in range(f.shape[0]):
        f[i] = plane[i, c]
        fo[i] = other[i, c]


@nb.njit(cache=True, nogil=True, inline="always")
def _plane_pass(plane, labels, m, n, h2, sign):
    # Both envelopes along axis 0 of an (n, m) plane, column by column, in place.
    f = np.empty(n, np.float64)
    lab = np.empty(n, np.uint8)
    tmp = np.empty(n, np.float64)
    v, g, zb = new_envelope(n)
    for c in range(m):
        column(plane, labels, c, f, lab)
        _envelope(f, lab, 1, n, h2, v, g, zb, tmp)
        _envelope(f, lab, 0, n, h2, v, g, zb, tmp)
        if sign == 1:  # the signed distance
            for i in range(n):
                d = np.sqrt(tmp[i])
                plane[i, c] = -d if lab[i] else d
        elif sign == 2:  # the squared distance, negated inside (the mask as its sign)
            for i in range(n):
                plane[i, c] = -tmp[i] if lab[i] else tmp[i]
        else:
            for i in range(n):
                plane[i, c] = tmp[i]


@nb.njit(cache=True, nogil=True, inline="always")
def _x_rows(mask, out, z, hx2):
    # Pass 1 (x) on the rows of slice z: distance along the row to the nearest voxel
    # of the other label (inf when the row has none).
    ny, nx = mask.shape[1], mask.shape[2]
    for y in range(ny):
        last = -1
        for x in range(nx):
            if x > 0 and mask[z, y, x] != mask[z, y, x - 1]:
                last = x - 1
            out[z, y, x] = np.inf if last < 0 else hx2 * (x - last) * (x - last)
        last = -1
        for x in range(nx - 1, -1, -1):
            if x < nx - 1 and mask[z, y, x] != mask[z, y, x + 1]:
                last = x + 1
            if last >= 0:
                d = hx2 * (last - x) * (last - x)
                if d < out[z, y, x]:
                    out[z, y, x] = d


@nb.njit(cache=True, nogil=True, inline="always")
def _z_plane(out, y, hz2):
    # Pass 3 (z) on the (z, x) plane of one y, copied out (rows are contiguous) with the
    # mask taken from the sign, processed in cache and copied back with the signed root.
    nz, nx = out.shape[0], out.shape[2]
    plane = np.empty((nz, nx), np.float32)
    labels = np.empty((nz, nx), np.uint8)
    for z in range(nz):
        for x in range(nx):
            v = out[z, y, x]
            if v < 0:
                labels[z, x] = 1
                plane[z, x] = -v
            else:
                labels[z, x] = 0
                plane[z, x] = v
    _plane_pass(plane, labels, nx, nz, hz2, 1)
    for z in range(nz):
        for x in range(nx):
            out[z, y, x] = plane[z, x]


# The three passes, serial, on a block of whole lines along the pass's axis (the
# other two axes may be any part of the volume): :class:`.passes.ExactDistance`
# runs them on the blocks of its passes, in memory over the threads or as block
# tasks. The mask is uint8 (0/1); between the passes the field is float32 squared
# distances negated inside (the mask as their sign: a squared distance to the
# other side is never 0), until the last pass's signed square root.
@nb.njit(cache=True, nogil=True)
def x_pass(mask, hx, out):
    """Pass 1 (x) of a (Z, Y, X) block of whole x rows into ``out`` (float32, unsigned)."""
    for z in range(mask.shape[0]):
        _x_rows(mask, out, z, hx * hx)


@nb.njit(cache=True, nogil=True)
def y_pass(field, mask, hy):
    """Pass 2 (y), in place, on a (Z, Y, X) block of whole y columns; negated inside."""
    for z in range(mask.shape[0]):
        _plane_pass(field[z], mask[z], mask.shape[2], mask.shape[1], hy * hy, 2)


@nb.njit(cache=True, nogil=True)
def z_pass(field, hz):
    """Pass 3 (z) and the signed square root, in place, on a block of whole z lines.

    ``field``: squared distances negated inside, as :func:`y_pass` leaves them.
    """
    for y in range(field.shape[1]):
        _z_plane(field, y, hz * hz)


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
