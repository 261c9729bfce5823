"""The commands' inputs opened lazily: read box by box, in memory or by blocks.

:func:`lazy_input` gives a command's input as a template (its geometry, frame
and key/values) and a picklable source of its samples (a memory map, a zarr
array, pages of a TIFF; reopened by path in a worker process), whatever the
executor (:mod:`volwarp_cli.execute`) then decides.
"""

from __future__ import annotations


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
