"""Connectivity of a triangle mesh: components, and whether it is closed.

One linear pass (numba): union-find over the triangles' shared vertices for
the components, and a per-vertex table of outgoing edges for the closedness
test. A surface is *closed* when every directed edge (a, b) of a triangle
occurs once and its reverse (b, a) exactly once: every edge joins exactly two
triangles that traverse it in opposite directions (watertight, consistently
wound).
"""

from __future__ import annotations

import numpy as np

from .mesh import Mesh

_KERNELS: dict = {}


def _topology_kernel():
    import numba

    @numba.njit(cache=True, nogil=True)
    def topology(n_vertices, faces):
        m = faces.shape[0]
        parent = np.arange(n_vertices)
        # (find with path halving is written out inline: a jitted helper
        # captured from the enclosing scope would defeat numba's disk cache)
        for t in range(m):
            r0 = faces[t, 0]
            while parent[r0] != r0:
                parent[r0] = parent[parent[r0]]
                r0 = parent[r0]
            for k in (1, 2):
                r = faces[t, k]
                while parent[r] != r:
                    parent[r] = parent[parent[r]]
                    r = parent[r]
                if r != r0:
                    if r < r0:
                        parent[r0] = r
                        r0 = r
                    else:
                        parent[r] = r0
        # components numbered in order of their first triangle
        comp = np.full(n_vertices, -1, dtype=np.int64)
        labels = np.empty(m, dtype=np.int64)
        count = 0
        for t in range(m):
            r = faces[t, 0]
            while parent[r] != r:
                parent[r] = parent[parent[r]]
                r = parent[r]
            if comp[r] < 0:
                comp[r] = count
                count += 1
            labels[t] = comp[r]
        # outgoing directed edges of each vertex (counting sort by start vertex)
        start = np.zeros(n_vertices + 1, dtype=np.int64)
        for t in range(m):
            for k in range(3):
                start[faces[t, k] + 1] += 1
        for i in range(n_vertices):
            start[i + 1] += start[i]
        fill = start[:-1].copy()
        ends = np.empty(3 * m, dtype=np.int64)
        for t in range(m):
            for k in range(3):
                a = faces[t, k]
                ends[fill[a]] = faces[t, (k + 1) % 3]
                fill[a] += 1
        closed = m > 0
        for a in range(n_vertices):
            if not closed:
                break
            for e in range(start[a], start[a + 1]):
                b = ends[e]
                same = 0
                for q in range(start[a], start[a + 1]):
                    if ends[q] == b:
                        same += 1
                back = 0
                for q in range(start[b], start[b + 1]):
                    if ends[q] == a:
                        back += 1
                if same != 1 or back != 1:
                    closed = False
                    break
        return count, labels, closed

    return topology


def topology(mesh: Mesh) -> tuple[int, np.ndarray, bool]:
    """(component count, component of each triangle, closed) in one pass.

    Components are joined through shared vertices and numbered 0.. in the
    order of their first triangle.
    """
    if mesh.is_empty:
        return 0, np.zeros(0, dtype=np.int64), False
    if "topology" not in _KERNELS:
        _KERNELS["topology"] = _topology_kernel()
    count, labels, closed = _KERNELS["topology"](mesh.n_vertices, mesh.faces)
    return int(count), labels, bool(closed)


def connected_components(mesh: Mesh) -> tuple[int, np.ndarray]:
    """(number of components, (M,) component of each triangle)."""
    count, labels, _ = topology(mesh)
    return count, labels


def is_closed(mesh: Mesh) -> bool:
    """True when the surface is watertight and consistently wound (see the module notes)."""
    return topology(mesh)[2]
