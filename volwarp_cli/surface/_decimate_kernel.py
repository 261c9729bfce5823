"""Numba kernel of quadric edge-collapse decimation (imported only when decimating).

Garland and Heckbert, "Surface simplification using quadric error metrics",
SIGGRAPH 1997: every vertex carries the sum of the squared-distance quadrics
of its triangles' planes; an edge collapses to the point minimising the sum
of its two vertices' quadrics, and cheap collapses go first. The schedule is
the threshold sweep of Sp4cerat's "Fast Quadric Mesh Simplification" (edges
under a rising error threshold collapse in passes) instead of a global heap.

Departures, to keep a closed manifold closed and manifold: a collapse must
pass the link condition (Dey et al. 1999: the edge's two ends share exactly
the two opposite vertices), may not leave a vertex with fewer than three
triangles, and may not flip or squash any triangle around it. Vertices on
the border of an open surface never move, so openings keep their outline.
This module imports numba at load time so that its functions can be cached
on disk; :func:`volwarp_cli.surface.ops.decimate` imports it lazily.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ._kernels import cross, offset, triangle_normal


@njit(cache=True, nogil=True)
def _quadric_error(q, x, y, z):
    return (q[0] * x * x + 2.0 * q[1] * x * y + 2.0 * q[2] * x * z + 2.0 * q[3] * x
            + q[4] * y * y + 2.0 * q[5] * y * z + 2.0 * q[6] * y
            + q[7] * z * z + 2.0 * q[8] * z + q[9])


@njit(cache=True, nogil=True)
def _edge_cost(quadrics, verts, i0, i1, q, p):
    """Error of collapsing (i0, i1); the best position goes to ``p`` (``q`` is scratch)."""
    for k in range(10):
        q[k] = quadrics[i0, k] + quadrics[i1, k]
    # minimise: [[q0 q1 q2] [q1 q4 q5] [q2 q5 q7]] p = -[q3 q6 q8]
    a, b, c, d, e, f = q[0], q[1], q[2], q[4], q[5], q[7]
    det = a * (d * f - e * e) - b * (b * f - e * c) + c * (b * e - d * c)
    mx = 0.5 * (verts[i0, 0] + verts[i1, 0])
    my = 0.5 * (verts[i0, 1] + verts[i1, 1])
    mz = 0.5 * (verts[i0, 2] + verts[i1, 2])
    ex = verts[i1, 0] - verts[i0, 0]
    ey = verts[i1, 1] - verts[i0, 1]
    ez = verts[i1, 2] - verts[i0, 2]
    edge2 = ex * ex + ey * ey + ez * ez
    if det != 0.0:
        r0, r1, r2 = -q[3], -q[6], -q[8]
        x = (r0 * (d * f - e * e) - b * (r1 * f - e * r2) + c * (r1 * e - d * r2)) / det
        y = (a * (r1 * f - e * r2) - r0 * (b * f - e * c) + c * (b * r2 - r1 * c)) / det
        z = (a * (d * r2 - r1 * e) - b * (b * r2 - r1 * c) + r0 * (b * e - d * c)) / det
        # a nearly singular system (a flat patch) may put the point far away:
        # then fall back to the best of the ends and the midpoint
        dist2 = (x - mx) ** 2 + (y - my) ** 2 + (z - mz) ** 2
        if dist2 <= 4.0 * edge2:
            p[0], p[1], p[2] = x, y, z
            return _quadric_error(q, x, y, z)
    best = _quadric_error(q, mx, my, mz)
    p[0], p[1], p[2] = mx, my, mz
    for w in (i0, i1):
        err = _quadric_error(q, verts[w, 0], verts[w, 1], verts[w, 2])
        if err < best:
            best = err
            p[0], p[1], p[2] = verts[w, 0], verts[w, 1], verts[w, 2]
    return best


@njit(cache=True, nogil=True)
def _face_update(verts, faces, t, normals, errors, quadrics, q, p):
    """Recompute triangle ``t``'s normal and its three edge costs."""
    nx, ny, nz = triangle_normal(verts, faces[t, 0], faces[t, 1], faces[t, 2])
    length = math.sqrt(nx * nx + ny * ny + nz * nz)
    if length > 0.0:
        nx /= length
        ny /= length
        nz /= length
    normals[t, 0], normals[t, 1], normals[t, 2] = nx, ny, nz
    lo = np.inf
    for k in range(3):
        err = _edge_cost(quadrics, verts, faces[t, k], faces[t, (k + 1) % 3], q, p)
        errors[t, k] = err
        lo = min(lo, err)
    errors[t, 3] = lo


@njit(cache=True, nogil=True)
def _rebuild_refs(faces, n_faces, n_vertices, tstart, tcount, refs_t, refs_v):
    tcount[:] = 0
    for t in range(n_faces):
        for k in range(3):
            tcount[faces[t, k]] += 1
    s = 0
    for i in range(n_vertices):
        tstart[i] = s
        s += tcount[i]
    fill = tstart.copy()
    for t in range(n_faces):
        for k in range(3):
            v = faces[t, k]
            refs_t[fill[v]] = t
            refs_v[fill[v]] = k
            fill[v] += 1
    return s


@njit(cache=True, nogil=True)
def _flipped(verts, faces, normals, deleted, refs_t, refs_v, start, count, i_other, p):
    """Whether moving the vertex of these refs to ``p`` would flip or squash a triangle."""
    for r in range(start, start + count):
        t = refs_t[r]
        if deleted[t]:
            continue
        s = refs_v[r]
        id1 = faces[t, (s + 1) % 3]
        id2 = faces[t, (s + 2) % 3]
        if id1 == i_other or id2 == i_other:
            continue  # this triangle disappears with the collapse
        d1x, d1y, d1z = offset(verts, id1, p)
        d2x, d2y, d2z = offset(verts, id2, p)
        l1 = math.sqrt(d1x * d1x + d1y * d1y + d1z * d1z)
        l2 = math.sqrt(d2x * d2x + d2y * d2y + d2z * d2z)
        if l1 == 0.0 or l2 == 0.0:
            return True
        d1x /= l1
        d1y /= l1
        d1z /= l1
        d2x /= l2
        d2y /= l2
        d2z /= l2
        if abs(d1x * d2x + d1y * d2y + d1z * d2z) > 0.999:
            return True
        nx, ny, nz = cross(d1x, d1y, d1z, d2x, d2y, d2z)
        ln = math.sqrt(nx * nx + ny * ny + nz * nz)
        if ln == 0.0:
            return True
        if (nx * normals[t, 0] + ny * normals[t, 1] + nz * normals[t, 2]) / ln < 0.2:
            return True
    return False


@njit(cache=True, nogil=True)
def _valence(deleted, refs_t, start, count):
    n = 0
    for r in range(start, start + count):
        if not deleted[refs_t[r]]:
            n += 1
    return n


@njit(cache=True, nogil=True)
def simplify(verts_in, faces_in, target, aggressiveness, max_iterations):
    """Collapse edges until at most ``target`` triangles remain (or nothing can go).

    ``verts_in`` should be scaled to about unit size (the threshold schedule
    is absolute). Returns (vertices, faces) with unused vertices dropped.
    """
    verts = verts_in.copy()
    faces = faces_in.copy()
    nv = verts.shape[0]
    nf = faces.shape[0]
    deleted = np.zeros(nf, dtype=np.bool_)
    dirty = np.zeros(nf, dtype=np.bool_)
    errors = np.zeros((nf, 4))
    normals = np.zeros((nf, 3))
    quadrics = np.zeros((nv, 10))
    q = np.zeros(10)
    p = np.zeros(3)
    # plane quadrics of the triangles, summed at their corners
    for t in range(nf):
        _face_update(verts, faces, t, normals, errors, quadrics, q, p)
        a = faces[t, 0]
        nx, ny, nz = normals[t, 0], normals[t, 1], normals[t, 2]
        dd = -(nx * verts[a, 0] + ny * verts[a, 1] + nz * verts[a, 2])
        for k in range(3):
            v = faces[t, k]
            quadrics[v, 0] += nx * nx
            quadrics[v, 1] += nx * ny
            quadrics[v, 2] += nx * nz
            quadrics[v, 3] += nx * dd
            quadrics[v, 4] += ny * ny
            quadrics[v, 5] += ny * nz
            quadrics[v, 6] += ny * dd
            quadrics[v, 7] += nz * nz
            quadrics[v, 8] += nz * dd
            quadrics[v, 9] += dd * dd
    for t in range(nf):
        _face_update(verts, faces, t, normals, errors, quadrics, q, p)
    tstart = np.zeros(nv, dtype=np.int64)
    tcount = np.zeros(nv, dtype=np.int64)
    cap = 6 * nf + 16
    refs_t = np.empty(cap, dtype=np.int64)
    refs_v = np.empty(cap, dtype=np.int64)
    n_refs = _rebuild_refs(faces, nf, nv, tstart, tcount, refs_t, refs_v)
    # border vertices: an edge used by one triangle only
    border = np.zeros(nv, dtype=np.bool_)
    stamp = np.zeros(nv, dtype=np.int64)
    seen = np.zeros(nv, dtype=np.int64)
    tag = 1
    for i in range(nv):
        tag += 1
        for r in range(tstart[i], tstart[i] + tcount[i]):
            t = refs_t[r]
            s = refs_v[r]
            for w in (faces[t, (s + 1) % 3], faces[t, (s + 2) % 3]):
                if stamp[w] != tag:
                    stamp[w] = tag
                    seen[w] = 0
                seen[w] += 1
        for r in range(tstart[i], tstart[i] + tcount[i]):
            t = refs_t[r]
            s = refs_v[r]
            for w in (faces[t, (s + 1) % 3], faces[t, (s + 2) % 3]):
                if seen[w] == 1:
                    border[i] = True
                    border[w] = True
    alive = nf
    for it in range(max_iterations):
        if alive <= target:
            break
        if it > 0 and it % 5 == 0:
            j = 0
            for t in range(nf):
                if not deleted[t]:
                    for k in range(3):
                        faces[j, k] = faces[t, k]
                        normals[j, k] = normals[t, k]
                    for k in range(4):
                        errors[j, k] = errors[t, k]
                    j += 1
            nf = j
            deleted[:nf] = False
            n_refs = _rebuild_refs(faces, nf, nv, tstart, tcount, refs_t, refs_v)
        dirty[:nf] = False
        threshold = 1e-9 * (it + 3.0) ** aggressiveness
        for t in range(nf):
            if deleted[t] or dirty[t] or errors[t, 3] > threshold:
                continue
            for k in range(3):
                if errors[t, k] > threshold:
                    continue
                i0 = faces[t, k]
                i1 = faces[t, (k + 1) % 3]
                if border[i0] or border[i1]:
                    continue
                # link condition: exactly two shared neighbours (the opposite corners)
                tag += 2
                for r in range(tstart[i0], tstart[i0] + tcount[i0]):
                    if deleted[refs_t[r]]:
                        continue
                    s = refs_v[r]
                    stamp[faces[refs_t[r], (s + 1) % 3]] = tag
                    stamp[faces[refs_t[r], (s + 2) % 3]] = tag
                common = 0
                o1 = -1
                o2 = -1
                for r in range(tstart[i1], tstart[i1] + tcount[i1]):
                    if deleted[refs_t[r]]:
                        continue
                    s = refs_v[r]
                    for w in (faces[refs_t[r], (s + 1) % 3], faces[refs_t[r], (s + 2) % 3]):
                        if stamp[w] == tag:
                            stamp[w] = tag + 1
                            common += 1
                            if o1 < 0:
                                o1 = w
                            else:
                                o2 = w
                if common != 2:
                    continue
                v0 = _valence(deleted, refs_t, tstart[i0], tcount[i0])
                v1 = _valence(deleted, refs_t, tstart[i1], tcount[i1])
                if v0 + v1 - 4 < 3:
                    continue
                if _valence(deleted, refs_t, tstart[o1], tcount[o1]) < 4 or \
                        _valence(deleted, refs_t, tstart[o2], tcount[o2]) < 4:
                    continue
                _edge_cost(quadrics, verts, i0, i1, q, p)
                if _flipped(verts, faces, normals, deleted, refs_t, refs_v, tstart[i0],
                            tcount[i0], i1, p):
                    continue
                if _flipped(verts, faces, normals, deleted, refs_t, refs_v, tstart[i1],
                            tcount[i1], i0, p):
                    continue
                # collapse i1 into i0
                verts[i0, 0], verts[i0, 1], verts[i0, 2] = p[0], p[1], p[2]
                for m in range(10):
                    quadrics[i0, m] += quadrics[i1, m]
                if n_refs + tcount[i0] + tcount[i1] > cap:
                    cap = 2 * cap + tcount[i0] + tcount[i1]
                    grown_t = np.empty(cap, dtype=np.int64)
                    grown_v = np.empty(cap, dtype=np.int64)
                    grown_t[:n_refs] = refs_t[:n_refs]
                    grown_v[:n_refs] = refs_v[:n_refs]
                    refs_t = grown_t
                    refs_v = grown_v
                new_start = n_refs
                for src in (i0, i1):
                    for r in range(tstart[src], tstart[src] + tcount[src]):
                        tt = refs_t[r]
                        if deleted[tt]:
                            continue
                        s = refs_v[r]
                        other = i1 if src == i0 else i0
                        if faces[tt, (s + 1) % 3] == other or faces[tt, (s + 2) % 3] == other:
                            deleted[tt] = True
                            alive -= 1
                            continue
                        faces[tt, s] = i0
                        dirty[tt] = True
                        refs_t[n_refs] = tt
                        refs_v[n_refs] = s
                        n_refs += 1
                for r in range(new_start, n_refs):
                    _face_update(verts, faces, refs_t[r], normals, errors, quadrics, q, p)
                count = n_refs - new_start
                if count <= tcount[i0]:
                    for r in range(count):
                        refs_t[tstart[i0] + r] = refs_t[new_start + r]
                        refs_v[tstart[i0] + r] = refs_v[new_start + r]
                    n_refs = new_start
                else:
                    tstart[i0] = new_start
                tcount[i0] = count
                tcount[i1] = 0
                break
            if alive <= target:
                break
    # compact: live triangles, used vertices
    out_faces = np.empty((alive, 3), dtype=np.int64)
    used = np.zeros(nv, dtype=np.bool_)
    j = 0
    for t in range(nf):
        if not deleted[t]:
            for k in range(3):
                out_faces[j, k] = faces[t, k]
                used[faces[t, k]] = True
            j += 1
    remap = np.full(nv, -1, dtype=np.int64)
    n_used = 0
    for i in range(nv):
        if used[i]:
            remap[i] = n_used
            n_used += 1
    out_verts = np.empty((n_used, 3))
    for i in range(nv):
        if used[i]:
            out_verts[remap[i]] = verts[i]
    for t in range(alive):
        for k in range(3):
            out_faces[t, k] = remap[out_faces[t, k]]
    return out_verts, out_faces
