"""OME-Zarr (OME-NGFF 0.5 on Zarr v3 with sharding, or 0.4 on Zarr v2) reading and writing.

A store (``scan.ome.zarr``, ``scan.zarr``) is a folder: a Zarr group whose
``multiscales`` metadata names one array per resolution level (``0`` the
full one), each with axes ``z, y, x`` (``unit: millimeter``) and a ``scale``
then a ``translation`` transformation: the voxel ``[k, j, i]`` lies at
``translation + scale * (k, j, i)`` (array order).

NGFF 0.4/0.5 cannot store a rotation, so volwarp writes

- a volume whose direction is a *signed permutation* (axis flips, axis swaps:
  every scan in RAS, LPS, coronal or sagittal order) reindexed by
  ``np.flip``/``np.transpose`` (exact, no interpolation) so that the stored
  direction is the identity; the origin is the world point of the new first
  voxel. Every sample keeps its world point, and any NGFF reader sees it
  where it lies (in volwarp's world frame, LPS). Reading gives back that
  identity-direction volume, not the source's index order.
- an *oblique* volume reindexed the same way by its *nearest* signed
  permutation (:func:`signed_permutation`), so that its
  index frame is the nearest to the world's, with the scale and the
  translation (the origin) of that frame: readers that know only NGFF get the
  image in that frame (the remaining rotation about the origin is missing). A
  direction a hair off flips (a scanner's tilt of 1e-6 rad, a NIfTI sform's
  float32 noise) was stored as it stood: those readers saw the scan mirrored.
  One with two equally near (exactly 45 degrees) is stored as it is.
  Writing one whose remaining rotation moves a voxel in those readers (more
  than a thousandth of a voxel) warns, naming the angle
  (:func:`warn_if_oblique`): .nrrd and .nii.gz keep the rotation for every
  reader.

Either way the group's namespaced ``volwarp`` attribute keeps origin, spacing
and direction at full precision, the world frame, the volume's key/values
(provenance) and how the pyramid was made. volwarp reads that attribute first
and checks it against the multiscales' scale and translation (and the array's
shape): a store edited by another program so that the two disagree is refused,
naming both.

Choices:

- **Levels.** Reading uses level 0. ``pyramid=N`` writes N more levels, each
  half the previous (sizes rounded up; the last block of an odd axis is
  partial), with scale ``spacing * 2**l`` and translation
  ``origin + spacing * (2**l - 1) / 2`` (half a coarse voxel minus half a fine
  one). Intensities are averaged (in float64, rounded back for integer types);
  label maps take the most frequent label of each 2x2x2 block (the smallest
  of equally frequent labels), so a coarse level holds only labels of level 0.
  ``labels``: True, False, or ``"auto"``: an integer volume that looks like a
  label map (piecewise constant: :func:`volwarp_cli.labelmap.looks_like_labels`, the
  rule :func:`volwarp_cli.labelmap.label_map_hint` says, whatever the number of
  labels: no segmentation is averaged for having many).
- **Label maps.** A label map of integer samples (the same rule, decided
  without levels too) carries NGFF's ``image-label`` (``{"version": ...}``)
  beside ``multiscales``, so that ome-zarr-py and napari take its samples
  for ids: NGFF 0.4 makes any group holding it a segmentation ("unlisted
  groups MAY be labels", ``source`` optional); 0.5 describes label images
  under an image's ``labels/`` group and says nothing of one standing alone
  (ome/ngff#179 asks for it), which NGFF's label schema, ome-zarr-py and
  ome-zarr-models accept. No ``colors`` (one per id of an atlas) and no
  ``source`` (no image above). A float map of ids is not tagged: NGFF's
  label images are integers.
- **Other axes.** Space axes ``z, y, x`` (any order, by name) are required;
  time and channel axes of size 1 are dropped, and one such axis of larger
  size is selected with ``volume_index`` (``--volume-index``), as a 4-D NIfTI.
- **Units.** Space units are converted to millimetres (micrometer, nanometer,
  angstrom, centimeter, meter, ...); an axis without a unit is taken as
  millimetres; an unknown unit is an error.
- **Completeness.** volwarp writes every chunk (also those of fill value), so
  a chunk missing from a volwarp store is damage and is refused; in stores of
  other writers a missing chunk is the fill value, as Zarr defines. Chunks are
  zstd frames with their content checksum, in NGFF 0.5 and 0.4 alike (and
  shard indexes carry CRC32C), so a truncated or altered chunk is an error,
  not wrong samples, in every reader. (In 0.4 the ``.zarray`` says
  ``{"id": "zstd", "level": 3}``: a ``checksum`` key there is refused by
  some readers, and the frames carry the flag anyway:
  :func:`_plain_zstd_metadata`.) Stores of other writers are read whatever
  their codecs (numcodecs' default zstd, blosc: an altered byte there may go
  unnoticed); a volwarp store whose chunks have no checksums (NGFF 0.4
  written by an older volwarp) is read with a warning (:func:`_check_chunks`).
- **Determinism.** No timestamps or host names; chunks and JSON are the same
  bytes for the same volume.

The zarr imports stay inside this module (imported lazily by the dispatch).
"""

from __future__ import annotations

import itertools
import json
import math
import os
from pathlib import Path

import numpy as np

from ..errors import BadUsage, ChoiceNeeded, FormatError, VolwarpError
from ..geometry import check_placement
from ..labelmap import looks_like_labels
from ..progress import log
from ..samples import check_dtype
from ..volume import Header, Volume, xyz_to_zyx, zyx_to_xyz
from .common import make_volume, native
from .units import NGFF_UNIT_TO_MM

#: NGFF versions volwarp writes (and reads)
VERSIONS = ("0.4", "0.5")
#: chunk edge (voxels) inside shards, and shard edge, before clipping to the shape
CHUNK = 64
SHARD = 256
#: the zstd level of the chunks
ZSTD_LEVEL = 3
#: version of volwarp's own attribute
ATTRIBUTE_VERSION = 1

#: a reindexed direction this close to the identity is the identity (a signed permutation)
_IDENTITY_TOLERANCE = 1e-12

# -- geometry ---------------------------------------------------------------------------

def signed_permutation(direction) -> tuple[list[int], list[float]] | None:
    """``(perm, signs)``: the signed permutation nearest ``direction``, or None.

    Index axis ``a`` (x, y, z) runs along world axis ``perm[a]``, with sign
    ``signs[a]`` (``direction[perm[a], a]``'s), for the axis order whose
    entries are largest (sum of ``|direction[perm[a], a]|``: the nearest in the
    Frobenius norm). Not each axis' own largest entry: two index axes may run
    most along one world axis (a double oblique of 40 degrees about x and y),
    and such a grid was stored as it stood (a left-handed one mirrored in
    other readers). None where two axis orders are equally near.
    """
    d = np.asarray(direction, dtype=np.float64)
    sums = {perm: np.abs(d[list(perm), [0, 1, 2]]).sum()
            for perm in itertools.permutations(range(3))}
    best = max(sums.values())
    nearest = [perm for perm, total in sums.items() if total == best]
    if len(nearest) > 1:
        return None
    perm = list(nearest[0])
    signs = [1.0 if d[perm[a], a] > 0 else -1.0 for a in range(3)]
    return perm, signs


def reindex_to_identity(vol: Volume) -> Volume:
    """``vol`` with identity direction, by flips and transposes only (signed permutations).

    Every sample keeps its world point; the origin becomes the world point of
    the new first voxel. An oblique volume is reindexed by its nearest signed
    permutation, its direction what remains (:func:`reindexed_geometry`); one
    with none (:func:`signed_permutation`: an exact tie) is returned as it is. Where axes move, the samples are a contiguous copy
    (the writer writes :func:`reindexed_samples`, a view, instead).
    :func:`reindexed_header` is the same for a Header (a store written by
    blocks moves each block).
    """
    found = reindex_axes(vol.direction)
    if found is None or np.array_equal(vol.direction, np.eye(3)):
        return vol
    data = reindexed_samples(vol.data, vol.direction)
    if data is not vol.data:
        data = np.ascontiguousarray(data)
    return reindexed_header(vol.header).with_data(data)


def reindexed_samples(data: np.ndarray, direction) -> np.ndarray:
    """The samples ``data`` of a grid of ``direction`` as the store holds them: a view.

    ``np.flip`` and ``transpose`` only (:func:`reindex_axes`), no copy: a
    store is written from it a write unit at a time, and zarr copies each
    chunk out of it, whatever its strides (a whole contiguous copy was a
    second volume beside the first that no estimate counted). ``data``
    itself where no axis moves.
    """
    found = reindex_axes(direction)
    if found is None:
        return data
    flips, order = found
    if flips:
        data = np.flip(data, axis=flips)
    return data.transpose(order) if order != (0, 1, 2) else data


def reindexed_header(header: Header) -> Header:
    """:func:`reindex_to_identity` of a volume's Header: the stored grid, no samples.

    ``header`` itself when its direction is the identity or has no nearest signed permutation (an exact tie).
    """
    found = reindex_axes(header.direction)
    if found is None:
        return header
    flips, order = found
    if not flips and order == (0, 1, 2):
        if np.allclose(header.direction, np.eye(3), rtol=0, atol=_IDENTITY_TOLERANCE) \
                and not np.array_equal(header.direction, np.eye(3)):
            return header.replace(direction=np.eye(3))  # (a rounding's -0.0, 1 - 1e-16)
        return header
    from ..provenance import AS_READ_AXIS_KEYS

    shape = tuple(header.shape[o] for o in order)
    # (a slice axis, slice numbers or per-axis entries of the file's index order: not the
    # store's, whose axes are flipped or permuted)
    meta = {k: v for k, v in header.meta.items() if k not in AS_READ_AXIS_KEYS}
    return header.replace(shape=shape, meta=meta, **reindexed_geometry(header, flips, order))


def reindex_axes(direction) -> tuple[tuple[int, ...], tuple[int, int, int]] | None:
    """How :func:`reindex_to_identity` moves samples: ``(flips, order)``, or None.

    The array (z, y, x) axes ``flips`` are reversed, then the array is
    transposed by ``order`` (stored axis ``c`` is array axis ``order[c]``).
    None when ``direction`` has no nearest signed permutation (an exact tie).
    """
    found = signed_permutation(direction)
    if found is None:
        return None
    perm, signs = found
    flips = tuple(2 - a for a in range(3) if signs[a] < 0)
    # new index axis b (x, y, z) is old axis a with perm[a] == b; array axes are 2 - axis
    old_of_new = [perm.index(b) for b in range(3)]
    return flips, tuple(2 - old_of_new[2 - c] for c in range(3))


def reindexed_geometry(vol: Volume | Header, flips, order) -> dict:
    """Spacing, origin and direction of ``vol`` reindexed by ``(flips, order)``.

    The direction is the identity where ``vol``'s is a signed permutation (to
    :data:`_IDENTITY_TOLERANCE`), else what remains of it (an oblique grid's
    rotation from its nearest signed permutation, kept exactly).
    """
    n = np.array(vol.shape_xyz)
    first = np.array([n[a] - 1 if 2 - a in flips else 0 for a in range(3)], dtype=np.float64)
    # stored index axis b (x) is array axis 2 - b, which came from array axis order[2 - b]
    old = [2 - order[2 - b] for b in range(3)]
    spacing = np.array([vol.spacing[a] for a in old])
    sign = [-1.0 if 2 - a in flips else 1.0 for a in old]
    direction = np.column_stack([s * vol.direction[:, a] for s, a in zip(sign, old,
                                                                          strict=True)])
    if np.allclose(direction, np.eye(3), rtol=0, atol=_IDENTITY_TOLERANCE):
        direction = np.eye(3)
    return {"spacing": spacing, "origin": vol.index_to_world(first) + 0.0,
            "direction": direction + 0.0}


def warn_if_oblique(stored: Volume | Header, path) -> None:
    """Say that readers other than volwarp misplace ``stored`` (the grid as the store holds it).

    What the reindexing leaves of an oblique grid's rotation is kept in
    volwarp's attribute only: ome-zarr-py, ngff-zarr, napari and neuroglancer
    place the samples axis-aligned, silently. Said where that moves some voxel
    centre by more than :data:`~volwarp_cli.geometry.COVER_TOLERANCE` of a
    voxel (a grid that coincides but for rounding: a 1e-6 rad tilt, a NIfTI
    sform's float32 noise, is not worth a warning).
    """
    from ..geometry import COVER_TOLERANCE

    direction = np.asarray(stored.direction, dtype=np.float64)
    if np.array_equal(direction, np.eye(3)):
        return
    n = np.array(stored.shape_xyz, dtype=np.float64) - 1
    corners = np.array(list(itertools.product(*[(0.0, k) for k in n]))) * stored.spacing
    # (the first voxel is where both put it; the farthest corner is the farthest off)
    off = float(np.linalg.norm(corners @ (direction - np.eye(3)).T, axis=1).max())
    if off <= COVER_TOLERANCE * float(np.min(stored.spacing)):
        return
    angle = math.degrees(math.acos(min(1.0, max(-1.0, (np.trace(direction) - 1) / 2))))
    log.warning("%s: the grid is oblique (turned %.3g degrees from the nearest axis-aligned "
                "one) and NGFF has no rotation: readers other than volwarp (ome-zarr-py, "
                "ngff-zarr, napari, neuroglancer) place it without the rotation, voxels up "
                "to %.3g mm off; volwarp keeps it in its own attribute, .nrrd and .nii.gz "
                "keep it for every reader", path, angle, off)


# -- layout -----------------------------------------------------------------------------

def store_layout(shape_zyx, version: str = "0.5", chunks=None) -> tuple[tuple, tuple | None]:
    """``(chunks, shards)`` for an array of ``shape_zyx``; shards None for NGFF 0.4 (Zarr v2).

    Chunks are ``chunks`` (default 64 per axis) clipped to the shape; shards
    (0.5) are 256 per axis rounded up to whole chunks and clipped to the
    shape rounded up to whole chunks, so every shard is a whole number of chunks.
    """
    check_version(version)
    chunk = tuple(CHUNK for _ in range(3)) if chunks is None else tuple(int(c) for c in chunks)
    if len(chunk) != 3 or min(chunk) < 1:
        raise VolwarpError(f"OME-Zarr chunks must be 3 positive sizes (z, y, x), got {chunks}")
    chunk = tuple(max(1, min(c, int(n))) for c, n in zip(chunk, shape_zyx, strict=True))
    if version == "0.4":
        return chunk, None
    shard = []
    for c, n in zip(chunk, shape_zyx, strict=True):
        whole = math.ceil(max(int(n), 1) / c) * c
        shard.append(min(math.ceil(SHARD / c) * c, whole))
    return chunk, tuple(shard)


#: the NGFF versions volwarp reads (0.3 and before: axes as names, read by name)
READ_VERSIONS = ("0.1", "0.2", "0.3", "0.4", "0.5")


def check_version(version: str) -> str:
    """The NGFF version, or raise naming the ones volwarp writes."""
    if str(version) not in VERSIONS:
        raise VolwarpError(f"OME-Zarr version must be one of {', '.join(VERSIONS)}, "
                           f"got {version!r}")
    return str(version)


def level_shapes(shape_zyx, levels: int) -> list[tuple[int, int, int]]:
    """The array shape of each level (level 0 first): halved, rounded up."""
    shapes = [tuple(int(n) for n in shape_zyx)]
    for _ in range(levels):
        shapes.append(tuple(max(1, math.ceil(n / 2)) for n in shapes[-1]))
    return shapes


def level_transform(spacing_xyz, origin_xyz, level: int) -> tuple[list[float], list[float]]:
    """NGFF ``(scale, translation)`` of a level, array order (z, y, x)."""
    f = float(2 ** level)
    spacing = np.asarray(spacing_xyz, dtype=np.float64)
    scale = spacing * f
    translation = np.asarray(origin_xyz, dtype=np.float64) + spacing * (f - 1.0) / 2.0
    return ([float(v) for v in xyz_to_zyx(scale)],
            [float(v) + 0.0 for v in xyz_to_zyx(translation)])


# -- downsampling -----------------------------------------------------------------------

def _parts(data: np.ndarray):
    """The up to 8 sub-grids ``data[dz::2, dy::2, dx::2]``, padded to the coarse shape, and masks."""
    coarse = tuple(math.ceil(n / 2) for n in data.shape)
    for dz in (0, 1):
        for dy in (0, 1):
            for dx in (0, 1):
                part = data[dz::2, dy::2, dx::2]
                if min(part.shape) == 0:
                    continue
                if part.shape == coarse:
                    yield part, None
                    continue
                pad = [(0, c - p) for c, p in zip(coarse, part.shape, strict=True)]
                valid = np.zeros(coarse, dtype=bool)
                valid[tuple(slice(0, p) for p in part.shape)] = True
                yield np.pad(part, pad), valid


def downsample(data: np.ndarray, labels: bool = False) -> np.ndarray:
    """One pyramid step: each 2x2x2 block (partial at odd ends) to one sample, same dtype.

    ``labels``: the most frequent value of the block (the smallest of equally
    frequent ones); else the mean, in float64, rounded for integer types.
    """
    data = np.asarray(data)
    if labels:
        return _mode(data)
    total = None
    count = None
    for part, valid in _parts(data):
        v = part.astype(np.float64)
        total = v if total is None else total + v
        w = np.ones(part.shape) if valid is None else valid.astype(np.float64)
        count = w if count is None else count + w
    mean = total / count
    if data.dtype.kind in "iu":
        info = np.iinfo(data.dtype)
        return np.clip(np.rint(mean), info.min, info.max).astype(data.dtype)
    return mean.astype(data.dtype)


def _mode(data: np.ndarray) -> np.ndarray:
    parts = list(_parts(data))
    values = [p for p, _ in parts]
    valid = [np.ones(p.shape, dtype=bool) if m is None else m for p, m in parts]
    best = values[0].copy()
    best_count = np.zeros(best.shape, dtype=np.int8)
    for k, (cand, ok) in enumerate(zip(values, valid, strict=True)):
        count = np.zeros(best.shape, dtype=np.int8)
        for other, ok2 in zip(values, valid, strict=True):
            count += (other == cand) & ok2
        count[~ok] = 0
        better = (count > best_count) | ((count == best_count) & (cand < best) & ok)
        if k == 0:
            better = ok.copy()
        best = np.where(better, cand, best)
        best_count = np.where(better, count, best_count)
    return best.astype(data.dtype)


def resolve_labels(labels, data: np.ndarray, meta=None) -> bool:
    """``labels`` True/False as given; ``"auto"`` (or None): the rule.

    A volume its key/values say is a label map (``meta``: a SEG's, a NIfTI of
    intent label; :func:`~volwarp_cli.labelmap.segmentation_of`) is one when
    its samples are integer ids (a float field that kept such keys is not:
    its levels took the mode of distances); else :func:`looks_like_labels` of
    ``data``.
    """
    if labels is None or labels == "auto":
        from ..labelmap import segmentation_of, whole_ids

        if segmentation_of(meta):
            return whole_ids(data)
        return looks_like_labels(data)
    return bool(labels)


# -- metadata ---------------------------------------------------------------------------

def _axes() -> list[dict]:
    return [{"name": n, "type": "space", "unit": "millimeter"} for n in ("z", "y", "x")]


def multiscales_metadata(vol_geom, levels: int, version: str, method: str | None) -> dict:
    """The ``multiscales`` entry for a volume of ``vol_geom`` (spacing/origin xyz) and its levels."""
    datasets = []
    for level in range(levels + 1):
        scale, translation = level_transform(vol_geom.spacing, vol_geom.origin, level)
        datasets.append({"path": str(level), "coordinateTransformations": [
            {"type": "scale", "scale": scale},
            {"type": "translation", "translation": translation}]})
    entry = {"name": "image", "axes": _axes(), "datasets": datasets}
    if version == "0.4":
        entry = {"version": "0.4", **entry}
    if levels:
        entry["type"] = method
        entry["metadata"] = {"method": "volwarp_cli.io.omezarr.downsample",
                             "description": "2x2x2 " + method + (
                                 " (most frequent label)" if method == "mode" else "")}
    return entry


def volwarp_attribute(vol: Volume | Header, source: Volume | Header, method: str | None) -> dict:
    """The namespaced ``volwarp`` attribute: exact geometry, frame, key/values, provenance."""
    attr = {
        "version": ATTRIBUTE_VERSION,
        "shape": [int(n) for n in vol.shape_xyz],
        "spacing": [float(v) for v in vol.spacing],
        "origin": [float(v) + 0.0 for v in vol.origin],
        "direction": [[float(v) + 0.0 for v in row] for row in vol.direction],
        "space": vol.space,
        # (the store's own numbers are LPS, whatever frame the volume was read from: a
        # NIfTI's RAS made info say "the file's own: right-anterior-superior" of a store)
        "file_space": vol.space,
        "complete": True,
        "meta": {str(k): str(v) for k, v in sorted(vol.meta.items())},
    }
    if source is not vol and not np.array_equal(source.direction, vol.direction):
        attr["reindexed_from"] = {
            "shape": [int(n) for n in source.shape_xyz],
            "spacing": [float(v) for v in source.spacing],
            "origin": [float(v) + 0.0 for v in source.origin],
            "direction": [[float(v) + 0.0 for v in row] for row in source.direction],
        }
    if method is not None:
        attr["downsampling"] = method
    return attr


def group_attributes(multiscales: dict, volwarp: dict, version: str,
                     image_label: bool = False) -> dict:
    """The group's attributes for ``version``; ``image_label``: NGFF's mark of a segmentation.

    ``image-label`` (``version`` only: no colours, no ``source``, the store
    being no image's ``labels/`` child) tells other readers the samples are ids
    (ome-zarr-py, napari: a labels layer, not an image of intensities): NGFF
    0.4 makes any group holding it a segmentation, "unlisted groups MAY be
    labels". Of label maps of integer samples only (:func:`tags_image_label`).
    """
    ome = {"multiscales": [multiscales]}
    if image_label:
        ome["image-label"] = {"version": version}
    if version == "0.5":
        return {"ome": {"version": "0.5", **ome}, "volwarp": volwarp}
    return {**ome, "volwarp": volwarp}


def tags_image_label(labels: bool, dtype) -> bool:
    """Whether a store of ``labels`` (the label-map choice) and ``dtype`` carries ``image-label``.

    NGFF's label images are of integer types: a float32 map of ids is a label
    map to volwarp (its levels take the mode), not to NGFF.
    """
    return bool(labels) and np.dtype(dtype).kind in "iu"


# -- writing ----------------------------------------------------------------------------

def create_arrays(group, shapes, dtype: np.dtype, version: str, chunks=None,
                  byte_order: str = "little", layout0=None):
    """Create one empty array per level in ``group`` (chunks and shards per level).

    ``layout0``: ``(chunks, shards)`` of level 0 instead of :func:`store_layout`'s
    (a store written by blocks: one shard per block).
    """
    import zarr  # noqa: F401  (imported here only: the in-memory path stays free of it)

    arrays = []
    for level, shape in enumerate(shapes):
        chunk, shard = (layout0 if level == 0 and layout0 is not None
                        else store_layout(shape, version, chunks))
        code = "<" if byte_order == "little" else ">"
        if version == "0.5":
            from zarr.codecs import BytesCodec, ZstdCodec

            arr = group.create_array(
                str(level), shape=shape, chunks=chunk, shards=shard, dtype=dtype,
                serializer=BytesCodec(endian=byte_order),
                compressors=[ZstdCodec(level=ZSTD_LEVEL, checksum=True)], fill_value=0,
                dimension_names=["z", "y", "x"], config={"write_empty_chunks": True})
        else:
            from numcodecs import Zstd

            arr = group.create_array(
                str(level), shape=shape, chunks=chunk, dtype=dtype.newbyteorder(code),
                compressors=Zstd(level=ZSTD_LEVEL, checksum=True), fill_value=0,
                chunk_key_encoding={"name": "v2", "separator": "/"},
                config={"write_empty_chunks": True})
            _plain_zstd_metadata(group, arr)
        arrays.append(arr)
    return arrays


def _plain_zstd_metadata(group, arr) -> None:
    """Describe ``arr``'s compressor (zstd with frame checksums) as ``{"id": "zstd", "level": L}``.

    The array object keeps encoding with ``checksum=True``: every chunk is a
    zstd frame ending with the checksum of its content, which every zstd
    decoder verifies whatever the metadata says (numcodecs for zarr-python
    and ome-zarr-py, libzstd for zarrista/ngff-zarr), so an altered chunk is
    an error in any reader. Only the *key* goes: ``checksum`` is an encoder
    setting, and some readers refuse it (ngff-zarr's zarrista: "unknown field
    `checksum`, expected `level`"; zarr-python itself leaves out
    ``"checksum": false`` for such readers). Reading, volwarp checks the
    frames themselves (:func:`_check_chunks`).
    """
    path = Path(str(group.store.root)) / arr.path / ".zarray"
    doc = json.loads(path.read_text(encoding="utf-8"))
    comp = doc.get("compressor") or {}
    if comp.get("id") == "zstd" and comp.pop("checksum", None) is not None:
        path.write_text(json.dumps(doc, indent=2), encoding="utf-8")


def open_group_for_writing(folder: Path, version: str):
    """A new Zarr group in the (empty, temporary) ``folder``."""
    import zarr

    return zarr.open_group(str(folder), mode="w", zarr_format=3 if version == "0.5" else 2)


def write_levels(arrays, first: np.ndarray | None, labels: bool, budget: int | None = None
                 ) -> None:
    """Fill level 0 with ``first`` (unless None: already written) and each next level from the last.

    Level 0 is written one shard at a time (zarr encodes the shards of one
    write at once: :func:`write_bytes` each); in NGFF 0.4 (no shards) in
    boxes of whole chunks, as many at once as ``budget`` holds
    (:func:`chunk_pieces`: zarr encodes up to its concurrency's chunks of a
    write at once, each with its copy, its frame and a zstd context). Each
    coarser level is made shard
    by shard from the level above, and each of its shards piece by piece
    (:func:`level_pieces`: the largest pieces whose reading and averaging fit
    ``budget`` beside the shard), so that no level, and no 2x region of a
    shard, is read whole unless it fits; level 1 is averaged from ``first``
    itself where it is given. The pieces start at even samples, so every
    coarse sample is made from the same 2x2x2 block in the same order: the
    same bytes whatever the budget.

    ``first`` may be any array of level 0's shape, a view of any strides and
    byte order (:func:`reindexed_samples`): zarr copies each chunk out of it.
    ``budget``: the bytes the work may hold (default: what is left under the
    memory limit, :func:`volwarp_cli.memory.memory_limit`); an
    :class:`~volwarp_cli.errors.OutOfMemoryError` where a level's smallest
    piece (one chunk of level 0 in NGFF 0.4) does not fit it.
    """
    from ..memory import memory_limit

    if budget is None:
        budget = memory_limit()
    if first is not None:
        target = arrays[0]
        unit = target.shards
        if unit is None:  # (0.4: whole chunks, as many at once as the budget holds)
            unit = chunk_pieces(target.shape, target.chunks, np.dtype(target.dtype).itemsize,
                                budget)
        for box in _boxes(target.shape, unit):
            target[box] = first[box]
    for level, (prev, arr) in enumerate(zip(arrays[:-1], arrays[1:], strict=True), start=1):
        source = first if level == 1 and first is not None else prev
        block = arr.shards or arr.chunks
        piece = level_pieces(block, arr.chunks, prev.shape, prev.chunks,
                             np.dtype(arr.dtype).itemsize, budget, held=source is first)
        for box in _boxes(arr.shape, block):
            shard = np.empty(tuple(s.stop - s.start for s in box), dtype=arr.dtype)
            for sub in _boxes(shard.shape, piece):
                src = tuple(slice(2 * (b.start + s.start), min(2 * (b.start + s.stop), n))
                            for b, s, n in zip(box, sub, prev.shape, strict=True))
                shard[sub] = downsample(np.asarray(source[src]), labels)
            arr[box] = shard
            del shard


#: zarr-python's chunks (and shards) encoded or decoded at once, when its config says none
_CONCURRENCY = 10


def _concurrency() -> int:
    """The ``async.concurrency`` of zarr, without loading zarr for an estimate (17 MiB).

    Its config where zarr is loaded, else the variable its config reads
    (``ZARR_ASYNC__CONCURRENCY``), else its default: a write re-checks once
    zarr is loaded (:func:`write_omezarr`).
    """
    import sys

    zarr = sys.modules.get("zarr")
    try:
        if zarr is not None:
            return max(1, int(zarr.config.get("async.concurrency") or _CONCURRENCY))
        return max(1, int(os.environ.get("ZARR_ASYNC__CONCURRENCY") or _CONCURRENCY))
    except Exception:  # (no such key, a malformed value: its default)
        return _CONCURRENCY


#: what zstd's compression context holds while it encodes a chunk (numcodecs makes one a
#: call; its tables are sized to the input, up to level 3's): with the chunk's copy and its
#: frame, 2.3-2.7 MiB a 1 MiB chunk in flight, measured
ZSTD_CONTEXT = 1 << 19
#: what a Zarr v2 write holds beside its chunks: zarr's buffers, and its threads' (a
#: 256^3 float32 level 0 written one 1 MiB chunk at a time by convert: 4.8-5.0 MiB over
#: the process, now and then 6.6 MiB, measured)
V2_WRITE_OVERHEAD = 5 << 20


def write_bytes(shape_zyx, itemsize: int, chunks, shards=None) -> int:
    """The bytes zarr holds beyond the samples while it writes a region of ``shape_zyx``.

    The region is made of whole write units (shards, or chunks in NGFF 0.4).
    Sharded (0.5): zarr encodes each shard whole, its chunks' zstd frames
    kept until they are joined into the shard's bytes, a second copy, so up
    to twice the region (samples that do not compress) beside a few chunks'
    buffers. 0.4 (Zarr v2): the chunks in flight (the write's, up to zarr's
    concurrency: ten by default, whatever the region's size), each with its
    copy, its frame (as large, for samples that do not compress) and a zstd
    context (:data:`ZSTD_CONTEXT`), and :data:`V2_WRITE_OVERHEAD`.
    """
    region = math.prod(int(n) for n in shape_zyx) * int(itemsize)
    if shards is None:
        chunk = math.prod(int(c) for c in chunks) * int(itemsize)
        count = math.prod(-(-int(n) // int(c)) for n, c in zip(shape_zyx, chunks, strict=True))
        in_flight = min(count, _concurrency())
        return in_flight * (2 * chunk + min(chunk, ZSTD_CONTEXT)) + V2_WRITE_OVERHEAD
    return 2 * region + _chunk_buffers(shape_zyx, chunks, itemsize)


def chunk_pieces(shape_zyx, chunks, itemsize: int, budget: int) -> tuple[int, int, int]:
    """The boxes :func:`write_levels` writes level 0 of a Zarr v2 (NGFF 0.4) array in.

    Whole chunks: the largest of :func:`_halvings` of the chunk grid whose
    write (:func:`write_bytes`: its chunks in flight) fits ``budget``, the
    whole array where it does (the same bytes either way: each chunk is
    encoded on its own). An :class:`~volwarp_cli.errors.OutOfMemoryError`
    naming both sizes where one chunk does not fit.
    """
    from ..errors import OutOfMemoryError
    from ..memory import human_bytes

    grid = tuple(max(1, -(-int(n) // int(c))) for n, c in zip(shape_zyx, chunks, strict=True))
    need = None
    for units in _halvings(grid):
        piece = tuple(min(u * int(c), max(int(n), 1))
                      for u, c, n in zip(units, chunks, shape_zyx, strict=True))
        need = write_bytes(piece, itemsize, chunks)
        if need <= budget:
            return piece
    raise OutOfMemoryError(f"writing a chunk of {'x'.join(map(str, tuple(chunks)[::-1]))} "
                           f"samples needs {human_bytes(need)} but only {human_bytes(budget)} "
                           "is left under the memory limit (raise --memory-limit)")


def read_bytes(shape_zyx, itemsize: int, chunks, hull_zyx=None) -> int:
    """The bytes reading a region of ``shape_zyx`` from a zarr array takes, the result included.

    ``hull_zyx``: the shape of the whole chunks the region touches (default
    the region): their encoded bytes are read first (a whole shard's at once
    where the region covers it), then decoded chunk by chunk into a buffer of
    the shard's part of the region, copied into the result: twice the region
    beside the chunks' bytes and a few chunks' buffers.
    """
    region = math.prod(int(n) for n in shape_zyx) * int(itemsize)
    hull = math.prod(int(n) for n in (hull_zyx or shape_zyx)) * int(itemsize)
    return 2 * region + hull + _chunk_buffers(hull_zyx or shape_zyx, chunks, itemsize)


def _chunk_buffers(shape_zyx, chunks, itemsize: int) -> int:
    """Two buffers (samples, frame) of each chunk zarr encodes or decodes at once, and 1 MiB."""
    count = math.prod(-(-int(n) // int(c)) for n, c in zip(shape_zyx, chunks, strict=True))
    chunk = math.prod(int(c) for c in chunks) * int(itemsize)
    return 2 * min(count, _concurrency()) * chunk + (1 << 20)


def downsample_bytes(coarse_voxels: int, itemsize: int) -> int:
    """The most :func:`downsample` holds (its result included) making ``coarse_voxels`` samples.

    Measured: the mean's float64 sums, counts and their copies (44-65 bytes
    a coarse voxel), the mode's padded parts and masks (16-87 for 8-byte
    samples at odd ends).
    """
    return int(coarse_voxels) * (56 + 8 * int(itemsize))


def _span(f: int, c: int, n: int) -> int:
    """Samples of the whole chunks (of ``c``) a run of ``f`` samples starting at a multiple of ``f`` touches."""
    whole = -(-f // c) * c
    if f % c and c % f:  # (not aligned to the chunks: one more)
        whole += c
    return min(whole, max(int(n), 1))


def _halvings(shape):
    """Piece shapes from ``shape`` down: halved along z, then y, then x (one sample at least)."""
    piece = [int(n) for n in shape]
    yield tuple(piece)
    for axis in range(3):
        while piece[axis] > 1:
            piece[axis] = -(-piece[axis] // 2)
            yield tuple(piece)


def level_pieces(block, chunks, prev_shape, prev_chunks, itemsize: int, budget: int, *,
                 held: bool = False) -> tuple[int, int, int]:
    """The pieces (coarse shape) :func:`write_levels` makes a coarse shard of ``block`` in.

    The largest of :func:`_halvings` whose step fits ``budget``
    (:func:`level_step_bytes`); ``chunks``: the coarse level's chunks;
    ``prev_shape``, ``prev_chunks``: the level above's (``held``: read from
    an array in memory instead, at no cost). An
    :class:`~volwarp_cli.errors.OutOfMemoryError` naming both sizes where none fits.
    """
    from ..errors import OutOfMemoryError
    from ..memory import human_bytes

    need = None
    for piece in _halvings(block):
        need = level_step_bytes(block, chunks, piece, prev_shape, prev_chunks, itemsize,
                                held=held)
        if need <= budget:
            return piece
    raise OutOfMemoryError(f"a pyramid level's shard of {'x'.join(map(str, block[::-1]))} "
                           f"samples needs {human_bytes(need)} but only "
                           f"{human_bytes(budget)} is left under the memory limit (raise "
                           "--memory-limit, or give fewer --pyramid levels)")


def level_step_bytes(block, chunks, piece, prev_shape, prev_chunks, itemsize: int, *,
                     held: bool = False) -> int:
    """The most a coarse shard of ``block`` made in pieces of ``piece`` holds (:func:`write_levels`).

    The shard's samples, and the larger of its encoding (:func:`write_bytes`)
    and one piece's reading (:func:`read_bytes`: the whole chunks of the
    level above its 2x region touches; none where ``held``) with its
    averaging (:func:`downsample_bytes`).
    """
    shard = math.prod(int(n) for n in block) * int(itemsize)
    fine = tuple(min(2 * p, int(n)) for p, n in zip(piece, prev_shape, strict=True))
    step = downsample_bytes(math.prod(piece), itemsize)
    if not held:
        hull = tuple(_span(f, int(c), n) for f, c, n in zip(fine, prev_chunks, prev_shape,
                                                             strict=True))
        step += read_bytes(fine, itemsize, prev_chunks, hull)
    return shard + max(step, write_bytes(block, itemsize, chunks, block))


def pyramid_bytes(shape_zyx, itemsize: int, version: str, levels: int, *, held: bool = False,
                  chunks=None, layout0=None) -> int:
    """The least memory :func:`write_levels` needs to make ``levels`` levels (0: none).

    Each level's shards made in its smallest pieces (:func:`level_step_bytes`);
    ``held``: level 1 made from level 0 in memory; ``chunks`` and
    ``layout0``: :func:`create_arrays`'s (a store written by blocks). The
    largest level's.
    """
    shapes = level_shapes(shape_zyx, levels)
    need = 0
    prev_chunks = (layout0 or store_layout(shapes[0], version, chunks))[0]
    for level in range(1, levels + 1):
        inner, shards = store_layout(shapes[level], version, chunks)
        block = shards or inner
        smallest = list(_halvings(block))[-1]
        need = max(need, level_step_bytes(block, inner, smallest, shapes[level - 1],
                                          prev_chunks, itemsize, held=held and level == 1))
        prev_chunks = inner
    return need


#: bytes a voxel counting a box's values takes (:func:`volwarp_cli.labelmap.looks_like_labels`:
#: the samples as int64 and their counts; measured 8)
COUNT_BYTES = 12


def scan_pieces(arr, budget: int) -> list:
    """Boxes tiling the zarr array ``arr``, each within one of its shards, read in ``budget``.

    For the label-map rule's count of a store's samples
    (:func:`volwarp_cli.labelmap.looks_like_labels_by_blocks`): the largest
    :func:`_halvings` of a shard whose reading (:func:`read_bytes`) and
    counting (:data:`COUNT_BYTES` a voxel) fit ``budget`` (one sample at the
    least). The answer does not depend on the boxes.
    """
    from ..box import Box

    item = np.dtype(arr.dtype).itemsize
    block = arr.shards or arr.chunks
    piece = (1, 1, 1)
    for cand in _halvings(tuple(min(b, n) for b, n in zip(block, arr.shape, strict=True))):
        hull = tuple(_span(p, c, n) for p, c, n in zip(cand, arr.chunks, arr.shape,
                                                       strict=True))
        if read_bytes(cand, item, arr.chunks, hull) + COUNT_BYTES * math.prod(cand) <= budget:
            piece = cand
            break
    boxes = []
    for shard in _boxes(arr.shape, block):
        for sub in _boxes(tuple(s.stop - s.start for s in shard), piece):
            lo = tuple(a.start + b.start for a, b in zip(shard, sub, strict=True))
            hi = tuple(a.start + b.stop for a, b in zip(shard, sub, strict=True))
            boxes.append(Box(lo, hi))
    return boxes


def memory_bytes(shape_zyx, dtype, version: str = "0.5", pyramid: int = 0, labels="auto") -> int:
    """What :func:`write_omezarr` holds beyond the volume's samples (which its caller holds).

    The largest of: level 0's one shard at a time (:func:`write_bytes`; NGFF
    0.4: one chunk at a time, the least: :func:`write_levels` writes as many
    at once as the budget then holds), the label-map rule's count (``labels="auto"`` with levels
    or of integer samples: its boxes of
    :data:`~volwarp_cli.labelmap.SCAN_BOX_VOXELS`) and the levels made in
    their smallest pieces (:func:`pyramid_bytes`: they take larger ones
    where the budget holds them).
    """
    from ..labelmap import SCAN_BOX_VOXELS

    version = check_version(version)
    item = np.dtype(dtype).itemsize
    chunks, shards = store_layout(shape_zyx, version)
    need = write_bytes(shards or chunks, item, chunks, shards)
    # (integer samples are looked at without levels too: whether image-label is written)
    if (pyramid or np.dtype(dtype).kind in "iu") and (labels is None or labels == "auto"):
        voxels = min(SCAN_BOX_VOXELS, math.prod(int(n) for n in shape_zyx))
        need = max(need, COUNT_BYTES * voxels)
    if pyramid:
        need = max(need, pyramid_bytes(shape_zyx, item, version, pyramid, held=True))
    return need


def _boxes(shape, block):
    import itertools

    ranges = [range(0, n, b) for n, b in zip(shape, block, strict=True)]
    for lo in itertools.product(*ranges):
        yield tuple(slice(a, min(a + b, n)) for a, b, n in zip(lo, block, shape, strict=True))


def write_omezarr(vol: Volume, path: str | os.PathLike, *, version: str = "0.5",
                  pyramid: int = 0, labels="auto", chunks=None,
                  byte_order: str = "little") -> None:
    """Write ``vol`` as an OME-Zarr store at ``path``, atomically (module notes).

    ``version``: ``"0.5"`` (Zarr v3, sharded) or ``"0.4"`` (Zarr v2);
    ``pyramid``: extra levels; ``labels``: True, False or ``"auto"`` (how the
    levels are made, and whether ``image-label`` says it holds ids); ``chunks``:
    chunk shape (z, y, x), default 64 per axis.
    """
    from ..memory import large_allocations_mapped
    from .atomic import atomic_folder

    path = Path(path)
    version = check_version(version)
    pyramid = int(pyramid)
    if pyramid < 0:
        raise VolwarpError(f"{path}: --pyramid must be 0 or more, got {pyramid}")
    check_dtype(vol.data.dtype, str(path))
    from ..memory import ensure_fits_in_memory

    stored = reindexed_header(vol.header)
    # (the samples as the store holds them, a view: zarr copies a chunk at a time out of
    # it, whatever its strides and byte order, so that no second volume is held)
    data = reindexed_samples(vol.data, vol.direction)
    # (before the store is made: its encoding, label count and levels beside the samples)
    ensure_fits_in_memory(memory_bytes(stored.shape, data.dtype, version, pyramid, labels),
                          f"writing {path} ({'x'.join(map(str, vol.shape_xyz))}"
                          f"{f', {pyramid} levels' if pyramid else ''})")
    # (decided without levels too where the samples are integers: image-label says it)
    is_labels = (resolve_labels(labels, data, vol.meta) if pyramid or data.dtype.kind in "iu"
                 else False)
    method = ("mode" if is_labels else "mean") if pyramid else None
    if pyramid:  # (the label choice said at -v, as every command says it)
        log.info("%s: %d pyramid level(s) by the %s (%s)", path, pyramid, method,
                 "a label map" if is_labels else "intensities")
    shapes = level_shapes(stored.shape, pyramid)
    attrs = group_attributes(multiscales_metadata(stored, pyramid, version, method),
                             volwarp_attribute(stored, vol, method), version,
                             tags_image_label(is_labels, data.dtype))
    warn_if_oblique(stored, path)
    # (zarr's threads' freed frames given back as the store is written: see there)
    with large_allocations_mapped(), atomic_folder(path) as tmp:
        group = open_group_for_writing(tmp, version)
        arrays = create_arrays(group, shapes, data.dtype.newbyteorder("="), version, chunks,
                               byte_order)
        write_levels(arrays, data, is_labels)
        group.attrs.update(attrs)


# -- reading ----------------------------------------------------------------------------

def _load_json(path: Path, where: str) -> dict:
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise FormatError(f"{where}: cannot read {path.name} ({exc.strerror})") from None
    except ValueError as exc:
        raise FormatError(f"{where}: {path.name} is not valid JSON ({exc})") from None
    if not isinstance(doc, dict):
        raise FormatError(f"{where}: {path.name} is not a JSON object")
    return doc


def group_metadata(path: Path) -> tuple[int, dict]:
    """``(zarr_format, attributes)`` of the group at ``path`` (FormatError if it is none)."""
    where = str(path)
    if not path.exists():
        raise FormatError(f"{where}: no such store")
    if not path.is_dir():
        raise FormatError(f"{where}: is a file, not an OME-Zarr store (a folder)")
    if (path / "zarr.json").is_file():
        doc = _load_json(path / "zarr.json", where)
        if doc.get("node_type") != "group":
            raise FormatError(f"{where}: zarr.json describes a {doc.get('node_type')!r}, "
                              "not a group (an OME-Zarr image is a group)")
        attrs = doc.get("attributes", {})
        return 3, attrs if isinstance(attrs, dict) else {}
    if (path / ".zgroup").is_file() or (path / ".zattrs").is_file():
        attrs = _load_json(path / ".zattrs", where) if (path / ".zattrs").is_file() else {}
        return 2, attrs
    raise FormatError(f"{where}: not a Zarr store (no zarr.json, .zgroup or .zattrs)")


def _multiscales(attrs: dict, where: str) -> dict:
    ome = attrs.get("ome")
    found = None
    if isinstance(ome, dict) and "multiscales" in ome:
        found = ome["multiscales"]
    elif "multiscales" in attrs:
        found = attrs["multiscales"]
    if not isinstance(found, list) or not found or not isinstance(found[0], dict):
        raise FormatError(f"{where}: no OME-NGFF 'multiscales' metadata (not an OME-Zarr image)")
    return found[0]


def _or_dicom_series(path: Path, exc: FormatError) -> FormatError:
    """``exc``, or for a folder that also holds DICOM files, a refusal naming both readings.

    A ``.zattrs`` or ``zarr.json`` left in a DICOM series folder (by a tool, or
    copied along) makes the folder a Zarr store here, refused as "no multiscales".
    It is not read as DICOM instead: a true Zarr store's raw chunks can pass
    for DICOM data sets (:func:`~.dicom.is_dicom_path` also takes files without
    the preamble), and a store read as a DICOM series would be silently wrong.
    """
    from . import stray_zarr_metadata

    found = stray_zarr_metadata(path)
    if found is None:
        return exc
    why = str(exc).removeprefix(f"{path}: ")
    return FormatError(f"{path}: holds DICOM files, and Zarr metadata ({found}) that is no "
                       f"OME-Zarr image ({why}): a DICOM series? move {found} out of it; "
                       "a Zarr store? volwarp reads OME-Zarr images only")


def _transforms(items, n: int, where: str, what: str) -> tuple[np.ndarray, np.ndarray]:
    scale = np.ones(n)
    translation = np.zeros(n)
    for t in items or []:
        if not isinstance(t, dict):
            raise FormatError(f"{where}: {what}: a coordinateTransformation is not an object")
        kind = t.get("type")
        if kind == "identity":
            continue
        if kind not in ("scale", "translation"):
            raise FormatError(f"{where}: {what}: coordinateTransformation {kind!r} is not "
                              "supported (scale, translation)")
        if kind not in t:
            raise FormatError(f"{where}: {what}: the {kind} transformation has no values "
                              "(given by path?)")
        try:
            v = np.array([float(x) for x in t[kind]], dtype=np.float64)
        except (TypeError, ValueError):
            raise FormatError(f"{where}: {what}: {kind} must be numbers") from None
        if v.shape != (n,) or not np.all(np.isfinite(v)):
            raise FormatError(f"{where}: {what}: {kind} must be {n} finite numbers, "
                              f"got {t[kind]}")
        if kind == "scale":
            scale, translation = scale * v, translation * v
        else:
            translation = translation + v
    return scale, translation


class Opened:
    """A store opened for reading: level 0 (zarr array), its selection, and its geometry."""

    def __init__(self, array, index, view_shape, spacing, origin, direction, space, file_space,
                 meta, where):
        self.array = array
        self.view_shape = tuple(view_shape)
        self.index = index  # the numpy index taking the stored array to [z, y, x]
        self.spacing, self.origin, self.direction = spacing, origin, direction
        self.space, self.file_space, self.meta = space, file_space, meta
        self.where = where
        #: ``(store, level 0's folder, identity)`` as opened (:func:`.mapped.folder_identity`)
        self.identity = None

    def changed(self) -> bool:
        """Whether the store changed since it was opened (another one swapped in, say)."""
        from .mapped import folder_identity

        return self.identity is not None and folder_identity(*self.identity[:2]) \
            != self.identity[2]

    def geometry(self):
        """The :class:`~volwarp_cli.geometry.Geometry` of the volume."""
        from ..geometry import Geometry

        return Geometry(self.view_shape, self.spacing, self.origin, self.direction)


def _finest(datasets: list, n: int, space_axes: list, where: str) -> int:
    """The index of the dataset with the finest grid (level 0): NGFF lists it first.

    A store that lists its levels otherwise was read at a coarser level, exit
    0: the finest by its scale is read, with a warning.
    """
    finest, best = 0, None
    for k, ds in enumerate(datasets):
        try:  # (the first must be well formed: its own errors come where it is read)
            if not isinstance(ds, dict) or "path" not in ds:
                raise FormatError(f"{where}: multiscales dataset {k} has no path")
            scale, _ = _transforms(ds.get("coordinateTransformations"), n, where,
                                   f"dataset {ds['path']!r}")
        except FormatError:
            if k == 0:
                raise
            continue  # (a coarser level this read never opens)
        size = float(np.prod(np.abs(scale[space_axes])))
        if best is None or size < best:
            finest, best = k, size
    if finest:
        log.warning("warning: %s: its multiscales list level %r first, but %r is finer (NGFF "
                    "lists the finest first): %r read", where, datasets[0]["path"],
                    datasets[finest]["path"], datasets[finest]["path"])
    return finest


def open_omezarr(path: str | os.PathLike, volume_index: int | None = None) -> Opened:
    """Open the store at ``path``: level 0 and the geometry volwarp gives it (module notes)."""
    import zarr

    from ..memory import bound_arenas
    from .mapped import folder_identity

    bound_arenas()  # (before zarr's decoding threads: their arenas kept the chunks they freed)

    path = Path(path)
    where = str(path)
    try:  # (the store's own folder as first seen: one swapped in from here on is another)
        st = os.stat(path)
        root_key = st.st_dev, st.st_ino
    except OSError:
        root_key = None
    try:
        fmt, attrs = group_metadata(path)
        ms = _multiscales(attrs, where)
    except FormatError as exc:
        raise _or_dicom_series(path, exc) from None
    ome = attrs.get("ome") if isinstance(attrs.get("ome"), dict) else {}
    version = ome.get("version", ms.get("version"))
    if version is not None and str(version) not in READ_VERSIONS:
        # (later versions change how coordinate transformations are given: not guessed)
        raise FormatError(f"{where}: OME-NGFF version {version!r}: volwarp reads versions "
                          f"{', '.join(READ_VERSIONS)}")
    axes = ms.get("axes")
    if not isinstance(axes, list) or not axes:
        raise FormatError(f"{where}: multiscales has no 'axes'")
    names = []
    kinds = []
    units = []
    for ax in axes:
        if isinstance(ax, str):  # NGFF 0.3 spelled axes as names
            ax = {"name": ax, "type": "space" if ax in "zyx" else None}
        if not isinstance(ax, dict) or "name" not in ax:
            raise FormatError(f"{where}: multiscales 'axes' entry {ax!r} has no name")
        names.append(str(ax["name"]))
        kind = ax.get("type")
        if kind is None and str(ax["name"]).lower() in ("x", "y", "z"):
            kind = "space"
        kinds.append(kind)
        units.append(ax.get("unit"))
    space_axes = [i for i, k in enumerate(kinds) if k == "space"]
    by_name = {names[i].lower(): i for i in space_axes}
    if len(space_axes) != 3 or sorted(by_name) != ["x", "y", "z"]:
        raise FormatError(f"{where}: volwarp reads 3-D images with space axes z, y, x; this "
                          f"one has axes {names}")
    datasets = ms.get("datasets")
    if not isinstance(datasets, list) or not datasets or not isinstance(datasets[0], dict) \
            or "path" not in datasets[0]:
        raise FormatError(f"{where}: multiscales has no datasets")
    n = len(axes)
    level = _finest(datasets, n, space_axes, where)
    s0, t0 = _transforms(datasets[level].get("coordinateTransformations"), n, where,
                         f"dataset {datasets[level]['path']!r}")
    s1, t1 = _transforms(ms.get("coordinateTransformations"), n, where, "multiscales")
    scale, translation = s0 * s1, t0 * s1 + t1
    factors = []
    for i in (by_name["z"], by_name["y"], by_name["x"]):
        unit = units[i]
        if unit is None:
            factors.append(1.0)
            continue
        factor = NGFF_UNIT_TO_MM.get(str(unit).lower()) or NGFF_UNIT_TO_MM.get(str(unit))
        if factor is None:
            raise FormatError(f"{where}: axis {names[i]!r} has unit {unit!r}, which volwarp "
                              f"cannot convert to millimetres (known: "
                              f"{', '.join(sorted(k for k in NGFF_UNIT_TO_MM if len(k) > 3))})")
        factors.append(factor)
    order = [by_name["z"], by_name["y"], by_name["x"]]
    spacing_zyx = np.array([scale[i] for i in order]) * factors
    origin_zyx = np.array([translation[i] for i in order]) * factors
    key = str(datasets[level]["path"])
    if os.path.isabs(key) or ".." in Path(key).parts:  # (a key in the store, not a path)
        raise FormatError(f"{where}: dataset path {key!r} leads out of the store (NGFF paths "
                          "are keys inside it)")
    array_path = path / key
    # (before zarr reads level 0's metadata: the chunks read later must be of that store)
    identity = (path, array_path, folder_identity(path, array_path, root_key))
    try:
        arr = zarr.open_array(str(array_path), mode="r", zarr_format=fmt)
    except Exception as exc:  # zarr raises several types for missing or bad metadata
        raise FormatError(f"{where}: cannot open level 0 ({datasets[level]['path']!r}: "
                          f"{type(exc).__name__}: {_one_line(exc)})") from None
    if arr.ndim != n:
        raise FormatError(f"{where}: level 0 has {arr.ndim} axes, the multiscales name {n}")
    # the selection: other axes (time, channel) dropped or chosen by volume_index
    index: list = []
    others = [i for i in range(n) if kinds[i] != "space"]
    big = [i for i in others if arr.shape[i] > 1]
    if len(big) > 1:
        raise FormatError(f"{where}: has axes {[names[i] for i in big]} of sizes "
                          f"{[arr.shape[i] for i in big]}; volwarp reads one volume, selected "
                          "along at most one of them with --volume-index")
    if big:
        count = arr.shape[big[0]]
        if volume_index is None:
            raise ChoiceNeeded(f"{where}: has {count} entries along axis {names[big[0]]!r}; "
                              f"select one with --volume-index 0..{count - 1}")
        if not 0 <= volume_index < count:
            raise BadUsage(f"{where}: --volume-index {volume_index} is out of range: axis "
                           f"{names[big[0]]!r} has {count} entries")
    elif volume_index not in (None, 0):
        raise BadUsage(f"{where}: --volume-index {volume_index} given, but the image holds "
                       "one volume")
    for i in range(n):  # (the index on the one longer axis; a size-1 axis' only entry)
        if kinds[i] == "space":
            index.append(slice(None))
        else:
            index.append(volume_index if big and i == big[0] else 0)
    remaining = [i for i in range(n) if kinds[i] == "space"]  # axes left after the selection
    transpose = [remaining.index(i) for i in order]
    check_dtype(arr.dtype, where)
    shape_zyx = tuple(int(arr.shape[i]) for i in order)
    vw = attrs.get("volwarp")
    spacing = np.array(zyx_to_xyz(spacing_zyx), dtype=np.float64)
    origin = np.array(zyx_to_xyz(origin_zyx), dtype=np.float64) + 0.0
    direction = np.eye(3)
    space = file_space = None
    meta: dict = {}
    if isinstance(vw, dict):
        spacing, origin, direction, space, file_space, meta = _check_volwarp(
            vw, spacing, origin, shape_zyx, where)
        if not _check_chunks(arr, array_path, where, bool(vw.get("complete"))):
            log.warning("%s: this volwarp store's chunks carry no checksum (written by an "
                        "older volwarp): a damaged chunk cannot be told from good samples; "
                        "rewrite it with volwarp convert", where)
    elif vw is not None:
        raise FormatError(f"{where}: the 'volwarp' attribute is not an object")
    elif getattr(arr, "shards", None):
        _refuse_empty_files(array_path, where)
    ome = attrs.get("ome") if isinstance(attrs.get("ome"), dict) else attrs
    if "image-label" in ome:  # (an NGFF labels image: its samples are label ids)
        meta = {**meta, "OME_image_label": json.dumps(ome["image-label"], sort_keys=True)}
    spacing, origin, direction = check_placement(
        spacing, origin, direction, zyx_to_xyz(shape_zyx), where=where, fields=_FIELDS)
    opened = Opened(arr, (tuple(index), transpose), shape_zyx, spacing, origin, direction,
                    space, file_space, meta, where)
    opened.identity = identity
    return opened


#: the metadata each part of the geometry comes from (for the errors that name it)
_FIELDS = {"spacing": "multiscales coordinateTransformations scale",
           "origin": "multiscales coordinateTransformations translation",
           "direction": "the 'volwarp' attribute's direction"}


def _check_volwarp(vw: dict, spacing, origin, shape_zyx, where: str):
    """The geometry in volwarp's attribute, checked against the multiscales (module notes)."""
    try:
        a_spacing = np.array(vw["spacing"], dtype=np.float64)
        a_origin = np.array(vw["origin"], dtype=np.float64)
        a_direction = np.array(vw["direction"], dtype=np.float64)
        a_shape = tuple(int(v) for v in vw["shape"])
    except (KeyError, TypeError, ValueError) as exc:
        raise FormatError(f"{where}: the 'volwarp' attribute is damaged ({exc!r})") from None
    if a_spacing.shape != (3,) or a_origin.shape != (3,) or a_direction.shape != (3, 3):
        raise FormatError(f"{where}: the 'volwarp' attribute is damaged (shapes of spacing, "
                          "origin, direction)")
    if a_shape != tuple(zyx_to_xyz(shape_zyx)):
        raise FormatError(f"{where}: the 'volwarp' attribute says shape {list(a_shape)}, level "
                          f"0 has {list(zyx_to_xyz(shape_zyx))} (x, y, z)")
    tol = 1e-9
    if not np.allclose(a_spacing, spacing, rtol=tol, atol=0):
        raise FormatError(f"{where}: the 'volwarp' attribute's spacing {a_spacing.tolist()} "
                          f"disagrees with the multiscales scale {spacing.tolist()} (x, y, z; "
                          "edited by another program?)")
    scale_len = float(np.max(np.abs(a_spacing) * np.array(a_shape))) + float(
        np.max(np.abs(a_origin)))
    if not np.allclose(a_origin, origin, rtol=0, atol=tol * max(1.0, scale_len)):
        raise FormatError(f"{where}: the 'volwarp' attribute's origin {a_origin.tolist()} "
                          f"disagrees with the multiscales translation {origin.tolist()} "
                          "(x, y, z; edited by another program?)")
    meta = vw.get("meta", {})
    if not isinstance(meta, dict):
        raise FormatError(f"{where}: the 'volwarp' attribute's meta is not an object")
    return (a_spacing, a_origin, a_direction, vw.get("space"), vw.get("file_space"),
            {str(k): str(v) for k, v in meta.items()})


#: numcodecs (Zarr v2) codecs whose decoding checks the data: checksum filters, and gzip
#: (its trailer's CRC-32); zstd only with its frame checksum
_V2_CHECKED = frozenset(("crc32", "crc32c", "adler32", "fletcher32", "gzip"))
#: the magic number that starts a zstd frame, and the Content_Checksum_flag of the byte after
_ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"
_ZSTD_CHECKSUM_FLAG = 0x04


def chunks_are_checksummed(arr) -> bool:
    """Whether the metadata of the zarr array ``arr`` say that reading a chunk verifies it.

    Zarr v3: zstd with ``checksum`` or CRC32C (and, sharded, a CRC32C on the
    shard index, as volwarp writes); Zarr v2: zstd with ``checksum``, a
    checksum filter or gzip. volwarp's own Zarr v2 stores leave the
    ``checksum`` key out (:func:`_plain_zstd_metadata`): their frames say it,
    and :func:`_check_chunks` reads it there.
    """
    md = arr.metadata
    if getattr(md, "zarr_format", 3) == 2:
        codecs = list(md.filters or ()) + ([md.compressor] if md.compressor is not None else [])
        return any(_v2_checked(c) for c in codecs)
    return _v3_checked(md.codecs)


def _v2_checked(codec) -> bool:
    name = str(getattr(codec, "codec_id", "")).lower()
    if name == "zstd":
        return bool(getattr(codec, "checksum", False))
    return name in _V2_CHECKED


def _v3_checked(codecs) -> bool:
    for codec in codecs:
        name = type(codec).__name__
        if name == "ShardingCodec":
            return (_v3_checked(codec.codecs)
                    and any(type(c).__name__ == "Crc32cCodec" for c in codec.index_codecs))
        if name in ("Crc32cCodec", "GzipCodec"):
            return True
        if name == "ZstdCodec" and getattr(codec, "checksum", False):
            return True
    return False


def _refuse_empty_files(array_path: Path, where: str) -> None:
    """Refuse an empty shard file of another program's store (zarr reads it as missing).

    A shard holds at least its index; an empty one was cut (a copy, a full disk),
    and zarr read it as its fill value, a block of zeros, without a word.
    """
    for folder, _, files in os.walk(array_path):
        for name in files:
            if name in ("zarr.json", ".zarray", ".zattrs", ".zgroup"):
                continue
            full = os.path.join(folder, name)
            if os.path.getsize(full) == 0:
                key = os.path.relpath(full, array_path)
                raise FormatError(f"{where}: chunk data is damaged (shard {key!r} of level 0 "
                                  "is an empty file)")


def _check_chunks(arr, array_path: Path, where: str, complete: bool) -> bool:
    """Check the chunk files of level 0 of a volwarp store; True when all are checksummed.

    ``complete`` (volwarp writes every chunk): a missing chunk (or shard) file
    is refused. The checksums: from the metadata (:func:`chunks_are_checksummed`),
    or, for zstd in Zarr v2, from each chunk's frame header (its
    Content_Checksum_flag), read here as the files are checked: a store of an
    older volwarp (0.4 without checksums) answers False.
    """
    import itertools

    frames = (getattr(arr.metadata, "zarr_format", 3) == 2
              and getattr(arr.metadata.compressor, "codec_id", None) == "zstd"
              and not chunks_are_checksummed(arr))
    if not complete and not frames:
        return chunks_are_checksummed(arr)
    block = arr.shards or arr.chunks
    grid = [range(math.ceil(n / b)) for n, b in zip(arr.shape, block, strict=True)]
    md = arr.metadata
    checked = True
    for coords in itertools.product(*grid):
        key = md.encode_chunk_key(coords)
        if not frames:
            try:
                size = (array_path / key).stat().st_size
            except OSError:
                size = None
            if size is None or not (array_path / key).is_file():
                raise FormatError(f"{where}: chunk {key!r} of level 0 is missing (the store is "
                                  "incomplete or damaged)")
            if size == 0:  # (zarr reads an empty shard as missing: the fill value, silently)
                raise FormatError(f"{where}: chunk data is damaged (chunk {key!r} of level 0 "
                                  "is an empty file)")
            continue
        try:
            with open(array_path / key, "rb") as fh:
                head = fh.read(5)
        except FileNotFoundError:
            if complete:
                raise FormatError(f"{where}: chunk {key!r} of level 0 is missing (the store "
                                  "is incomplete or damaged)") from None
            continue
        except OSError as exc:
            raise FormatError(f"{where}: cannot read chunk {key!r} ({exc.strerror})") from None
        if len(head) < 5 or head[:4] != _ZSTD_MAGIC:
            raise FormatError(f"{where}: chunk data is damaged (chunk {key!r} of level 0 is "
                              "not a zstd frame)")
        checked = checked and bool(head[4] & _ZSTD_CHECKSUM_FLAG)
    return checked if frames else chunks_are_checksummed(arr)


def _one_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__


def read_region(opened: Opened, region) -> np.ndarray:
    """Samples of the [z, y, x] ``region`` (a tuple of slices) of an opened store, native order."""
    sel, transpose = opened.index
    # the region in stored axis order
    stored = list(sel)
    space_positions = [i for i, s in enumerate(sel) if isinstance(s, slice)]
    for out_axis, src in enumerate(transpose):
        stored[space_positions[src]] = region[out_axis]
    try:
        block = _read_by_chunk_rows(opened.array, stored, space_positions)
    except Exception as exc:  # a damaged chunk: checksums, zstd, shard index
        if opened.changed():  # (the opening's shard index, another store's shard)
            from .mapped import folder_changed

            raise folder_changed(opened.where) from None
        raise FormatError(f"{opened.where}: chunk data is damaged ({type(exc).__name__}: "
                          f"{_one_line(exc)})") from None
    return native(block.transpose(transpose)) if transpose != [0, 1, 2] else native(block)


#: decoded chunk bytes a row of :func:`_read_by_chunk_rows` takes at most (one chunk more)
ROW_BYTES = 4 << 20


def _read_by_chunk_rows(arr, stored: list, space_positions: list) -> np.ndarray:
    """``arr[stored]``, read a row of chunks at a time into the result.

    Read at once, a region decodes every chunk it touches and zarr holds them
    all beside the result: 8 planes (2 MiB) of a 256^3 store of 64^3 chunks took
    27 MiB, which no block's weighing counted (a review measured runs 25-60% over
    their memory limit from OME-Zarr inputs). A row of chunks (one chunk deep on
    the two slowest space axes, whole along the fastest) holds a few chunks.
    """
    slow = space_positions[:2]
    # (rows of several chunks where chunks are thin, up to ROW_BYTES of decoded chunks: a
    # store of single planes read a plane at a time took twice as long)
    fast = 1
    for axis in space_positions[2:]:
        start, stop, _ = stored[axis].indices(arr.shape[axis])
        c = int(arr.chunks[axis])
        fast *= (-(-stop // c) - start // c) * c
    item = arr.dtype.itemsize
    bounds = {axis: stored[axis].indices(arr.shape[axis])[:2] for axis in slow}
    c0, c1 = (int(arr.chunks[axis]) for axis in slow)
    start1, stop1 = bounds[slow[1]]
    hull1 = (-(-stop1 // c1) - start1 // c1) * c1  # (the chunks the region spans on a1)
    step1 = min(hull1, c1 * max(1, ROW_BYTES // max(1, c0 * c1 * fast * item)))
    step0 = c0 * max(1, ROW_BYTES // max(1, c0 * step1 * fast * item))
    spans = {}
    for axis, c, step in ((slow[0], c0, step0), (slow[1], c1, step1)):
        start, stop = bounds[axis]
        edges = [start, *range((start // c) * c + step, stop, step), stop] \
            if stop > start else []
        spans[axis] = list(zip(edges[:-1], edges[1:], strict=True))
    if all(len(v) <= 1 for v in spans.values()):
        return np.asarray(arr[tuple(stored)])  # (one row already)
    shape = [len(range(*s.indices(n))) for s, n in zip(stored, arr.shape, strict=True)
             if isinstance(s, slice)]
    out = np.empty(shape, dtype=arr.dtype)
    kept = [i for i, s in enumerate(stored) if isinstance(s, slice)]  # (result's axes)
    a0, a1 = slow
    for lo0, hi0 in spans[a0]:
        for lo1, hi1 in spans[a1]:
            piece = list(stored)
            piece[a0], piece[a1] = slice(lo0, hi0), slice(lo1, hi1)
            dst = [slice(None)] * len(shape)
            start0 = stored[a0].indices(arr.shape[a0])[0]
            start1 = stored[a1].indices(arr.shape[a1])[0]
            dst[kept.index(a0)] = slice(lo0 - start0, hi0 - start0)
            dst[kept.index(a1)] = slice(lo1 - start1, hi1 - start1)
            out[tuple(dst)] = arr[tuple(piece)]
    return out


#: What a whole read holds beside the samples: a row of chunks (:data:`ROW_BYTES`) decoded on
#: zarr's threads with their compressed bytes, and the codecs' libraries loaded on the first
#: decode: 11-12 MiB measured (256^3 float32 of 64^3 zstd chunks), with its freed chunks given
#: back as they are freed (:func:`~volwarp_cli.memory.large_allocations_mapped`: else glibc's
#: arenas of zarr's threads kept 25 MiB more, to the process's peak)
READ_BYTES = 16 << 20


def read_omezarr(path: str | os.PathLike, volume_index: int | None = None) -> Volume:
    """Read level 0 of the OME-Zarr store at ``path`` (module notes)."""
    from ..memory import ensure_fits_in_memory, large_allocations_mapped

    opened = open_omezarr(path, volume_index)
    shape = opened.view_shape
    ensure_fits_in_memory(int(np.prod(shape, dtype=np.int64)) * opened.array.dtype.itemsize
                          + READ_BYTES, f"{opened.where} ({'x'.join(map(str, zyx_to_xyz(shape)))})")
    with large_allocations_mapped():  # (zarr's decoding threads' freed chunks given back)
        data = read_region(opened, tuple(slice(0, n) for n in shape))
    from .mapped import folder_changed, watch_folder

    if opened.changed():  # (read row by row, by path: the last rows another store's)
        raise folder_changed(opened.where)
    # (and watched to the end of a run, as a store read by box is: a worker process given
    # the input reopens it by path, and read another store swapped in, exit 0)
    watch_folder(*opened.identity, opened.where)
    return make_volume(opened.where, data, spacing=opened.spacing, origin=opened.origin,
                       direction=opened.direction, space=opened.space,
                       file_space=opened.file_space, meta=opened.meta)


class LazyOmeZarr:
    """The level 0 of a store as a read-only array: ``[z0:z1, y0:y1, x0:x1]`` reads only that."""

    def __init__(self, opened: Opened):
        from .mapped import watch_folder

        self._opened = opened
        # (its chunks are read by path as the work goes: another store swapped in meanwhile
        # gave a mix; no output is renamed into place then)
        watch_folder(*opened.identity, opened.where)
        self.shape = tuple(opened.view_shape)
        self.dtype = native(np.zeros(0, dtype=opened.array.dtype)).dtype
        self.ndim = 3
        # one sample read now: zarr's reading machinery (its event loop, thread pool and
        # codecs, some 20-30 MiB) is loaded before a run weighs its blocks against what
        # the budget leaves, not inside the first block (runs went past their limit)
        if all(self.shape):
            self[0:1, 0:1, 0:1]

    def __getitem__(self, key):
        from .filearray import box_of_key

        box, pick = box_of_key(key, self.shape)
        return read_region(self._opened, tuple(slice(lo, hi) for lo, hi in box))[pick]

    def __array__(self, dtype=None, copy=None):
        out = self[:, :, :]
        return out if dtype is None else out.astype(dtype)
