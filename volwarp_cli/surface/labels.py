"""A label map's surfaces: its labels, read block by block, and each one's indicator.

The surface of a label is the isosurface at 0.5 of its indicator (1 where
the label is, 0 elsewhere), closed at the volume's border (``cap``): a
label's voxels enclosed by their faces, bevelled at edges and corners.
"""

from __future__ import annotations

import numpy as np

from ..errors import VolwarpError


def check_label_map(dtype, name: str, what: str) -> None:
    """Refuse samples that are not a label map (integers) for ``what`` (``--label``...)."""
    if np.dtype(dtype).kind not in "iu":
        raise VolwarpError(f"{name}: {what} needs a label map (integer samples), got "
                           f"{np.dtype(dtype)}")


class LabelIndicator:
    """The indicator of one label of a sliceable label map (1 inside, float32), read by boxes.

    Picklable when the map is (a :class:`~volwarp_cli.io.lazy.LazySource`).
    """

    def __init__(self, source, label: int):
        self.source, self.label = source, int(label)
        self.shape = tuple(source.shape)
        self.dtype = np.dtype(np.float32)
        self.ndim = 3

    def __getitem__(self, key) -> np.ndarray:
        return (np.asarray(self.source[key]) == self.label).astype(np.float32)


def label_values(source, boxes, run=None) -> list[int]:
    """The distinct values of a sliceable integer map, ascending, read by ``boxes``.

    The boxes one after the other here, or by ``run(task, boxes)`` (an
    engine's map).
    """
    def task(box):
        return np.unique(np.asarray(source[box.slices]))

    parts = run(task, boxes) if run is not None else [task(b) for b in boxes]
    values = np.unique(np.concatenate(parts)) if parts else np.empty(0, np.int64)
    return [int(v) for v in values]
