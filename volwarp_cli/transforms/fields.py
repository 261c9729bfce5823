"""Displacement-field images: a vector of three LPS millimetres per voxel, ``p -> p + u(p)``.

As ITK, SimpleITK and ANTs write them (``1Warp.nii.gz``,
``1InverseWarp.nii.gz``, ``sitk.WriteImage`` of a field) and as volwarp's
own ``warp --displacement-to`` does:

- NIfTI: a 5-D (x, y, z, 1, 3) image, intent 1007 (vector). The header's
  geometry is RAS (read to LPS as every NIfTI), but the *vectors* are LPS:
  ITK writes its components as they are. Read in one pass (a ``.nii.gz``
  decompressed once), kept in the file's type (float32 stays float32); a
  float field larger than its share of the memory budget
  (:func:`~volwarp_cli.memory.read_by_box`) is read by windows instead
  (:class:`LazyField`: a block reads the vectors its points reach), from
  the file, or from a scratch copy of a ``.nii.gz``'s samples
  (:mod:`volwarp_cli.io.inflated`).
- NRRD (``kinds: vector domain domain domain``) and MetaImage with three
  components: the vectors are in the file's ``space`` (a RAS file's are
  turned to LPS). Larger than their share of the budget, float vectors
  interleaved (a NRRD's first axis, MetaImage's channels) or in planes (a
  NRRD's last axis) are read by windows too (a compressed file's from a
  scratch copy).

volwarp's ``--forward-field-to`` (``volwarp_field: forward``) moves points of
the input, not the output grid's: refused here, with the field to use.
"""

from __future__ import annotations

import math
import os
import threading

import numpy as np

from ..errors import OutOfMemoryError, VolwarpError
from .model import DisplacementField, GridFrame


def read_field(path: str, fmt: str) -> DisplacementField:
    """The displacement field image at ``path`` (``fmt``: nifti, nrrd or metaimage)."""
    from ..runscope import stop_if_dry_run

    stop_if_dry_run(path)  # (a field is a volume's worth of reading: batch's checks end here)
    if fmt == "nifti":
        frame, vectors, meta = _nifti(path)
    else:
        frame, vectors, meta = _components(path)
    if meta.get("volwarp_field") == "forward":
        raise VolwarpError(f"{path}: volwarp's forward field (x -> F(x) - x) moves the "
                           "input's points, it does not resample; apply the warp's "
                           "--displacement-to field instead")
    name = f"{path} (displacement field)"
    nifti = fmt == "nifti"
    if isinstance(vectors, LazyField):
        return DisplacementField(frame, None, name, source=vectors, nifti=nifti)
    return DisplacementField(frame, vectors, name, nifti=nifti)


def _frame(vol_geometry: dict, shape_zyx) -> GridFrame:
    nz, ny, nx = (int(n) for n in shape_zyx)
    return GridFrame((nx, ny, nz), np.asarray(vol_geometry["origin"], float),
                     np.asarray(vol_geometry["spacing"], float),
                     np.asarray(vol_geometry["direction"], float))


#: held while a field is read whole on a worker that cannot see its scratch copy (rare)
_WHOLE_READ = threading.Lock()


class LazyField:
    """A field's vectors read by windows from its file (or a compressed file's scratch copy).

    ``samples``: the file's samples as a 3-D :class:`~volwarp_cli.io.filearray.FileArray`
    read by pread: the three components in planes, one volume after the other
    (``planar``: NIfTI's, a NRRD's last axis; shape (3 z, y, x)), or
    interleaved (a NRRD's first axis, MetaImage's channels; shape (z, y, 3 x)).
    ``signs``: the file frame's vectors to LPS (None: they are LPS).
    Picklable (file paths and offsets): a worker process reads its own
    windows. ``read(lo, hi)``: the (z, y, x, 3) vectors of the box ``[lo,
    hi)`` (z, y, x), interleaved.

    ``field``: the field's own file, a NIfTI or not (``nifti``); ``samples``
    may be a compressed file's scratch copy. A worker that does not see that
    copy (on another machine: :meth:`.io.inflated.InflatedArray.reachable`)
    reads the field whole from ``field`` instead (once, whichever of its
    threads asks first), as a worker reopening a compressed input does: that
    worker then holds the whole field, beyond the block's own budget.
    """

    def __init__(self, samples, shape_zyx, *, planar: bool, signs=None, field: str,
                 nifti: bool):
        nz, ny, nx = shape_zyx
        self.samples, self.planar, self.signs = samples, planar, signs
        self.field, self.nifti = os.path.abspath(field), nifti
        self.shape = (nz, ny, nx, 3)
        self.dtype = np.dtype(samples.dtype).newbyteorder("=")
        self._whole = None

    def __getstate__(self):
        return {**self.__dict__, "_whole": None}

    def __setstate__(self, state):
        self.__dict__.update(state)
        check = getattr(self.samples, "reachable", None)
        if check is not None and not check():  # (a remote worker: no scratch copy here)
            self.samples = None

    @property
    def path(self) -> str:
        """The file the vectors are read from."""
        return self.field if self.samples is None else self.samples.path

    def read(self, lo, hi) -> np.ndarray:
        """The vectors of box ``[lo, hi)`` (z, y, x)."""
        (z0, y0, x0), (z1, y1, x1) = lo, hi
        if self.samples is None:
            return self._read_whole()[z0:z1, y0:y1, x0:x1]
        if self.planar:
            nz = self.shape[0]
            out = np.empty((z1 - z0, y1 - y0, x1 - x0, 3), self.dtype)
            for c in range(3):
                out[..., c] = self.samples[c * nz + z0:c * nz + z1, y0:y1, x0:x1]
        else:
            out = self.samples[z0:z1, y0:y1, 3 * x0:3 * x1].reshape(z1 - z0, y1 - y0,
                                                                     x1 - x0, 3)
        return out if self.signs is None else to_lps(out, self.signs)

    def _read_whole(self) -> np.ndarray:
        """The field's vectors read whole from its own file, once (the block tasks' threads wait)."""
        with _WHOLE_READ:
            if self._whole is None:
                whole = read_whole(self.field, self.nifti)
                if whole.shape != self.shape:
                    raise VolwarpError(f"{self.field}: changed while it was read (now "
                                       f"{whole.shape[:3]} vectors, not {self.shape[:3]})")
                self._whole = whole
        return self._whole

    def tile_range(self, tile: int):
        """Per-tile extremes (:func:`.model.tile_range`), read slab by slab of ``tile`` planes."""
        from .model import tile_range

        nz, ny, nx, _ = self.shape
        parts = [tile_range(self.read((z, 0, 0), (min(z + tile, nz), ny, nx)), tile)
                 for z in range(0, nz, tile)]
        return (np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts]))


def to_lps(vectors: np.ndarray, signs) -> np.ndarray:
    """Vectors of a file frame to LPS: by its axes' signs, or by a 3x3 matrix.

    Signs are exact (a NaN stays in its component); the matrix's columns are
    the file's component axes in LPS (a NRRD's measurement frame).
    """
    signs = np.asarray(signs, dtype=vectors.dtype)
    return vectors * signs if signs.ndim == 1 else vectors @ signs.T


def frame_signs(path: str, file_space) -> np.ndarray | None:
    """What takes a field file's vector components to LPS mm (:func:`to_lps`); None: nothing.

    A NRRD's :func:`~volwarp_cli.io.nrrd.vector_frame` (its ``space``,
    ``measurement frame`` and length units); else the signs of the file's
    frame. Per-component factors (signs, a unit) where the matrix is
    diagonal: exact, a NaN stays in its component.
    """
    from ..io import volume_format
    from ..volume import frame_to_lps

    if volume_format(path, reading=True) == "nrrd":
        from ..io.nrrd import vector_frame

        matrix = vector_frame(path)
    else:
        matrix = frame_to_lps(file_space)
    if matrix is None or np.array_equal(matrix, np.eye(3)):
        return None
    if np.array_equal(matrix, np.diag(np.diag(matrix))):
        return np.diag(matrix).copy()
    return matrix


def read_whole(path: str, nifti: bool) -> np.ndarray:
    """The vectors (z, y, x, 3, LPS) of the field at ``path``, read whole (never by windows)."""
    return (_nifti if nifti else _components)(path, whole=True)[1]


def _nifti(path: str, whole: bool = False):
    from ..io.inflated import NoRoom, naming_no_room
    from ..io.nifti import gunzip_range_into, nifti_geometry, nifti_meta, open_nifti
    from ..memory import ensure_fits_in_memory, read_by_box
    from ..runscope import in_run

    nf = open_nifti(path)
    if nf.components != 3 or nf.volumes != 1:
        raise VolwarpError(f"{path}: a NIfTI of shape {nf.shape} is not a displacement field "
                           "(a 5-D x, y, z, 1, 3 vector image)")
    geometry, chosen = nifti_geometry(nf.header, nf.where)
    meta = nifti_meta(nf, chosen, 0)
    nx, ny, nz = nf.shape[:3]
    kind = nf.file_dtype
    no_room = None
    if not whole and not nf.scaled and kind.kind == "f" and read_by_box(nf.data_bytes) and (
            not nf.gzipped or in_run()):  # (a copy to scratch: inside a command's run only)
        try:
            return _frame(geometry, (nz, ny, nx)), _lazy_field(nf, (nz, ny, nx)), meta
        except NoRoom as why:
            no_room = str(why)
    out_type = np.dtype(np.float32 if nf.scaled or kind.kind != "f" else kind.newbyteorder("="))
    # (the vectors as held: an int16 field's float32 vectors are twice its file's samples)
    with naming_no_room(no_room):
        ensure_fits_in_memory(nx * ny * nz * 3 * out_type.itemsize,
                              f"{path} ({'x'.join(map(str, nf.shape))})")
    # interleaved (z, y, x, 3): a point's neighbours' vectors share cache lines (the planar
    # layout of the file was 1.5x slower to sample)
    vectors = np.empty((nz, ny, nx, 3), dtype=out_type)
    if nf.gzipped:  # each decompressed piece into place: no copy of the file's planes held
        gunzip_range_into(nf.path, nf.offset, nf.data_bytes, nf.offset + nf.data_bytes,
                          nf.where, f"{'x'.join(map(str, nf.shape))} samples",
                          _ComponentSink(vectors, kind, nf), beside=True)
    else:  # slab by slab into place: no second copy of the field held
        plane = ny * nx * kind.itemsize
        step = max(1, (64 << 20) // (3 * plane))
        with open(path, "rb") as fh:
            for z0 in range(0, nz, step):
                z1 = min(nz, z0 + step)
                parts = []
                for c in range(3):
                    fh.seek(nf.offset + (c * nz + z0) * plane)
                    buf = fh.read((z1 - z0) * plane)
                    if len(buf) != (z1 - z0) * plane:
                        raise VolwarpError(f"{path}: cannot read NIfTI data (truncated)")
                    parts.append(np.frombuffer(buf, dtype=kind).reshape(z1 - z0, ny, nx))
                _interleave(parts, vectors[z0:z1], nf)
    return _frame(geometry, (nz, ny, nx)), vectors, meta


def _lazy_field(nf, shape_zyx):
    """The field's vectors read by windows: from the file, or a ``.nii.gz``'s scratch copy.

    Raises :class:`~volwarp_cli.io.inflated.NoRoom` where a ``.nii.gz``'s
    samples find no room on the disk (then read whole, or refused by the
    memory check with its sizes and the disk's).
    """
    from ..io.common import note_input
    from ..io.filearray import FileArray
    from ..io.inflated import inflated_array
    from ..io.mapped import watch
    from ..io.nifti import gunzip_range_into

    if not nf.gzipped:
        note_input(nf.path)
        watch(nf.path)  # (an output is not renamed into place if it changed meanwhile)
        return LazyField(FileArray(nf.path, nf.file_dtype, nf.offset, _planes(shape_zyx)),
                         shape_zyx, planar=True, field=nf.path, nifti=True)

    def fill(sink):
        gunzip_range_into(nf.path, nf.offset, nf.data_bytes, nf.offset + nf.data_bytes,
                          nf.where, nf.layout(), sink)

    copy = inflated_array(nf.path, nf.data_bytes, nf.file_dtype, _planes(shape_zyx), nf.where,
                          fill)
    return LazyField(copy, shape_zyx, planar=True, field=nf.path, nifti=True)


def _planes(shape_zyx) -> tuple:
    """The 3-D shape of three components' volumes one after the other."""
    nz, ny, nx = shape_zyx
    return (3 * nz, ny, nx)


class _ComponentSink:
    """A NIfTI field's inflated planes placed piece by piece into interleaved vectors.

    The planes (x components, then y, then z) go into ``vectors`` (z, y, x, 3),
    scaled as the file says. A sample split between two pieces waits for the rest of its bytes.
    """

    def __init__(self, vectors: np.ndarray, kind: np.dtype, nf):
        self.flat = vectors.reshape(-1, 3)
        self.kind, self.nf = kind, nf
        self.carry = b""
        self.done = 0  # samples placed

    def __call__(self, at: int, piece: memoryview) -> None:
        item = self.kind.itemsize
        data = self.carry + bytes(piece) if self.carry else piece
        whole = len(data) // item * item
        values = np.frombuffer(data[:whole], dtype=self.kind)
        self.carry = bytes(data[whole:])
        n, i = len(self.flat), 0
        while i < len(values):
            c, v = divmod(self.done, n)
            take = min(len(values) - i, n - v)
            self.flat[v:v + take, c] = _scaled(values[i:i + take], self.nf)
            i += take
            self.done += take


def _interleave(planes, out: np.ndarray, nf) -> None:
    """The three component planes (z, y, x) into ``out`` (z, y, x, 3), scaled as the file says.

    One pass of a kernel where the samples are native floats of ``out``'s
    type (numpy's three strided passes over a fresh field took 6x as long:
    each touches every page); else numpy's.
    """
    if not nf.scaled and all(p.dtype == out.dtype and p.dtype.isnative for p in planes):
        from ._applykernels import interleave

        interleave(planes[0], planes[1], planes[2], out)
        return
    for c in range(3):
        out[..., c] = _scaled(planes[c], nf)


def _scaled(samples: np.ndarray, nf) -> np.ndarray:
    """A NIfTI's samples with its scl_slope/scl_inter applied (none: as they are)."""
    if nf.scaled:
        return samples * float(nf.slope) + float(nf.inter)
    return samples


def _components(path: str, whole: bool = False):
    """A NRRD or MetaImage field: by windows where its vectors exceed their share of the budget."""
    from ..io import read_components
    from ..io.inflated import naming_no_room
    from ..io.lazy import NoRoomToInflate, NotLazy, open_vectors_lazy
    from ..memory import read_by_box

    no_room = None
    if not whole:  # (whole: read below, no scratch copy made to be thrown away)
        try:
            header, samples, _, planar = open_vectors_lazy(path, count=3, kinds="f")
            held = samples is not None and math.prod(samples.shape) * header.dtype.itemsize
            if held and read_by_box(held):
                source = LazyField(samples, header.shape, planar=planar,
                                   signs=frame_signs(path, header.file_space), field=path,
                                   nifti=False)
                return _frame(_geometry_of(header), header.shape), source, dict(header.meta)
        except NoRoomToInflate as why:
            no_room = str(why)
        except (NotLazy, OSError):
            pass  # (read whole below, with the reader's own errors)
    try:
        with naming_no_room(no_room):
            first, vectors = read_components(path)
    except OutOfMemoryError:
        raise  # (not "not a displacement field": the field is one, too large)
    except VolwarpError as exc:
        raise VolwarpError(f"{path}: not a displacement field of 3 components per voxel "
                           f"({str(exc).removeprefix(str(path) + ': ')})") from None
    n = vectors.shape[-1]
    if n != 3:
        raise VolwarpError(f"{path}: has {n} component{'s' if n > 1 else ''} per voxel: not "
                           "a displacement field (3 components per voxel)")
    if vectors.dtype.kind != "f":
        vectors = vectors.astype(np.float32)
    signs = frame_signs(path, first.file_space)
    if signs is not None:
        vectors = to_lps(vectors, signs)
    return (_frame(_geometry_of(first), first.data.shape), np.ascontiguousarray(vectors),
            dict(first.meta))


def _geometry_of(placed) -> dict:
    """A Volume's or Header's placement (LPS), as :func:`_frame` takes it."""
    return {"origin": placed.origin, "spacing": placed.spacing, "direction": placed.direction}
