"""The commands' out-of-core path: inputs read by blocks, outputs written by blocks.

A command that runs by blocks (``--chunked``, or when its work does not fit
the memory budget) opens its input lazily (:func:`lazy_input`: a memory map,
a zarr array, pages of a TIFF; reopened by path in a worker process), builds
its result as a Dask array or as block tasks, and writes every block straight
into a :class:`~volwarp_cli.io.blockwrite.BlockOutput` (:func:`write_blocks`),
which appears at its path only when every block is in. The graph pieces
(:func:`~volwarp_cli.engine.dask_input`, :func:`~volwarp_cli.engine.write_blocks`)
are the engine's, shared with the cores that build graphs themselves.
"""

from __future__ import annotations

import numpy as np

from ..execute import MIN_BLOCK_BUDGET, block_budget  # noqa: F401  (the executor's, shared)
from ..io.blockwrite import open_volume_blocks as block_output  # noqa: F401  (the commands')
from ..progress import log


def wants_blocks(reason: str | None = None) -> bool:
    """Whether the command runs by blocks.

    Yes with ``--chunked``; with neither ``--chunked`` nor ``--no-chunked``,
    when ``reason`` (why the work does not fit in memory) is given and the
    budget leaves room for blocks (:func:`block_budget`), said on stderr.
    """
    from ..errors import OutOfMemoryError
    from .resources import scale_settings

    chunked = scale_settings().chunked
    if chunked is None and reason is not None:
        try:
            block_budget()
        except OutOfMemoryError:  # no room for blocks either: the refusal stands
            return False
        log.warning("%s: running by blocks (--no-chunked to refuse instead)", reason)
        return True
    return bool(chunked)


def blocks_can_write(path, shape_zyx, dtype, write_kw) -> bool:
    """Whether samples of ``shape_zyx`` and ``dtype`` can be written by blocks to ``path``.

    A format written block by block (not compressed), and an output that fits
    the free space of its folder (:func:`volwarp_cli.execute.blocks_refusal`).
    """
    import math

    from ..execute import blocks_refusal

    nbytes = math.prod(int(n) for n in shape_zyx) * np.dtype(dtype).itemsize
    return blocks_refusal([(path, nbytes)], bool(write_kw.get("compress")),
                          int(write_kw.get("pyramid", 0) or 0)) is None


def lazy_input(path, raw=None, volume_index=None, dicom=None):
    """``(template, source)`` of an input read by blocks.

    ``template``: the input's Volume with a zero-strided placeholder (its
    geometry, frame and key/values); ``source``: a picklable
    :class:`~volwarp_cli.io.lazy.LazySource` of its samples.
    """
    from ..io.lazy import LazySource, open_volume_template
    from .common import check_input_options

    check_input_options(path, raw, dicom)
    template, array = open_volume_template(path, raw=raw, volume_index=volume_index,
                                           dicom=dicom)
    return template, LazySource(path, raw=raw, volume_index=volume_index, array=array,
                                dicom=dicom)
