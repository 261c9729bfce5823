"""Big inputs without loading them: a volume's geometry and an array read on slicing.

:func:`open_volume_lazy` gives ``(Geometry, array)``, where ``array`` has
``shape`` (z, y, x), ``dtype`` and numpy slicing ``array[z0:z1, y0:y1, x0:x1]``
that reads only the samples asked for; the geometry is the one
:func:`~volwarp_cli.io.read_volume` gives for the same file (the readers'
own header parsers are used). Per format:

- **OME-Zarr**: level 0 through zarr (chunks read on demand); inside a command's run,
  a store whose samples fit their share of the budget is read whole instead (each
  block decoded its chunks again: a 256^3 warp 2.35 s against 0.5 s from NRRD).
- **NRRD** raw encoding (attached, or detached with one data file), **MetaImage**
  uncompressed (``.mha`` or ``.mhd`` with one data file) and headerless
  **raw**: a :class:`.filearray.FileArray` in the file's byte order, read with
  ``pread`` box by box (slices come back in the machine's order). Not a memory
  map: mapped pages would count in the process's memory as they are touched.
  Truncated meanwhile, a read stops the run with one line.
- **TIFF** 3-D stacks of one sample per pixel, checked by
  :func:`.tiff.read_tiff_stack` (what ``read_volume`` refuses is refused,
  with its message): tifffile's zarr interface (``imread(aszarr=True)``),
  pages decoded on demand, where tifffile's series is the stack as
  (z, y, x); ImageJ's one-IFD stack over 4 GiB by ``pread``.
- **NIfTI**: a :class:`.filearray.FileArray` of the samples (nibabel's
  ``[x, y, z]`` in Fortran order are ``[z, y, x]`` in C order; volwarp's
  reader does nothing else to them: the direction matrix holds the
  reflections), opened by :func:`.nifti.open_nifti` as ``read_volume`` opens
  it (CIFTI refused, a file shorter than its samples refused before any
  work); a 4-D file's volume or a 5-D file's component (``volume_index``)
  is its own block of samples; ``scl_slope``/``scl_inter`` are applied box
  by box (:class:`ScaledSamples`).

The header's key/values are ``read_volume``'s, from the same functions of
the readers where they have them (NIfTI header fields and extension,
MetaImage fields; for NRRD the key/values and ``NRRD_content``,
``NRRD_space units``, ``NRRD_measurement frame`` as :func:`.nrrd.read_nrrd`
makes them), so that an output by blocks carries what the in-memory one does.

- **Compressed** NIfTI (``.nii.gz``), gzip NRRD (no byte skip, one data
  file) and compressed MetaImage, 3-D: read whole where their samples fit
  their share of the memory budget (:func:`~volwarp_cli.memory.read_by_box`);
  larger, inflated once into a scratch file and read from it by box
  (:mod:`.inflated`).

Anything else (bzip2/ascii encodings, 4-D NRRD, MetaImage or raw files with
several volumes or components, a TIFF whose tifffile series is not its stack,
DICOM that is resampled) is read whole by
``read_volume``, unless ``require_lazy`` asks for an error instead.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..errors import FormatError, VolwarpError
from ..geometry import Geometry
from ..samples import check_dtype, voxel_count
from ..volume import Header, xyz_to_zyx
from .filearray import FileArray

__all__ = ["open_volume_lazy", "open_volume_header", "NotLazy",
           "LazySource", "make_header"]


class NotLazy(Exception):
    """Raised inside: this file cannot be read lazily (the reason is the message)."""


class NoRoomToInflate(NotLazy):
    """A compressed input too large to hold, and no disk room to inflate it (the message)."""


def open_volume_lazy(path: str | os.PathLike, *, raw=None, volume_index: int | None = None,
                     require_lazy: bool = False, dicom: dict | None = None):
    """``(Geometry, array_like)`` of the volume file at ``path`` (module notes).

    ``raw``: the :class:`~volwarp_cli.io.raw.RawLayout` of a headerless file;
    ``volume_index``: as for ``read_volume`` (OME-Zarr; other 4-D files are
    read whole). ``require_lazy``: raise a VolwarpError naming the reason
    when the file would have to be read whole.
    """
    header, array = open_volume_header(path, raw=raw, volume_index=volume_index,
                                       require_lazy=require_lazy, dicom=dicom)
    return Geometry.of(header), array


def open_volume_header(path: str | os.PathLike, *, raw=None, volume_index: int | None = None,
                       require_lazy: bool = False, dicom: dict | None = None,
                       samples: bool = True, inflate: bool = True):
    """:func:`open_volume_lazy` with the file's Header: ``(header, array_like)``.

    ``header`` (a :class:`~volwarp_cli.volume.Header`) is the Volume
    ``read_volume`` would give without its samples (their shape and type):
    its frame (``space``, ``file_space``) and key/values are the file's, for
    the outputs made from it. A file read whole gives its Volume's header and
    its samples.

    ``samples=False``: the header is what is wanted; a compressed file gives
    it with None for the samples (nothing inflated). ``inflate=False``: a
    compressed file too large to hold is read whole, never copied to scratch
    (a worker process reopening a command's input: the command decides).
    Copies to scratch are made only inside a command's run
    (:func:`~volwarp_cli.runscope.run_scope`), which removes them at its end.
    """
    from ..runscope import stop_if_dry_run
    from . import read_volume, volume_format
    from .inputs import refuse_stream_input

    stop_if_dry_run(path)  # (volwarp batch's checks of a step end here)
    path = Path(path)
    if not path.exists():  # (as read_volume says it: a FormatError, not an OSError)
        raise FormatError(f"{path}: no such file")
    refuse_stream_input(path)
    fmt = volume_format(path, reading=True)
    try:
        if fmt == "dicom":  # a stack of files: slabs read from their frames' files
            from .dicom import is_dicom_path

            if path.is_dir() and not is_dicom_path(path):
                raise NotLazy("no DICOM files")  # (read_volume says so, as in memory)
            if volume_index is not None:
                raise NotLazy("a DICOM input has one volume")  # (read_volume says so)
            from .dicom._read import open_dicom_lazy

            opened = open_dicom_lazy(path, **(dicom or {}))
            if opened is None:
                raise NotLazy("its stack is resampled (a gantry tilt or irregular spacing)")
            return opened
        if fmt == "omezarr":
            from .omezarr import LazyOmeZarr, open_omezarr

            opened = open_omezarr(path, volume_index)
            if samples and not require_lazy and _fits_whole(
                    voxel_count(opened.view_shape) * opened.array.dtype.itemsize):
                # (its chunks decoded once, not again for each box: a 256^3 warp of a store
                # took 2.35 s against 0.5 s for the same volume as NRRD)
                raise NotLazy("a store whose samples fit in memory is read whole")
            lazy = LazyOmeZarr(opened)
            return make_header(opened.where, lazy.shape, lazy.dtype,
                               spacing=opened.spacing, origin=opened.origin,
                               direction=opened.direction, space=opened.space,
                               file_space=opened.file_space, meta=opened.meta), lazy
        copy = "header" if not samples else "inflate" if inflate else "never"
        if fmt == "nifti":  # (a volume or component of a 4-D or 5-D file too)
            return _nifti(path, copy, volume_index)
        if fmt == "tiff":  # (an image of a TIFF holding several too)
            return _tiff(path, volume_index)
        if volume_index not in (None, 0):
            raise NotLazy("a volume of a 4-D file is read whole")
        openers = {"nrrd": lambda: _nrrd(path, copy), "metaimage": lambda: _metaimage(path, copy),
                   "raw": lambda: _raw(path, raw)}
        if fmt not in openers:
            raise NotLazy(f"{fmt} files are read whole")
        return openers[fmt]()
    except NotLazy as why:
        if require_lazy:
            raise VolwarpError(f"{path}: cannot be read without loading it ({why}); write it "
                               "as .ome.zarr or uncompressed .nrrd first") from None
        no_room = str(why) if isinstance(why, NoRoomToInflate) else None
    from .inflated import naming_no_room

    with naming_no_room(no_room):
        vol = read_volume(path, raw=raw, volume_index=volume_index, dicom=dicom)
    return vol.header, vol.data


def _fits_whole(nbytes: int) -> bool:
    """Whether samples of ``nbytes`` are read whole rather than by box.

    Inside a command's run, where they fit their share of the memory budget
    (:func:`~volwarp_cli.memory.read_by_box`).
    """
    from ..memory import read_by_box
    from ..runscope import in_run

    return in_run() and not read_by_box(nbytes)


def _inflated(original: Path, nbytes: int, file_dtype, shape_zyx, where: str, fill,
              copy: str, *, part=0, held: int | None = None):
    """A compressed input's samples read by box from a scratch copy, where too big to hold.

    ``copy``: "header" (None: the samples are not wanted), "never" or
    "inflate"; ``part``: which block of the file's samples (as
    :func:`.inflated.inflated_array`); ``held``: what reading it whole holds
    (default ``nbytes``; a scaled NIfTI's float samples too). Raises NotLazy
    where that fits its share of the memory budget (read whole: faster),
    outside a command's run or where ``copy`` forbids a copy, and
    :class:`NoRoomToInflate` where the disk has no room.
    """
    from ..runscope import in_run
    from .inflated import NoRoom, inflated_array

    if copy == "header":
        return None
    if copy == "never" or not in_run():
        raise NotLazy("compressed samples are read whole")
    if _fits_whole(nbytes if held is None else held):
        raise NotLazy("compressed samples that fit in memory are read whole")
    try:
        return inflated_array(original, nbytes, file_dtype, shape_zyx, where, fill, part)
    except NoRoom as why:
        raise NoRoomToInflate(str(why)) from None


def make_header(where: str, shape_zyx, dtype, *, error=FormatError, **geometry) -> Header:
    """The :class:`~volwarp_cli.volume.Header` of a file's samples, or ``error`` naming ``where``.

    :func:`.common.make_volume` without the samples: the Header's own checks
    (a singular direction, a spacing that is not positive, ...) do not know
    which file the geometry came from.
    """
    try:
        return Header(shape_zyx, dtype, **geometry)
    except VolwarpError as exc:
        raise error(f"{where}: {exc}") from None


def _memmap(file: Path, dtype: np.dtype, offset: int, shape_zyx, where: str, *,
            kind=FileArray):
    """The samples in ``file`` as a :class:`.filearray.FileArray` (read by pread, not mapped).

    Checked for truncation first; the file is noted as an input, and watched:
    an output is not renamed into place when it changed meanwhile
    (:func:`.mapped.watch`; read by blocks as the work went, a scan rewritten
    in place gave a mix of the two, exit 0).
    """
    from .common import note_input
    from .mapped import watch

    nbytes = voxel_count(shape_zyx) * dtype.itemsize
    with open(file, "rb") as fh:
        size = os.fstat(fh.fileno()).st_size
        if offset < 0 or size - offset < nbytes:
            raise FormatError(f"{where}: data is truncated: expected {nbytes} bytes of samples, "
                              f"found {max(size - max(offset, 0), 0)}")
        note_input(fh)
        watch(fh, str(file))
    return kind(file, dtype, offset, shape_zyx)


# -- NRRD -------------------------------------------------------------------------------

def _nrrd(path: Path, copy: str, *, vectors: tuple | None = None):
    """``(header, samples)`` of a 3-D NRRD; of a vector image too with ``vectors``.

    ``vectors``: ``(count, kinds)`` wanted (:func:`open_vectors_lazy`).
    """
    from . import nrrd
    from .common import open_data_file

    where = str(path)
    with open(path, "rb") as fh:
        fields, keyvals = nrrd.read_header(fh, where)
        for req in ("type", "dimension", "sizes", "encoding"):
            if req not in fields:
                raise NotLazy(f"no '{req}' field")
        encoding = nrrd._ENCODINGS.get(fields["encoding"].lower())
        if encoding not in ("raw", "gzip"):
            raise NotLazy(f"encoding {fields['encoding']} is read whole")
        try:
            dim = int(fields["dimension"])
            sizes = [int(s) for s in fields["sizes"].split()]
        except ValueError:
            raise NotLazy("bad sizes") from None
        if len(sizes) != dim or min(sizes) <= 0:
            raise NotLazy("bad sizes")
        axis = None  # the components' axis of a vector image: first (interleaved) or last
        if vectors and dim == 4:
            try:
                axis = nrrd._component_axis(fields, dim, sizes, where)
            except FormatError:
                raise NotLazy("not one component axis") from None
            if axis not in (0, 3):
                raise NotLazy("components neither interleaved nor in planes")
        elif dim != 3:
            raise NotLazy("only 3-D files are mapped")
        else:  # (a 2-D image of components is refused as the whole read refuses it)
            nrrd._component_axis(fields, dim, sizes, where)
        type_name = fields["type"].lower()
        if type_name not in nrrd._TYPES:
            raise NotLazy("unknown type")
        dtype = check_dtype(nrrd._TYPES[type_name], where)
        file_dtype = nrrd.file_type(fields, dtype, encoding, where)
        spacing, origin, direction, space = nrrd._geometry(fields, dim, where)
        files = nrrd._data_files(fields, path, fh, where, sizes)
        lineskip = nrrd._whole(fields, ("line skip", "lineskip"), where)
        byteskip = nrrd._whole(fields, ("byte skip", "byteskip"), where, minimum=-1)
        if files is not None and len(files) != 1:
            raise NotLazy("data split over several files")
        if encoding == "gzip" and byteskip != 0:
            raise NotLazy("a byte skip of compressed data is read whole")
        nbytes = voxel_count(sizes) * dtype.itemsize
        if files is None:
            data_path, dfh = path, fh
        else:
            data_path = files[0]
            dfh = open_data_file(path, data_path, where)
        try:
            if files is not None:
                dfh.seek(0)
            for _ in range(lineskip):
                if not dfh.readline():
                    raise FormatError(f"{where}: file ends inside 'line skip'")
            size = os.fstat(dfh.fileno()).st_size
            start = size - nbytes if byteskip == -1 else dfh.tell() + byteskip
            if byteskip == -1 and start < dfh.tell():  # (the header read as samples)
                raise FormatError(f"{where}: data is truncated: expected {nbytes} bytes of "
                                  "samples at the end ('byte skip: -1')")
        finally:
            if dfh is not fh:
                dfh.close()
    if encoding == "raw" and byteskip != -1 and size - start > nbytes:
        raise FormatError(f"{data_path}: file has {size - start} bytes of samples, expected "
                          f"{nbytes} (wrong sizes or type in the header?)")
    spatial = [s for a, s in enumerate(sizes) if a != axis]
    shape = xyz_to_zyx(spatial)
    header = make_header(where, shape, dtype, spacing=spacing, origin=origin,
                         direction=direction, space=space,
                         meta=_nrrd_meta(fields, keyvals, space, where))
    count = 1 if axis is None else sizes[axis]
    _wanted(vectors, count, dtype)
    layout = _vector_layout(shape, count, planar=axis == 3)
    if encoding == "gzip":
        samples = _inflated(data_path, nbytes, file_dtype, layout, where,
                            _stream_at(data_path, start, nbytes), copy)
    else:
        samples = _memmap(data_path, file_dtype, start, layout, str(data_path))
    return (header, samples, count, axis == 3) if vectors else (header, samples)


def _vector_layout(shape_zyx, count: int, *, planar: bool) -> tuple:
    """The 3-D shape a file's ``count`` samples a voxel are read as.

    (z, y, x * count) where they are interleaved, (count * z, y, x) where each
    component is a volume of its own.
    """
    nz, ny, nx = shape_zyx
    return (count * nz, ny, nx) if planar else (nz, ny, nx * count)


def open_vectors_lazy(path: str | os.PathLike, *, count: int | None = None,
                      kinds: str = "biuf"):
    """A NRRD or MetaImage vector image's samples read by box: ``(header, samples, n, planar)``.

    ``header``: the grid's :class:`~volwarp_cli.volume.Header` (the file's
    frame and key/values; samples of ``header.dtype``); ``samples``: the
    file's samples (a :class:`.filearray.FileArray`, or a compressed file's
    scratch copy) as the 3-D array of :func:`_vector_layout`, ``n`` a voxel,
    ``planar`` whether they are one volume per component. ``count``, ``kinds``:
    the components a voxel and the sample kinds wanted (numpy's ``dtype.kind``).
    Raises :class:`NotLazy` where the file is read whole (other vectors than
    wanted, a compressed one that fits its share of the budget, data split
    over files, other layouts), before any copy is made.
    """
    from . import volume_format

    path = Path(path)
    fmt = volume_format(path, reading=True)
    want = (count, kinds)
    if fmt == "nrrd":
        return _nrrd(path, "inflate", vectors=want)
    if fmt == "metaimage":
        return _metaimage(path, "inflate", vectors=want)
    raise NotLazy(f"{fmt} vector images are read whole")


def _wanted(vectors, count: int, dtype) -> None:
    """Raise NotLazy unless the file holds the vectors wanted (before any inflating)."""
    if vectors and (vectors[0] not in (None, count) or dtype.kind not in vectors[1]):
        raise NotLazy(f"{count} {dtype} samples a voxel: read whole")


def _stream_at(data_path: Path, start: int, nbytes: int):
    """A ``fill(sink)`` of :func:`_inflated`: the gzip/zlib stream at ``start`` of ``data_path``."""
    from .common import inflate_exact

    def fill(sink) -> None:
        with open(data_path, "rb") as fh:
            fh.seek(start)
            inflate_exact(fh, nbytes, str(data_path), sink)

    return fill


def _nrrd_meta(fields: dict, keyvals: dict, space, where: str) -> dict:
    """The key/values :func:`~volwarp_cli.io.nrrd.read_nrrd` gives a 3-D file."""
    from .nrrd import kept_fields

    return {**keyvals, **kept_fields(fields, space, where)}


# -- MetaImage ------------------------------------------------------------------------------

def _metaimage(path: Path, copy: str, *, vectors: tuple | None = None):
    """``(header, samples)`` of a 3-D MetaImage; with ``vectors``, of channels too (as _nrrd)."""
    from . import metaimage as mi
    from .common import open_data_file

    where = str(path)
    with open(path, "rb") as fh:
        pairs = mi.read_header(fh, where)
        header_end = fh.tell()
    fields = mi.header_fields(pairs, where)
    for req in ("NDims", "DimSize", "ElementType"):
        if req not in fields:
            raise NotLazy(f"no '{req}' field")
    if "ObjectType" in fields and fields["ObjectType"][1] != "Image":
        raise NotLazy("not an image")  # (read_volume says so)
    if mi._int(fields, "NDims", 0, where) != 3:
        raise NotLazy("only 3-D files are mapped")
    count = mi._int(fields, "ElementNumberOfChannels", 1, where)
    if count != 1 and not vectors or count < 1:
        raise NotLazy("several channels per voxel")
    if not mi._bool(fields, "BinaryData", True, where):
        raise NotLazy("ascii data is read whole")
    compressed = mi._bool(fields, "CompressedData", False, where)
    sizes = mi._numbers(fields, "DimSize", 3, where, int)
    type_name = fields["ElementType"][1]
    if type_name not in mi._TYPES or min(sizes) <= 0:
        raise NotLazy("unknown type or sizes")
    dtype = check_dtype(mi._TYPES[type_name], where)
    msb = mi._bool(fields, "BinaryDataByteOrderMSB", False, where)
    file_dtype = dtype.newbyteorder(">" if msb else "<")
    spacing, origin, direction = mi._geometry(fields, 3, where)
    header_size = mi._int(fields, "HeaderSize", 0, where)
    if header_size < -1:
        raise NotLazy("a HeaderSize below -1")  # (read_volume says so)
    spec = fields["ElementDataFile"][1]
    nbytes = voxel_count(sizes) * count * dtype.itemsize
    if spec in ("LOCAL", "Local", "local"):
        data_path, start = path, header_end
    else:
        if spec.split()[:1] == ["LIST"] or "%" in spec:
            raise NotLazy("data split over several files")
        data_path, start = path.parent / spec, 0
        open_data_file(path, data_path, where).close()  # (the folder rule, as the reader)
    size = os.path.getsize(data_path)
    if header_size > 0:
        start = header_size
    elif header_size == -1 and not compressed:
        if size - nbytes < start:  # (the header read as samples: a file cut short)
            raise FormatError(f"{where}: data is truncated: expected {nbytes} bytes of "
                              "samples at the end ('HeaderSize = -1')")
        start = size - nbytes
    if compressed:
        start = mi.compressed_start(mi._int(fields, "CompressedDataSize", -1, where),
                                    header_size, size, start, str(data_path))
    elif size - start > nbytes:
        raise FormatError(f"{data_path}: file has {size - start} bytes of samples, expected "
                          f"{nbytes} (wrong DimSize or ElementType in the header?)")
    shape = xyz_to_zyx(sizes)
    header = make_header(where, shape, dtype, spacing=spacing, origin=origin,
                         direction=direction, space="left-posterior-superior",
                         file_space="left-posterior-superior", meta=mi._meta(pairs, direction))
    _wanted(vectors, count, dtype)
    layout = _vector_layout(shape, count, planar=False)  # (channels: interleaved)
    if compressed:
        samples = _inflated(data_path, nbytes, file_dtype, layout, where,
                            _stream_at(data_path, start, nbytes), copy)
    else:
        samples = _memmap(data_path, file_dtype, start, layout, str(data_path))
    return (header, samples, count, False) if vectors else (header, samples)


# -- raw --------------------------------------------------------------------------------

def _raw(path: Path, layout):
    where = str(path)
    if layout is None:
        raise VolwarpError(f"{where}: a raw file needs --raw-shape and --raw-dtype "
                           "(or a detached .nhdr header pointing at it)")
    dtype = check_dtype(layout.dtype, where)
    shape = xyz_to_zyx(tuple(int(s) for s in layout.shape))
    nbytes = voxel_count(shape) * dtype.itemsize
    try:
        size = os.path.getsize(path)
    except OSError as exc:
        raise FormatError(f"{where}: cannot open ({exc.strerror})") from None
    if size != nbytes + layout.header_bytes:
        raise FormatError(f"{where}: file is {size} bytes but {'x'.join(map(str, layout.shape))}"
                          f" {dtype.name} needs {nbytes + layout.header_bytes} bytes")
    from .raw import raw_placement

    header = make_header(where, shape, dtype, error=VolwarpError,
                         **raw_placement(layout, where, shape))
    file_dtype = dtype.newbyteorder("<" if layout.endian == "little" else ">")
    return header, _memmap(path, file_dtype, layout.header_bytes, shape, where)


# -- TIFF -------------------------------------------------------------------------------

def _tiff(path: Path, volume_index: int | None = None):
    """``(header, samples)`` of a TIFF stack: :func:`.tiff.read_tiff`'s checks, then by box.

    Pages decoded on demand through tifffile's zarr view of the chosen image's
    series, where that series is the stack as (z, y, x); ImageJ's one-IFD
    layout of a stack over 4 GiB is read by box from the file. An ImageJ value
    calibration is applied box by box. Anything else is read whole.
    """
    import tifffile
    import zarr

    from ..runscope import at_run_end, in_run
    from . import tiff as tiff_io

    where = str(path)
    if in_run():  # (its pages are read by tifffile as the work goes: a file rewritten
        # meanwhile gave a mix of the two, exit 0; refused before any rename instead)
        from .mapped import watch

        watch(path)
    # (refuses what the whole reader refuses, as it does)
    stack = tiff_io.read_tiff_stack(path, volume_index)
    header = make_header(where, stack.shape, stack.dtype, **stack.placement)
    if stack.planes_at is not None:
        samples = _memmap(path, stack.file_dtype, stack.planes_at, stack.shape, where)
    else:
        store = tifffile.imread(path, aszarr=True, series=stack.image)  # (keeps its files open)
        try:
            arr = zarr.open(store, mode="r")
            if arr.ndim > 3 and all(n == 1 for n in arr.shape[:-3]):  # (size-1 axes: dropped)
                arr = _Squeezed(arr)
            if (tuple(arr.shape) != stack.shape
                    or np.dtype(arr.dtype).newbyteorder("=") != stack.file_dtype.newbyteorder("=")):
                # e.g. a series of tifffile's whose pages are not the image's only
                raise NotLazy(f"tifffile's zarr view is {arr.shape} {arr.dtype}, not the stack")
        except BaseException:
            store.close()
            raise
        samples = _ZarrView(arr, store, where)
        if in_run():  # (a read that fails closes the store, but zarr's other chunk reads of
            # that box, still running, may open a file again: closed when the command ends,
            # before the failure's traceback is collected with the view, and the file)
            at_run_end(samples.close)
    if stack.calibration is not None:
        c0, c1 = stack.calibration
        samples = _CalibratedTiff(samples, c1, c0, stack.dtype)
    return header, samples


class _Squeezed:
    """A zarr array's last three axes, its leading ones of size 1 indexed at 0."""

    def __init__(self, arr):
        self._arr, self._lead = arr, (0,) * (arr.ndim - 3)
        self.shape, self.dtype, self.ndim = tuple(arr.shape[-3:]), arr.dtype, 3

    def __getitem__(self, key):
        return self._arr[self._lead + key]


def _settle_zarr_reads(timeout: float = 5.0) -> None:
    """Wait (up to ``timeout`` s) for the reads under way on zarr's event loop to end."""
    import asyncio

    from zarr.core.sync import sync

    async def settle():
        others = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
        if others:
            await asyncio.wait(others, timeout=timeout)

    try:
        sync(settle())
    except Exception:  # (zarr's loop gone, or this is its thread: close at once)
        pass


class _ZarrView:
    """A 3-D zarr array (z, y, x) with numpy's negative steps.

    ``store`` (tifffile's zarr store, which keeps the files it has read open) is
    closed by :meth:`close` or when the view is dropped, as a
    :class:`.filearray.FileArray` closes its file. Samples that cannot be
    decoded are a FormatError naming ``where``, the whole reader's.
    """

    def __init__(self, arr, store=None, where: str = ""):
        self._arr = arr
        self._store = store
        self._where = where
        self.shape = tuple(arr.shape)
        self.dtype = arr.dtype
        self.ndim = 3

    def close(self) -> None:
        """Close the store's open files (tifffile opens them again on the next read).

        zarr's reads still under way first end: the reads of a box's other
        chunks go on after one of them failed, and one starting after the
        close opened the file again, for good (a ResourceWarning at a garbage
        collection in whatever ran next).
        """
        if self._store is not None:
            _settle_zarr_reads()
            self._store.close()

    def __del__(self):
        try:  # (no waiting here: a collection may run on zarr's own thread)
            if self._store is not None:
                self._store.close()
        except Exception:  # pragma: no cover - interpreter shutdown
            pass

    def __getitem__(self, key):
        key = key if isinstance(key, tuple) else (key,)
        if any(k is Ellipsis for k in key):
            i = next(j for j, k in enumerate(key) if k is Ellipsis)
            key = key[:i] + (slice(None),) * (3 - len(key) + 1) + key[i + 1:]
        key = key + (slice(None),) * (3 - len(key))
        forward, flips, axis = [], [], 0
        for k, n in zip(key, self.shape, strict=True):
            if isinstance(k, slice) and (k.step or 1) < 0:
                idx = range(*k.indices(n))
                forward.append(slice(idx[-1], idx[0] + 1, -idx.step) if len(idx)
                               else slice(0, 0))
                flips.append(axis)
            else:
                forward.append(k)
            axis += isinstance(k, slice)
        failure = None
        try:
            out = np.asarray(self._arr[tuple(forward)])
        except Exception as exc:  # tifffile raises many types for damaged files
            from .tiff import unreadable_data

            failure = unreadable_data(self._where, exc)
        if failure is not None:
            # (raised here, not in the handler: tifffile's failure, whose traceback holds the
            # files its store opened, is not kept as the context; those files are closed
            # now, not at a garbage collection in whatever ran next)
            self.close()
            raise failure
        return np.flip(out, axis=tuple(flips)) if flips else out

    def __array__(self, dtype=None, copy=None):
        out = np.asarray(self[...])
        return out if dtype is None else out.astype(dtype)


# -- NIfTI ------------------------------------------------------------------------------

def _nifti(path: Path, copy: str, volume_index: int | None):
    from . import _check_content, nifti

    where = str(path)
    _check_content(path, "nifti")  # (read_volume's own messages for a missing file)
    nf = nifti.open_nifti(path)  # checked as read_volume does: class, sizes, file length
    k, component = nf.select(volume_index)  # (a 4-D file without an index: read_volume's error)
    dtype = nf.sample_dtype()
    geometry, chosen = nifti.nifti_geometry(nf.header, where)
    shape = xyz_to_zyx(nf.shape[:3])
    header = make_header(where, shape, dtype, meta=nifti.nifti_meta(nf, chosen, component),
                         **geometry)
    start = nf.offset + k * nf.block_bytes  # (the volume's or the component's samples)
    if nf.gzipped:  # (the samples' bytes of the whole stream: its checks as read whole)
        def fill(sink):
            nifti.gunzip_range_into(nf.path, start, nf.block_bytes,
                                    nf.offset + nf.data_bytes, where, nf.layout(), sink)

        whole = nf.block_bytes + (voxel_count(shape) * 8 if nf.scaled else 0)  # (as read)
        array = _inflated(path, nf.block_bytes, nf.file_dtype, shape, where, fill, copy,
                          part=start, held=whole)
    else:
        array = _memmap(path, nf.file_dtype, start, shape, where, kind=_NiftiView)
    if nf.scaled and array is not None:
        array = ScaledSamples(array, nf.slope, nf.inter, dtype)
    return header, array


class ScaledSamples:
    """A NIfTI's samples with its ``scl_slope``/``scl_inter`` applied box by box.

    As :func:`.nifti.read_nifti` applies them to the whole (nibabel's
    ``apply_read_scaling``, then the sample type): element by element, so
    every box is the whole's. Picklable, and carried to a worker process
    where its samples are (:class:`.inflated.InflatedArray`).
    """

    def __init__(self, base, slope, inter, dtype):
        self.base, self.slope, self.inter = base, slope, inter
        self.dtype = np.dtype(dtype)
        self.shape = tuple(base.shape)
        self.ndim = 3
        self.portable = getattr(base, "portable", False)

    def reachable(self) -> bool:
        """Whether this process sees the samples' file (:meth:`.inflated.InflatedArray.reachable`)."""
        return _reachable(self.base)

    def __getitem__(self, key) -> np.ndarray:
        from .nifti import nibabel

        apply_read_scaling = nibabel().volumeutils.apply_read_scaling
        raw = self.base[key]
        with np.errstate(all="ignore"):
            return apply_read_scaling(raw, np.asanyarray(self.slope),
                                      np.asanyarray(self.inter)).astype(self.dtype)

    def __array__(self, dtype=None, copy=None):
        if copy is False:
            raise ValueError("scaled samples are computed: a copy cannot be avoided")
        out = self[...]
        return out if dtype is None else out.astype(dtype)

    def close(self) -> None:
        """Close the samples' file."""
        self.base.close()


class _CalibratedTiff(ScaledSamples):
    """A TIFF's samples with ImageJ's straight-line calibration applied box by box.

    :func:`.tiff.calibrate`, as :func:`.tiff.read_tiff` applies it to the whole.
    """

    def __getitem__(self, key) -> np.ndarray:
        from .tiff import calibrate

        return calibrate(np.asarray(self.base[key]), (self.inter, self.slope))


class _NiftiView(FileArray):
    """The samples of an uncompressed NIfTI file, read by ``pread`` as a ``[z, y, x]`` array.

    nibabel's ``[x, y, z]`` (Fortran order, x fastest) are these samples in C
    order; volwarp's reader does nothing else to them (the direction matrix
    holds the reflections).
    """


class LazySource:
    """An input opened on demand: picklable, so a worker process opens it itself.

    ``path`` and the reader's options; the opened array (a memory map, a zarr
    array) is dropped from a pickled copy and opened again where it is used,
    with the permission the run that made it had to read a detached header's
    data file outside its folder (``--allow-outside-data``: a worker process
    or thread has its own run scope, :mod:`volwarp_cli.runscope`).
    """

    def __init__(self, path, *, raw=None, volume_index=None, array=None, dicom=None):
        from ..runscope import run_files

        # (absolute: a worker process, here or on another machine, may run elsewhere)
        self.path = os.path.abspath(path)
        self.raw = raw
        self.volume_index = volume_index
        self.dicom = dicom
        self.allow_outside_data = run_files().allow_outside_data
        self._array = array

    @property
    def array(self):
        """The input's samples, sliceable ``[z, y, x]`` (opened on first use)."""
        if self._array is None:
            from ..runscope import run_scope

            with run_scope() as files:  # (this thread's own: the permission it was given)
                files.allow_outside_data = self.allow_outside_data
                # (reopened by path, in a worker: a compressed input is read whole, as the
                # command chose, never copied again, and kept beyond this scope)
                _, self._array = open_volume_header(self.path, raw=self.raw,
                                                    volume_index=self.volume_index,
                                                    dicom=self.dicom, inflate=False)
        return self._array

    @property
    def shape(self):
        """The input's shape (z, y, x)."""
        return tuple(self.array.shape)

    @property
    def dtype(self) -> np.dtype:
        """The input's sample type."""
        return np.dtype(self.array.dtype)

    def __getitem__(self, key):
        return self.array[key]

    def __getstate__(self):
        # an array that carries all it reads (a DICOM stack's frames) goes along: reopening
        # by path would scan the folder's headers again in every process
        keep = self._array if getattr(self._array, "portable", False) else None
        return {"path": self.path, "raw": self.raw, "volume_index": self.volume_index,
                "dicom": self.dicom, "allow_outside_data": self.allow_outside_data,
                "_array": keep}

    def __setstate__(self, state):
        self.__dict__.update(state)
        if self._array is not None and not _reachable(self._array):
            # (a worker on another machine: the command's scratch copy is not here; the
            # input is reopened by path, as a worker without a copy does)
            self._array = None


def _reachable(array) -> bool:
    """Whether a portable array's file is seen by this process (True: no file to see)."""
    check = getattr(array, "reachable", None)
    return True if check is None else bool(check())
