"""`volwarp convert IN -o OUT`: any supported volume format to any other.

DICOM SEG and RTSTRUCT inputs are read as label maps; a label map is written
as a SEG or RTSTRUCT against a reference series (``--dicom-type``).
"""

from __future__ import annotations

import os

import click

from ..errors import BadUsage
from ..io import check_output_path, write_volume
from ..labelmap import VALUES, keep_label_ids, meta_as_taken, segmentation_of, whole_ids
from ..memory import human_bytes
from ..progress import timed
from .common import load_input
from .options import (
    INPUT_PATH,
    READ_ONCE_PATH,
    Command,
    _volume_output,
    common_options,
    examples,
    input_options,
    output_option,
    write_options,
)

#: --pyramid-method: write_volume's ``labels`` for each choice
PYRAMID_METHODS = {"auto": "auto", "mode": True, "mean": False}
#: --dicom-type choices
DICOM_TYPES = ("seg", "labelmap-seg", "rtstruct")
#: the DICOM read options that choose how --reference is read when writing a segmentation
REFERENCE_CHOICES = ("series", "irregular", "duplicates")
#: --reference's help here: an input's series (as every command), or the output's
REFERENCE_HELP = ("The image series (folder, DICOMDIR or file) a segmentation lies on. "
                  "RTSTRUCT input: its ROIs are rasterised on that grid (required); SEG "
                  "input: the label map is put on its whole grid (default: the SEG's own "
                  "frames' grid); --dicom-type output: the series the SEG or RTSTRUCT "
                  "references, whose grid the label map must lie on (required; --series "
                  "chooses it when the path holds several, else the series the label map's "
                  "key/values name).")


def _output(ctx, param, value):
    """A volume output, or a ``.dcm`` file (a SEG or RTSTRUCT: ``--dicom-type`` says which)."""
    if value is not None and value.lower().endswith(".dcm"):
        if os.path.isdir(value):
            raise click.BadParameter(f"{value!r} is a directory.", ctx=ctx, param=param)
        return value
    return _volume_output(ctx, param, value)


@click.command(name="convert", cls=Command, epilog=examples(
    "volwarp convert ct_series/ -o ct.nrrd --compress",
    "volwarp convert labels.nrrd --reference ct_series/ --dicom-type seg -o seg.dcm",
))
@click.argument("input", type=INPUT_PATH)
@output_option(help_text="Output file (format by extension; .dcm with --dicom-type).",
               callback=_output, folders=True)
@write_options
@click.option("--pyramid-method", type=click.Choice(list(PYRAMID_METHODS)), default="auto",
              show_default=True,
              help="How --pyramid makes each level from the last, 2x2x2 voxels to one: "
                   "mode (the most frequent value: label maps, never an invented label), "
                   "mean (intensities), or auto (mode for integer volumes that are "
                   "piecewise constant, whatever their number of labels; else mean).")
@click.option("--values", type=click.Choice(VALUES), default=None,
              help="Take the samples as intensities or as label ids [default: labels when "
                   "INPUT looks like a label map, as `volwarp info` hints]. Labels keep every "
                   "id: a --dtype that cannot hold one is refused, and --pyramid levels take "
                   "the mode; intensities are clipped to --dtype's range, and levels take "
                   "the mean (unless --pyramid-method says).")
@click.option("--dicom-type", type=click.Choice(DICOM_TYPES), default=None,
              help="Write the label map as a DICOM SEG (seg: BINARY, segments numbered 1..K "
                   "in label order; labelmap-seg: LABELMAP, the label values kept) or "
                   "RTSTRUCT (one ROI per label, ROI Number = label) to OUTPUT.dcm, "
                   "against --reference.")
@click.option("--contours", type=click.Choice(["edges", "smooth"]), default=None,
              help="With --dicom-type rtstruct: contours on the voxel edges (default; read "
                   "back, the label map exactly), or smooth ones from each slice's sub-voxel distance "
                   "field, for planning systems that want smooth outlines (read back by "
                   "volwarp, also exact; their polygon areas are smaller: "
                   "docs/segmentations.md).")
@click.option("--segments", type=READ_ONCE_PATH, default=None, metavar="CSV",
              help="With --dicom-type: segment or ROI names, a CSV file of label,name rows; "
                   "they win over the names the label map's key/values keep from the SEG or "
                   "RTSTRUCT it was read from (default: those, else 'label N' for a SEG, "
                   "'label_N' for an RTSTRUCT).")
@input_options(reference_help=REFERENCE_HELP)
@common_options
def command(input, output, dtype, compress, byte_order, pyramid_method, values, dicom_type,
            contours, segments, raw, volume_index, dicom, reference, ome_zarr):
    """Convert INPUT to OUTPUT (format by extension), keeping geometry and key/values.

    DICOM SEG and RTSTRUCT inputs are read as label maps (--reference, --segment,
    --structure); --dicom-type writes one (docs/segmentations.md).
    """
    if values == "labels" and pyramid_method == "mean":
        raise click.UsageError("--pyramid-method mean would average label ids into ids the map "
                               "does not have: give --pyramid-method mode (or auto) with "
                               "--values labels")
    if pyramid_method != "auto" and not ome_zarr.get("pyramid"):
        raise click.UsageError(f"--pyramid-method {pyramid_method} chooses how --pyramid "
                               "levels are made: give --pyramid N (N >= 1) with it")
    writing = _dicom_output(output, dicom_type, segments, reference, dtype, compress,
                            byte_order, ome_zarr, values)
    if not writing and values is not None and dtype is None and not ome_zarr.get("pyramid"):
        raise click.UsageError(f"--values {values} decides how --dtype casts the samples and how "
                               "--pyramid's levels are made: without either it changes "
                               "nothing (convert keeps every sample as it is)")
    if contours is not None and dicom_type != "rtstruct":
        raise click.UsageError(f"--contours {contours} shapes the contours of an RTSTRUCT: "
                               "give --dicom-type rtstruct")
    check_output_path(output, option="-o")
    reference_options = {}  # how --reference is read when a segmentation is written
    if writing:
        reference_options = {k: v for k, v in (dicom or {}).items() if k in REFERENCE_CHOICES}
        if not _is_segmentation(input) and not _is_dicom_image(input):
            # (a label map file: --series, --irregular, --duplicates choose the reference's)
            dicom = {k: v for k, v in (dicom or {}).items()
                     if k not in REFERENCE_CHOICES} or None
        elif not _is_segmentation(input):
            reference_options = {}  # (a DICOM image input: they choose the input's series)
    if reference is not None and (not writing or _is_segmentation(input)):
        dicom = {**(dicom or {}), "reference": reference}  # (the input lies on that series)
    vol = load_input(input, raw, volume_index, dicom=dicom)
    if writing:
        _write_segmentation(vol, output, dicom_type, reference, segments, contours, str(input),
                            reference_options)
        return
    labels = PYRAMID_METHODS[pyramid_method]
    ids = values == "labels" or (values is None and segmentation_of(vol.meta))
    if ids and not whole_ids(vol.data):
        if values == "labels":  # (as warp, apply, distance, mesh: fractions are no ids)
            raise BadUsage(f"{input}: --values labels needs a label map (integer ids), got "
                           f"{vol.dtype} samples that are not all integers")
        ids = False  # (a float field that kept a SEG's keys: intensities)
    if values == "labels":  # (against the rule: recorded for the next command, as warp does)
        from ..warp.defaults import choose_values

        against = choose_values(vol.data, "labels", name=str(input), meta=vol.meta).against_rule
        vol = vol.replace(meta=meta_as_taken(vol.meta, True, against))
    elif values == "intensity":  # (its label keys dropped, as warp's and apply's)
        vol = vol.replace(meta=meta_as_taken(vol.meta, False, False))
    if labels == "auto" and values is not None:
        labels = values == "labels"
    elif labels == "auto" and ids:  # (a SEG's ids whatever they look like)
        labels = True
    if dtype is not None and dtype != vol.dtype.name:
        # --values decides, else the label rule: --pyramid-method makes the coarser levels
        # only (a label map's `mean` levels are asked for; its ids 300 and 1000 clipped to
        # 255 in the full-resolution level were not)
        keep_label_ids(vol.data, dtype, str(input),
                       "auto" if values is None else values == "labels", vol.meta)
        vol = vol.replace(meta=_without_range(vol.meta))
    _check_write_memory(vol, output, dtype, compress, byte_order, labels, ome_zarr)
    with timed(f"write {output}"):  # (its key/values kept, the provenance of its samples too)
        write_volume(vol, output, dtype=dtype, compress=compress, byte_order=byte_order,
                     labels=labels, **ome_zarr)


def _without_range(meta) -> dict:
    """``meta`` without MetaIO's ``ElementMin``/``ElementMax``: the range of the samples as read.

    A ``--dtype`` cast clips and rounds them: an int16 scan of -1000..1000 as uint8 is
    0..255, and a header still saying -1000..1000 was kept by ``convert`` as true.
    """
    from ..io.metaimage import AS_READ_FIELDS, PREFIX

    return {k: v for k, v in meta.items() if k not in {PREFIX + f for f in AS_READ_FIELDS}}


def _check_write_memory(vol, output, dtype, compress, byte_order, labels="auto",
                        ome_zarr=None) -> None:
    """Refuse, before anything is written, a write whose copies do not fit what the read left.

    The budget is the process's peak: the samples read are held, and the
    write's own copies (:func:`~volwarp_cli.io.write_memory`: a cast, the
    file's byte order, a compressed stream made whole; an OME-Zarr store's
    write beside its cast) come on top of them, with the writer's modules and
    libraries (ISA-L's for a ``.nii.gz``: 1.8 MiB over a tight limit,
    uncounted): where the budget is tight they are loaded first
    (:func:`~volwarp_cli.io.load_writer`) and counted.
    """
    import numpy as np

    from ..io import load_writer, write_memory
    from ..memory import ensure_fits_once_loaded

    need = write_memory(output, vol.data.shape, vol.dtype, dtype=dtype, compress=compress,
                        byte_order=byte_order, labels=labels, **(ome_zarr or {}))
    out = np.dtype(dtype or vol.dtype).name
    ensure_fits_once_loaded(need, f"writing {output} ({'x'.join(map(str, vol.shape_xyz))} "
                                  f"{out}, beside the {human_bytes(vol.data.nbytes)} read)",
                            lambda: load_writer(output, compress))


def _dicom_output(output, dicom_type, segments, reference, dtype, compress, byte_order,
                  ome_zarr, values=None) -> bool:
    """True when OUTPUT is a SEG or RTSTRUCT; usage errors for options that do not fit."""
    is_dcm = output.lower().endswith(".dcm")
    if not is_dcm:
        if dicom_type or segments:
            given = "--dicom-type" if dicom_type else "--segments"
            raise click.UsageError(f"{given} writes a DICOM segmentation: give -o NAME.dcm")
        return False
    if dicom_type is None:
        raise click.UsageError(f"-o {output}: volwarp reads DICOM images but does not write it; "
                               "it writes DICOM segmentations: give --dicom-type "
                               "seg|labelmap-seg|rtstruct and --reference SERIES")
    if reference is None:
        raise click.UsageError(f"--dicom-type {dicom_type} writes against the image series the "
                               "label map lies on: give --reference SERIES")
    if dtype or compress or byte_order != "little" or ome_zarr.get("pyramid") or \
            ome_zarr.get("ome_zarr_version") != "0.5" or values:
        raise click.UsageError("--dtype, --compress, --byte-order, --pyramid, "
                               "--ome-zarr-version and --values describe volume outputs, not "
                               f"a DICOM {dicom_type} (its labels are labels)")
    return True


def _is_segmentation(path) -> bool:
    from ..io.dicom import segmentation_kind

    return segmentation_kind(path) is not None


def _is_dicom_image(path) -> bool:
    from ..io import volume_format

    try:
        return volume_format(path, reading=True) == "dicom" and not _is_segmentation(path)
    except Exception:  # (an unknown extension: the reader says so)
        return False


def _write_segmentation(vol, output, dicom_type, reference, segments, contours,
                        source, reference_options) -> None:
    """Write ``vol`` as a SEG or RTSTRUCT against ``reference``.

    ``reference_options``: ``series``, ``irregular``, ``duplicates`` as the
    command line gave them, choosing how the reference is read; without
    ``series``, the series the map's key/values name is taken when the
    reference holds several.
    """
    from ..io.dicom import DicomSeriesChoiceError, read_reference
    from ..io.dicom_seg import read_names, write_seg

    names = read_names(segments) if segments else None
    want = tuple(vol.meta.get(k) for k in ("DICOM_ReferencedSeriesInstanceUID",
                                           "DICOM_SeriesInstanceUID") if vol.meta.get(k))
    with timed(f"read {reference}"):
        try:
            ref = read_reference(reference, want_series=want, **reference_options)
        except DicomSeriesChoiceError as exc:  # (say which path: the output's reference)
            raise DicomSeriesChoiceError(f"--reference {exc}") from None
    with timed(f"write {output}"):
        if dicom_type == "rtstruct":
            from ..io.rtstruct import write_rtstruct

            write_rtstruct(vol, output, ref, names=names, contours=contours or "edges",
                           source=source, names_from=segments)
        else:
            write_seg(vol, output, ref, labelmap=dicom_type == "labelmap-seg", names=names,
                      source=source, names_from=segments)
