"""The planned frames of a warp spec: each increment's lattice, and what the plan holds.

A step's increments are the straight path from the lattice before it to its
end (``start + (end - start) * f / n``); only its last frame keeps a lattice
of its own, so a step of many frames holds two lattices, not one a frame.
"""

from __future__ import annotations

import tracemalloc

import numpy as np

from volwarp_cli.bspline.lattice import Lattice
from volwarp_cli.bspline.plan import SpecUnits, default_pad, plan, read_warp_spec
from volwarp_cli.spec.loader import load_spec_data
from volwarp_cli.volume import Volume

LATTICE = 12


def _plan(steps):
    doc = load_spec_data({"version": 1, "units": "voxel",
                          "capture": {"lattice": LATTICE, "oversample": 1},
                          "steps": steps}, "warp")
    spec = read_warp_spec(doc)
    vol = Volume(np.zeros((20, 20, 20), np.float32))
    grid = Lattice.create(vol.data.shape[::-1], (LATTICE,) * 3, 1.0)
    dq0 = np.zeros((LATTICE,) * 3 + (3,))
    return plan(doc, spec, grid, dq0, SpecUnits(vol, "voxel")), dq0


def test_increments_follow_the_straight_path_of_each_step():
    steps = [{"move": [{"index": [3, 4, 5], "by": [3.0, -1.5, 0.25]}], "frames": 4},
             {"move": [{"index": [3, 4, 5], "by": [-1.0, 2.0, 7.0]},
                       {"index": [0, 11, 2], "to": [1.0, 2.0, 3.0]}], "frames": 3},
             {"move": [{"index": [6, 6, 6], "by": [0.5, 0.5, 0.5]}]}]
    frames, dq0 = _plan(steps)
    assert [(f.step, f.sub) for f in frames] == [(1, 1), (1, 2), (1, 3), (1, 4),
                                                (2, 1), (2, 2), (2, 3), (3, 1)]
    ends = [frames[3].dq, frames[6].dq, frames[7].dq]
    first = dq0.copy()
    first[5, 4, 3] += (3.0, -1.5, 0.25)
    np.testing.assert_array_equal(ends[0], first)
    starts = [dq0, ends[0], ends[1]]
    for frame in frames:
        s, f = frame.step - 1, frame.sub
        n = [4, 3, 1][s]
        want = ends[s] if f == n else starts[s] + (ends[s] - starts[s]) * (f / n)
        np.testing.assert_array_equal(frame.dq, want)  # bit for bit, as before
        np.testing.assert_array_equal(frame.dq, frame.dq)  # made the same each time
    # the moved point's path is linear in the increment within a step
    path = np.array([fr.dq[5, 4, 3] for fr in frames[:4]])
    np.testing.assert_allclose(path, np.outer([0.25, 0.5, 0.75, 1.0], [3.0, -1.5, 0.25]))
    # the pad holds every frame's reach: an increment lies between its step's ends, so
    # the largest move of a step end, rounded up, plus one
    reach = np.max([np.abs(e - dq0).reshape(-1, 3).max(axis=0) for e in ends], axis=0)
    assert default_pad(frames, dq0) == tuple(int(np.ceil(r)) + 1 for r in reach)
    assert reach[2] == 7.25  # (the first point's two moves in z: 0.25 + 7)


def test_many_frames_hold_two_lattices_not_one_each():
    lattice_bytes = LATTICE ** 3 * 3 * 8
    tracemalloc.start()
    try:
        frames, _ = _plan([{"move": [{"index": [3, 4, 5], "by": [3.0, 0.0, 0.0]}],
                            "frames": 2000}])
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert len(frames) == 2000
    # each increment once held its own lattice: 2000 of them, 83 MB here
    assert peak < 40 * lattice_bytes, peak
    assert frames[999].dq[5, 4, 3, 0] == 1.5
