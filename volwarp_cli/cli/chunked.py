"""The commands' inputs opened lazily: read box by box, in memory or by blocks.

:func:`lazy_input` gives a command's input as a header (its shape, type,
geometry, frame and key/values) and a picklable source of its samples (a
memory map, a zarr array, pages of a TIFF; reopened by path in a worker
process), whatever the executor (:mod:`volwarp_cli.execute`) then decides.
"""

from __future__ import annotations


def lazy_input(path, raw=None, volume_index=None, dicom=None):
    """``(header, source)`` of an input read by blocks.

    ``header``: the input's :class:`~volwarp_cli.volume.Header` (its shape,
    type, geometry, frame and key/values); ``source``: a picklable
    :class:`~volwarp_cli.io.lazy.LazySource` of its samples.
    """
    from ..io.lazy import LazySource, open_volume_header
    from .common import check_input_options

    check_input_options(path, raw, dicom)
    header, array = open_volume_header(path, raw=raw, volume_index=volume_index, dicom=dicom)
    return header, LazySource(path, raw=raw, volume_index=volume_index, array=array,
                              dicom=dicom)
