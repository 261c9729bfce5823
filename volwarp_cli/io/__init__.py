"""Volume files: the format is chosen by extension and checked by content.

``read_volume`` and ``write_volume`` are the only entry points the rest of
volwarp uses; each format module converts its file's layout to the
``[z, y, x]`` array and (x, y, z) geometry of :class:`~volwarp_cli.volume.Volume`.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..errors import BadUsage, FormatError, VolwarpError
from ..runscope import stop_if_dry_run
from ..volume import Volume
from .atomic import atomic_output, check_output_path
from .common import SUPPORTED_DTYPES, cast_samples, note_input

if TYPE_CHECKING:
    from .raw import RawLayout

__all__ = ["read_volume", "write_volume", "volume_format", "RawLayout", "atomic_output",
           "check_output_path", "SUPPORTED_DTYPES", "VOLUME_EXTENSIONS", "FOLDER_FORMATS"]


def __getattr__(name: str):
    """``RawLayout``, from :mod:`.raw` when asked for.

    A raw input's options only: most commands never load that module, nor
    make its dataclass (1 ms of every start).
    """
    if name == "RawLayout":
        from .raw import RawLayout

        return RawLayout
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


#: extension -> format name
VOLUME_EXTENSIONS = {
    ".nrrd": "nrrd", ".nhdr": "nrrd",
    ".mha": "metaimage", ".mhd": "metaimage",
    ".tif": "tiff", ".tiff": "tiff",
    ".raw": "raw", ".bin": "raw",
    ".nii": "nifti", ".nii.gz": "nifti",
    ".dcm": "dicom",
    ".zarr": "omezarr",  # also .ome.zarr; a store is a folder
}
#: the formats whose files are folders
FOLDER_FORMATS = frozenset({"omezarr"})
#: the formats volwarp reads but does not write
READ_ONLY_FORMATS = frozenset({"dicom"})

_MAGIC_CHECK = {
    "nrrd": lambda head: head.startswith(b"NRRD000"),
    "tiff": lambda head: head[:4] in (b"II*\0", b"MM\0*", b"II+\0", b"MM\0+"),
    "nifti": lambda head: head[:2] == b"\x1f\x8b" or head[344:348] in (b"n+1\0", b"n+2\0")
    or head[4:8] in (b"n+2\0",),
    "metaimage": lambda head: _metaimage_head(head),
}
_FORMAT_NAMES = {"nrrd": "NRRD", "tiff": "TIFF", "nifti": "NIfTI", "raw": "raw",
                 "metaimage": "MetaImage", "dicom": "DICOM", "omezarr": "OME-Zarr"}


def volume_format(path: str | os.PathLike, *, reading: bool = False) -> str:
    """The format name for ``path`` by its extension, or raise listing the known ones.

    ``reading``: DICOM is also recognised without an extension (scanners name
    files ``IM000001``, folders of them, ``DICOMDIR``), by content.
    """
    name = Path(path).name.lower()
    if name.endswith(".zarr"):
        return "omezarr"  # a folder (OME-Zarr store), read or written
    if reading and Path(path).is_dir():
        # (a Zarr group without the suffix: NGFF keeps a segmentation at
        # image.ome.zarr/labels/<name>, which was searched for DICOM files)
        if zarr_metadata_files(path):
            return "omezarr"
        return "dicom"  # read_volume says so when it holds none
    if name.endswith(".nii.gz"):
        return "nifti"
    fmt = VOLUME_EXTENSIONS.get(Path(name).suffix)
    if fmt is None and reading and _is_dicom(Path(path)):
        return "dicom"
    if fmt is None and name.endswith(".vwc"):  # (a capture file: not a volume)
        raise BadUsage(f"{path}: a capture file (.vwc) is read by `volwarp warp` and "
                       "`volwarp info` only; give the volume it was captured from"
                       if reading else f"{path}: a capture file (.vwc) is written by "
                       "`volwarp capture` only; write a volume (.nrrd, .nii.gz, ...)")
    if fmt is None:
        known = " ".join(sorted(e for e, f in VOLUME_EXTENSIONS.items()
                                if reading or f not in READ_ONLY_FORMATS))
        raise VolwarpError(f"{path}: unknown volume extension (known: {known}; "
                           "DICOM files, folders and DICOMDIRs are read by content)")
    if fmt in READ_ONLY_FORMATS and not reading:
        raise VolwarpError(f"{path}: volwarp reads {_FORMAT_NAMES[fmt]} but does not write it "
                           "(write .nrrd, .nii.gz or .mha)")
    return fmt


def zarr_metadata_files(folder) -> list[str]:
    """The Zarr group metadata files ``folder`` holds (``zarr.json``, ``.zgroup``, ``.zattrs``)."""
    return [n for n in ("zarr.json", ".zgroup", ".zattrs") if (Path(folder) / n).is_file()]


def stray_zarr_metadata(folder) -> str | None:
    """``".zattrs"`` (or the files, joined by "and") where a folder of DICOM files holds Zarr metadata.

    Such a folder is read as a Zarr store (:func:`volume_format`): the
    refusals that follow name the stray files. None for any other folder.
    """
    from .dicom import is_dicom_path

    found = zarr_metadata_files(folder) if Path(folder).is_dir() else []
    return " and ".join(found) if found and is_dicom_path(folder) else None


def check_read_options(path, raw=None, dicom=None) -> None:
    """A :class:`BadUsage` for ``--raw-*`` or DICOM options given for an input of another format.

    A DICOM series folder holding a stray ``.zattrs``/``zarr.json`` is read as
    a Zarr store: DICOM options for it are refused naming the stray file (they
    were refused as for any other format, "is not one", though it holds DICOM).
    """
    if raw is not None and not str(path).lower().endswith((".raw", ".bin")):
        raise BadUsage(f"--raw-* options describe headerless .raw/.bin inputs, not {path}")
    if dicom is None:
        return
    fmt = volume_format(path, reading=True)
    if fmt == "dicom":
        return
    given = " ".join(f"--{k.replace('_', '-')}" for k in sorted(dicom))
    why = f"{given} applies to DICOM inputs, and {path} is not one"
    stray = stray_zarr_metadata(path) if fmt == "omezarr" else None
    if stray:
        why = (f"{given} applies to DICOM inputs, and {path} is read as a Zarr store: it "
               f"holds Zarr metadata ({stray}) beside its DICOM files; a DICOM series? move "
               f"{stray} out of it")
    raise BadUsage(why)


def _metaimage_head(head: bytes) -> bool:
    from .metaimage import looks_like_metaimage

    return looks_like_metaimage(head)


def _is_dicom(path: Path) -> bool:
    from .dicom import is_dicom_path

    return path.exists() and is_dicom_path(path)


def _check_content(path: Path, fmt: str) -> None:
    if not path.exists():
        raise FormatError(f"{path}: no such file")
    if path.is_dir():
        raise FormatError(f"{path}: is a folder, not a volume file")
    check = _MAGIC_CHECK.get(fmt)
    if check is None:
        return
    try:
        with open(path, "rb") as fh:
            head = fh.read(352)
    except OSError as exc:
        raise FormatError(f"{path}: cannot open ({exc.strerror})") from None
    if not check(head) and head[:2] == b"\x1f\x8b":  # (said as such, not as its bytes)
        raise FormatError(f"{path}: is gzip-compressed as a whole, not a {_FORMAT_NAMES[fmt]} "
                          "file: gunzip it (volwarp's --compress compresses inside the file)")
    if not check(head):
        raise FormatError(f"{path}: content is not {_FORMAT_NAMES[fmt]} "
                          f"(file starts with {head[:8]!r})")


def read_volume(path: str | os.PathLike, *, raw: RawLayout | None = None,
                volume_index: int | None = None, mmap: bool = False,
                dicom: dict | None = None) -> Volume:
    """Read a volume file; ``raw`` describes headerless ``.raw``/``.bin`` files.

    ``volume_index`` selects one volume of a 4-D NIfTI or MetaImage file,
    one component of a multi-component (4-D) NRRD file or of a vector NIfTI
    field (x, y, z, 1, C), or one image of a TIFF holding several (OME-TIFF
    images, tifffile series). ``mmap``: where the
    samples lie raw in the machine's byte order in an attached NRRD, map them
    read-only instead of copying (a command that only reads its input).
    ``dicom``: keyword arguments of :func:`~volwarp_cli.io.dicom.read_dicom`
    (series, irregular, duplicates, keep_shear, keep_phi); used for a DICOM
    input only (the command line refuses them for others).
    """
    from .inputs import refuse_stream_input

    stop_if_dry_run(path)  # (volwarp batch's checks of a step end here)
    path = Path(path)
    refuse_stream_input(path)  # (opened twice, a pipe waited forever)
    if volume_format(path, reading=True) == "omezarr":  # a folder: the reader checks it
        from .omezarr import read_omezarr
        return read_omezarr(path, volume_index)
    if path.is_dir():  # a folder is DICOM or nothing
        if not _is_dicom(path):
            raise FormatError(f"{path}: is a folder with no DICOM files, not a volume file")
        fmt = "dicom"
    else:
        fmt = volume_format(path, reading=True)
        _check_content(path, fmt)
    if volume_index is not None and fmt in ("raw", "dicom"):
        raise BadUsage(f"{path}: --volume-index selects a volume of a 4-D NIfTI or "
                       "MetaImage, a component of a 4-D NRRD or an image of a TIFF; a "
                       f"{_FORMAT_NAMES[fmt]} input has one")
    if fmt == "dicom":
        from .dicom import read_dicom
        vol = read_dicom(path, **(dicom or {}))
    elif fmt == "metaimage":
        from .metaimage import read_metaimage
        vol = read_metaimage(path, volume_index)
    elif fmt == "nrrd":
        from .nrrd import read_nrrd
        vol = read_nrrd(path, volume_index, mmap=mmap)
    elif fmt == "tiff":
        from .tiff import read_tiff
        vol = read_tiff(path, volume_index)
    elif fmt == "nifti":
        from .nifti import read_nifti
        vol = read_nifti(path, volume_index)
    else:
        from .raw import read_raw
        vol = read_raw(path, raw)
    if path.is_file():
        note_input(path)  # (data files of detached headers: noted as they are opened)
    return vol


def read_components(path: str | os.PathLike) -> tuple[Volume, np.ndarray]:
    """Every component per voxel of a NRRD or MetaImage file, read once: a vector image.

    ``(Volume, samples)``: the first component's Volume (geometry, key/values)
    and the samples (z, y, x, n), n = 1 for a plain volume. (``read_volume``
    reads one component a call: a field's three would read the file three
    times.)
    """
    from .inputs import refuse_stream_input

    stop_if_dry_run(path)
    path = Path(path)
    refuse_stream_input(path)
    fmt = volume_format(path, reading=True)
    _check_content(path, fmt)
    if fmt == "nrrd":
        from .nrrd import read_nrrd_components as read
    elif fmt == "metaimage":
        from .metaimage import read_metaimage_components as read
    else:
        raise FormatError(f"{path}: a {_FORMAT_NAMES[fmt]} file is not read as a vector "
                          "image (NRRD or MetaImage)")
    vol, samples = read(path)
    note_input(path)
    return vol, samples


def check_byte_order(path, fmt: str, byte_order: str, option: str | None = None) -> None:
    """Refuse a byte order ``path``'s format is not written in (NIfTI: little-endian only).

    ``option``: the option that names ``path``, for the message (an export's).
    """
    if fmt == "nifti" and byte_order != "little":
        where = f"{option} {path}" if option else str(path)
        raise BadUsage(f"{where}: volwarp writes NIfTI little-endian only (--byte-order)")


def say_unused_writer_options(path, fmt: str, compress: bool, ome_zarr_version: str) -> None:
    """Say (once a run) a writer option that ``path``'s format has nothing to do with.

    Not refused: a command's options go to all its outputs (``-o x.nrrd
    --compress --jacobian-to j.nii``), and apply where they can. In memory
    (:func:`write_volume`) as by blocks (:func:`.blockwrite.open_volume_blocks`).
    """
    unused = []
    name = Path(path).name.lower()
    if compress and (fmt == "raw" or (fmt == "nifti" and not name.endswith(".gz"))):
        unused.append(("--compress", "a .nii or raw file is never compressed (.nii.gz is "
                                     "gzip NIfTI)"))
    if ome_zarr_version != "0.5" and fmt != "omezarr":
        unused.append(("--ome-zarr-version", "it is for OME-Zarr outputs (.ome.zarr)"))
    if not unused:
        return
    from ..progress import log
    from ..runscope import run_files

    said = run_files().said
    for option, why in unused:
        if ("unused writer option", option, fmt) not in said:
            said.add(("unused writer option", option, fmt))
            log.warning("warning: %s does not apply to %s: %s", option, path, why)


def write_volume(vol: Volume, path: str | os.PathLike, *, dtype=None, compress: bool = False,
                 byte_order: str = "little", ome_zarr_version: str = "0.5", pyramid: int = 0,
                 labels="auto") -> None:
    """Write ``vol`` atomically, converting samples to ``dtype`` when given.

    Integer outputs from float samples are rounded and clipped to the type's
    range; NaN is refused for integer types.

    OME-Zarr outputs (``.ome.zarr``, ``.zarr``: folders) take
    ``ome_zarr_version`` (``"0.5"``: Zarr v3, sharded; ``"0.4"``: Zarr v2),
    ``pyramid`` (extra half-size levels) and ``labels`` (True, False or
    ``"auto"``: whether levels take the most frequent label rather than the
    mean); their chunks are always zstd-compressed (``compress`` changes
    nothing). Other formats have one level: ``pyramid`` must be 0.
    """
    path = Path(path)
    fmt = volume_format(path)
    check_output_path(path)
    if pyramid and fmt != "omezarr":
        raise BadUsage(f"{path}: --pyramid writes extra levels of OME-Zarr outputs "
                       "(.ome.zarr); a " + _FORMAT_NAMES[fmt] + " file has one")
    check_byte_order(path, fmt, byte_order)
    say_unused_writer_options(path, fmt, compress, ome_zarr_version)
    cast = None  # (a type the writer casts to by slabs as it writes)
    if dtype is not None and np.dtype(dtype) != vol.data.dtype:
        if _cast_by_slabs(path, fmt, compress) and np.issubdtype(vol.data.dtype, np.number):
            cast = np.dtype(dtype)
        else:
            vol = vol.with_data(cast_samples(vol.data, dtype, what=str(path)))
    if not np.issubdtype(vol.data.dtype, np.number):
        raise VolwarpError(f"{path}: cannot write samples of type {vol.data.dtype}")
    if fmt == "omezarr":
        from .omezarr import write_omezarr
        write_omezarr(vol, path, version=ome_zarr_version, pyramid=pyramid, labels=labels,
                      byte_order=byte_order)
    elif fmt == "nrrd":
        from .nrrd import write_nrrd
        write_nrrd(vol, path, compress=compress, byte_order=byte_order, dtype=cast)
    elif fmt == "tiff":
        from .tiff import write_tiff
        write_tiff(vol, path, compress=compress, byte_order=byte_order)
    elif fmt == "metaimage":
        from .metaimage import write_metaimage
        write_metaimage(vol, path, compress=compress, byte_order=byte_order, dtype=cast)
    elif fmt == "nifti":
        from .nifti import write_nifti
        write_nifti(vol, path, dtype=cast)
    else:
        from .raw import write_raw
        write_raw(vol, path, byte_order=byte_order, dtype=cast)


def load_writer(path: str | os.PathLike, compress: bool = False) -> None:
    """Load what :func:`write_volume` needs to write ``path``, without writing anything.

    The format's writer and a compressed output's compressor (ISA-L's
    deflate for gzip, tifffile's zlib, zarr and its codecs): 1-20 MiB that a
    check against a tight memory limit must find already held
    (:func:`volwarp_cli.memory.ensure_fits_once_loaded`).
    """
    import importlib

    path = Path(path)
    fmt = volume_format(path)
    importlib.import_module(f"{__name__}.{fmt}")
    if fmt == "omezarr":
        import numcodecs  # noqa: F401  (the 0.4 stores' codec)
        import zarr.codecs  # noqa: F401
    elif fmt == "tiff":
        import tifffile  # noqa: F401
    if compressed_output(path, fmt, compress) and fmt in ("nifti", "nrrd"):
        from . import deflate  # noqa: F401  (ISA-L)


def compressed_output(path, fmt: str, compress: bool = False) -> bool:
    """Whether the output ``path`` of format ``fmt`` holds its samples compressed.

    OME-Zarr (its chunks always zstd), ``.nii.gz``, and with ``--compress``
    every format but raw: in memory (:func:`write_volume`) as by blocks.
    """
    if fmt == "nifti":
        return Path(path).name.lower().endswith(".gz")
    return fmt == "omezarr" or (bool(compress) and fmt != "raw")


def _cast_by_slabs(path: Path, fmt: str, compress: bool) -> bool:
    """Whether ``path``'s writer casts the samples slab by slab as it writes them.

    Uncompressed NRRD, MetaImage, NIfTI and raw files: the samples go to the
    file as they lie, so a slab's cast is the whole's bytes for its part.
    """
    return fmt in ("nrrd", "metaimage", "nifti", "raw") and not compressed_output(path, fmt, compress)


def _cast_bytes(count: int, src: np.dtype, out: np.dtype, swapped: bool) -> int:
    """The bytes casting ``count`` samples from ``src`` to ``out`` and swapping them holds."""
    held = 0
    if out != src:
        held += count * out.itemsize
        if out.kind in "iu" and src.kind == "f":
            held += count * src.itemsize  # (np.rint's floats, beside the cast)
        elif out.kind in "iu" and src.kind in "iu" and not (
                np.iinfo(out).min <= np.iinfo(src).min and np.iinfo(src).max <= np.iinfo(out).max):
            held += count * src.itemsize  # (the clip's copy, beside the cast)
    if swapped:
        held += count * out.itemsize
    return held


def write_memory(path: str | os.PathLike, shape, src_dtype, *, dtype=None,
                 compress: bool = False, byte_order: str = "little",
                 ome_zarr_version: str = "0.5", pyramid: int = 0, labels="auto") -> int:
    """The bytes :func:`write_volume` holds beyond the samples' own array, at its peak.

    For a check before the write (``volwarp convert``: what the read left
    must hold it). ``shape``: the samples' (z, y, x); ``src_dtype``: theirs.
    Uncompressed NRRD, MetaImage, NIfTI and raw files cast and order their
    samples a slab at a time (:data:`~.common.SLAB_BYTES`); other outputs
    hold the whole's cast (and the rounded floats of a float-to-integer
    cast beside it), the whole in the file's byte order where it is not the
    machine's, and the compressed bytes where they are made whole first
    (a zlib MetaImage, whose header gives their size; TIFF's and gzip's
    streams go to the file as they are made: a few blocks). As many bytes
    compressed as uncompressed, the worst case. And :data:`WRITER_BYTES` for
    the writer's own objects and buffers. OME-Zarr outputs
    (``ome_zarr_version``, ``pyramid``, ``labels``: :func:`write_volume`'s):
    the store's write (:func:`.omezarr.memory_bytes`; zarr puts each chunk
    in the file's byte order as it encodes it), and a cast, made whole first
    and held while the store is written: the larger of the cast and its
    result beside the store's write.
    """
    path = Path(path)
    fmt = volume_format(path)
    if fmt == "omezarr":
        return _cast_beside_store(shape, src_dtype, dtype, ome_zarr_version, pyramid, labels)
    return WRITER_BYTES + _copies_bytes(path, fmt, shape, src_dtype, dtype, compress, byte_order)


def _cast_beside_store(shape, src_dtype, dtype, version: str, pyramid: int, labels) -> int:
    """:func:`write_memory` of an OME-Zarr output: the store's write, and a cast held beside it.

    The store's own write (:func:`.omezarr.memory_bytes`) is checked again by
    :func:`.omezarr.write_omezarr` once zarr is loaded; counted here too, a
    write that cannot fit is refused before zarr's 17 MiB are loaded.
    """
    import math

    from .omezarr import memory_bytes

    src = np.dtype(src_dtype)
    out = src if dtype is None else np.dtype(dtype)
    store = memory_bytes(shape, out, version, pyramid, labels)
    if out == src:
        return store
    count = math.prod(int(n) for n in shape)
    return max(_cast_bytes(count, src, out, False), count * out.itemsize + store)


#: what a writer holds beyond its copies of the samples: its header, its calls' objects,
#: and the code it runs first (numpy's and the writer's pages, resident once touched):
#: measured 1.3-1.6 MiB on a quiet machine, 2.0 under a full test suite (96^3 and 256^3
#: float32 to .nii, .nii.gz, .nii as int16)
WRITER_BYTES = 3 << 20


def _copies_bytes(path: Path, fmt: str, shape, src_dtype, dtype, compress: bool,
                  byte_order: str) -> int:
    """:func:`write_memory`'s copies of the samples (a cast, a swap, a compressed stream)."""
    import math
    import sys

    from .common import SLAB_BYTES

    src = np.dtype(src_dtype)
    out = src if dtype is None else np.dtype(dtype)
    count = math.prod(int(n) for n in shape)
    size = count * out.itemsize
    if fmt == "nifti":
        byte_order = sys.byteorder
    swapped = byte_order != sys.byteorder and out.itemsize > 1
    if _cast_by_slabs(path, fmt, compress):  # (a slab's cast and swap at a time)
        if out == src and not swapped:
            return 0
        plane = count // max(1, int(shape[0])) if count else 0
        widest = max(out.itemsize, src.itemsize)
        planes = min(int(shape[0]), max(1, SLAB_BYTES // max(1, plane * widest)))
        return _cast_bytes(planes * plane, src, out, swapped)
    held = _cast_bytes(count, src, out, swapped)
    if fmt == "metaimage" and compress:
        held += size + size // 64 + (1 << 20)  # (zlib's worst case: stored blocks)
    elif fmt == "tiff":
        held += min(size, 3 * SLAB_BYTES)
    else:  # (gzip: under 8 MiB made whole, its parts joined, and the stream grown to its
        # size: 2.8 times the samples' measured; else blocks on four threads)
        from .deflate import BLOCKS_FROM

        held += 3 * size + (1 << 16) if size < BLOCKS_FROM else 16 << 20
    return held
