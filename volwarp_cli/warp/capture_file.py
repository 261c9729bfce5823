r"""The ``.vwc`` capture file: a captured domain voxmap and its set-up, versioned.

Layout (all integers little-endian)::

    offset 0   16 bytes  magic  b"VOLWARP-CAPTURE\n"
    offset 16  uint32    format version (currently 3; 1 and 2 are read too)
    offset 20  uint32    n, the length of the JSON header
    offset 24  n bytes   JSON header (UTF-8, sorted keys, no timestamps)
    offset 24+n          payload: the domain voxmap, C order [z, y, x],
                         little-endian float32 or float64

The header holds ``format`` ("vwc"), ``version``, ``input`` (shape x y z,
dtype, spacing, origin, direction, space, meta, min, max, mean of the captured
volume, and ``border``, the median of its faces: the warp's default
background), ``capture`` (lattice, placement, oversample, sampling, pad,
granularity, subdivision, domain_shape), ``payload`` (dtype, shape x y z,
nbytes, crc32) and ``header_crc32`` (of the other fields). Loading checks the
magic (a foreign file), the version, the file size (a truncated file), the
header's CRC-32 (an edited or damaged header: an origin, an input shape) and
the payload's (a corrupted one); each failure is a
:class:`~volwarp_cli.errors.FormatError` naming the file.
Identical captures give byte-identical files.

Version 3 (volwarp 0.1.8) records the input's border value and requires the
header's checksum (an edit that deleted it too was read as a file from
before it). Version 2 files may have neither: their border value is taken
from the stored domain. Version 2 placed the domain on the input as an exact
subdivision of its voxels at an integer oversample (``subdivision`` k; see
:mod:`volwarp_cli.bspline.lattice`); version 1 files have the spanning grid
(the domain's box the input's), and are warped as they were captured.

It lives in ``warp/``, not ``io/``, because it stores a
:class:`~volwarp_cli.bspline.capture.Capture`, not a volume: reading one builds the
B-spline ``Lattice`` and ``Capture`` and checks their placement and sampling names, and
``io/`` imports nothing of the numeric core.
"""

from __future__ import annotations

import contextlib
import json
import os
import struct
import zlib
from pathlib import Path

import numpy as np

from ..bspline.capture import Capture, capture_border
from ..bspline.lattice import Lattice
from ..errors import FormatError
from ..io.atomic import atomic_output
from ..volume import Header, xyz_to_zyx

MAGIC = b"VOLWARP-CAPTURE\n"
VERSION = 3
#: Versions read: 1 has no ``subdivision`` (its grid spans the input); 2 may lack the
#: header's checksum and the input's border value; 3 has both, the checksum required.
READ_VERSIONS = (1, 2, 3)
_PREFIX = struct.Struct("<16sII")
#: the header's own CRC-32 (of its other fields, as :func:`_header_crc` writes them): an
#: edited or damaged header (an origin, an input shape) is refused, as a payload is.
#: Files written before it have none, and are read as they were.
HEADER_CRC = "header_crc32"


def _header_crc(fields: dict) -> int:
    """The CRC-32 of a header's fields but :data:`HEADER_CRC`, as sorted-key JSON."""
    rest = {k: v for k, v in fields.items() if k != HEADER_CRC}
    return zlib.crc32(json.dumps(rest, sort_keys=True).encode("utf-8"))


def _header(cap: Capture, payload: np.ndarray, crc: int) -> dict:
    g = cap.geometry
    return {
        "format": "vwc",
        "version": VERSION,
        "input": {
            "shape": list(cap.grid.input_shape),
            "dtype": cap.input_dtype.name,
            "spacing": [float(v) for v in g.spacing],
            "origin": [float(v) for v in g.origin],
            "direction": [[float(v) for v in row] for row in g.direction],
            "space": g.space,
            "meta": {str(k): str(v) for k, v in sorted(g.meta.items())},
            "min": cap.stats[0],
            "max": cap.stats[1],
            "mean": cap.stats[2],
            "border": None if cap.border is None else float(cap.border),
        },
        "capture": {
            "lattice": list(cap.grid.lattice),
            "placement": cap.placement,
            "oversample": cap.oversample,
            "sampling": cap.sampling,
            "pad": list(cap.pad) if cap.pad is not None else None,
            "granularity": list(cap.grid.granularity),
            "subdivision": cap.grid.subdivision,
            "domain_shape": list(cap.grid.domain_shape),
        },
        "payload": {
            "dtype": payload.dtype.name,
            "shape": list(cap.grid.domain_shape),
            "nbytes": int(payload.nbytes),
            "crc32": crc,
        },
    }


def write_capture(cap: Capture, path: str | os.PathLike) -> None:
    """Write ``cap`` to ``path`` atomically."""
    payload = np.ascontiguousarray(cap.domain, dtype=cap.domain.dtype.newbyteorder("<"))
    crc = zlib.crc32(memoryview(payload).cast("B"))
    fields = _header(cap, payload, crc)
    fields[HEADER_CRC] = _header_crc(fields)
    head = json.dumps(fields, sort_keys=True).encode("utf-8")
    with atomic_output(path) as tmp, open(tmp, "wb") as fh:
        fh.write(_PREFIX.pack(MAGIC, VERSION, len(head)))
        fh.write(head)
        fh.write(memoryview(payload).cast("B"))


def read_header(path: str | os.PathLike) -> tuple[dict, int]:
    """The checked JSON header of a capture file and the payload's byte offset."""
    from ..runscope import stop_if_dry_run

    stop_if_dry_run(path)  # (every capture reader starts here; volwarp batch's checks end)
    path = Path(path)
    try:
        size = path.stat().st_size
        with open(path, "rb") as fh:
            prefix = fh.read(_PREFIX.size)
            if len(prefix) < _PREFIX.size and MAGIC.startswith(prefix[:len(MAGIC)]):
                # (its start is a capture file's: cut short, not another kind of file)
                raise FormatError(f"{path}: truncated capture file ({len(prefix)} bytes; "
                                  f"its header alone takes {_PREFIX.size} or more)"
                                  if prefix else f"{path}: empty file, not a capture file")
            if len(prefix) < _PREFIX.size or not prefix.startswith(MAGIC):
                raise FormatError(f"{path}: not a volwarp capture file (file starts with "
                                  f"{prefix[:16]!r})")
            magic, version, n = _PREFIX.unpack(prefix)
            if version not in READ_VERSIONS:
                raise FormatError(f"{path}: capture file version {version} is not supported "
                                  f"(this volwarp reads versions "
                                  f"{', '.join(map(str, READ_VERSIONS))})")
            raw = fh.read(n)
    except FileNotFoundError:
        raise FormatError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise FormatError(f"{path}: is a folder, not a capture file") from None
    except OSError as exc:
        raise FormatError(f"{path}: cannot read ({exc.strerror})") from None
    if len(raw) < n:
        raise FormatError(f"{path}: capture file is truncated (header incomplete)")
    try:
        head = json.loads(raw.decode("utf-8"))
        payload = head["payload"]
        expected = _PREFIX.size + n + int(payload["nbytes"])
        shape = [int(v) for v in payload["shape"]]
        dtype = np.dtype(payload["dtype"])
        head["input"]["shape"], head["capture"]["lattice"]  # noqa: B018 - presence check
    except (ValueError, KeyError, TypeError) as exc:
        raise FormatError(f"{path}: capture file header is malformed ({exc})") from None
    if int(np.prod(shape)) * dtype.itemsize != int(payload["nbytes"]):
        raise FormatError(f"{path}: capture file header is inconsistent (payload size)")
    if version == 1:  # before subdivision grids
        head["capture"]["subdivision"] = 0
        _refuse_unconverted_frame(head, path)
    problem = _header_problem(head)
    if problem:
        raise FormatError(f"{path}: capture file header is malformed ({problem})")
    if version >= 3 and HEADER_CRC not in head:  # (an edit that took the checksum out too)
        raise FormatError(f"{path}: capture file is corrupt (its header checksum is missing: "
                          "edited or damaged; capture the input again)")
    if HEADER_CRC in head and head[HEADER_CRC] != _header_crc(head):  # (fields that pass)
        raise FormatError(f"{path}: capture file is corrupt (header checksum mismatch: edited "
                          "or damaged; capture the input again)")
    if size < expected:
        raise FormatError(f"{path}: capture file is truncated: expected {expected} bytes, "
                          f"found {size}")
    if size > expected:
        raise FormatError(f"{path}: capture file has {size - expected} unexpected trailing bytes")
    return head, _PREFIX.size + n


def _refuse_unconverted_frame(head: dict, path) -> None:
    """Refuse a version 1 file captured from a RAS or LAS input, rather than half convert it.

    Such a file holds the input's numbers in that frame (volwarp converted frames
    only later) and its key/values (a NRRD measurement frame) too.
    """
    from ..volume import LPS, SPACE_NAMES, frame_to_lps

    space = head.get("input", {}).get("space")
    try:
        to_lps = frame_to_lps(space)
    except Exception:  # an unknown name: the header check below reports it
        return
    if to_lps is not None and not np.array_equal(to_lps, np.eye(3)):
        name = SPACE_NAMES[str(space).lower()]
        raise FormatError(f"{path}: this capture file (version 1) keeps its input's "
                          f"{name} coordinates, from before volwarp's world frame was "
                          f"{LPS}; capture the input again")


def _header_problem(head: dict) -> str | None:
    """What is wrong with a header's fields (the JSON is not checksummed), or None."""
    from ..bspline.lattice import PLACEMENTS
    from ..bspline.pullback import SAMPLINGS
    from ..samples import SUPPORTED_DTYPES

    def ints(v, n, least):
        return (isinstance(v, list) and len(v) == n
                and all(isinstance(x, int) and not isinstance(x, bool) and x >= least
                        for x in v))

    def reals(v, n):
        return (isinstance(v, list) and len(v) == n
                and all(isinstance(x, (int, float)) and not isinstance(x, bool)
                        and np.isfinite(x) for x in v))

    try:
        inp, capd, pl = head["input"], head["capture"], head["payload"]
        checks = [
            (ints(inp["shape"], 3, 1), "input shape"),
            (inp["dtype"] in SUPPORTED_DTYPES, "input dtype"),
            (reals(inp["spacing"], 3) and min(inp["spacing"]) > 0, "input spacing"),
            (reals(inp["origin"], 3), "input origin"),
            (isinstance(inp["direction"], list) and len(inp["direction"]) == 3
             and all(reals(r, 3) for r in inp["direction"]), "input direction"),
            (reals([inp["min"], inp["max"]], 2) and inp["min"] <= inp["max"], "input range"),
            (inp["mean"] is None or reals([inp["mean"]], 1), "input mean"),
            (inp.get("border") is None or reals([inp["border"]], 1), "input border"),
            (ints(capd["lattice"], 3, 4), "lattice"),
            (ints(capd["granularity"], 3, 1), "granularity"),
            (isinstance(capd["subdivision"], int) and not isinstance(capd["subdivision"], bool)
             and 0 <= capd["subdivision"] <= 16
             and (capd["subdivision"] == 0 or (
                 capd["placement"] == "uniform" and ints(inp["shape"], 3, 1)
                 and ints(capd["granularity"], 3, 1) and ints(capd["lattice"], 3, 4)
                 and all(g * (c - 3) >= capd["subdivision"] * i for g, c, i in
                         zip(capd["granularity"], capd["lattice"], inp["shape"], strict=True)))),
             "subdivision"),
            (capd["placement"] in PLACEMENTS, "placement"),
            (capd["sampling"] in SAMPLINGS, "sampling"),
            (reals([capd["oversample"]], 1) and capd["oversample"] > 0, "oversample"),
            (capd["pad"] is None or ints(capd["pad"], 3, 0), "pad"),
            (pl["dtype"] in ("float32", "float64"), "payload dtype"),
            (capd["domain_shape"] == pl["shape"] == [
                g * (c - 3) for g, c in zip(capd["granularity"], capd["lattice"], strict=True)],
             "domain shape does not match the lattice"),
        ]
    except (KeyError, TypeError) as exc:
        return f"missing or wrong field {exc}"
    bad = [what for ok, what in checks if not ok]
    return ", ".join(bad) if bad else None


def read_capture(path: str | os.PathLike) -> Capture:
    """Load and check a capture file written by :func:`write_capture`."""
    head, offset = read_header(path)
    pl = head["payload"]
    dtype = np.dtype(pl["dtype"]).newbyteorder("<")
    shape = tuple(int(v) for v in pl["shape"])[::-1]
    from ..memory import ensure_fits_in_memory
    ensure_fits_in_memory(int(pl["nbytes"]), f"{path}: domain voxmap")
    with open(path, "rb") as fh:
        fh.seek(offset)
        buf = bytearray(int(pl["nbytes"]))
        got = fh.readinto(buf)
    if got != len(buf):
        raise FormatError(f"{path}: capture file is truncated")
    if zlib.crc32(buf) != int(pl["crc32"]):
        raise FormatError(f"{path}: capture file is corrupt (payload checksum mismatch)")
    domain = np.frombuffer(buf, dtype=dtype).reshape(shape)
    domain = domain.astype(dtype.newbyteorder("="), copy=False)
    return _capture_of(head, domain, path)


def _capture_of(head: dict, domain, path, sampler=None) -> Capture:
    """The :class:`~volwarp_cli.bspline.capture.Capture` a checked header describes, over ``domain`` or ``sampler``."""
    pl = head["payload"]
    try:
        inp = head["input"]
        capd = head["capture"]
        geometry = Header(xyz_to_zyx(inp["shape"]), np.dtype(inp["dtype"]),
                          spacing=inp["spacing"], origin=inp["origin"],
                          direction=inp["direction"], space=inp["space"], meta=inp["meta"])
        grid = Lattice(tuple(int(v) for v in inp["shape"]), tuple(int(v) for v in capd["lattice"]),
                    tuple(int(v) for v in capd["granularity"]), int(capd["subdivision"]))
        if grid.domain_shape != tuple(int(v) for v in pl["shape"]):
            raise ValueError("domain shape does not match the lattice")
        pad = capd["pad"]
        cap = Capture(domain, grid, capd["placement"], float(capd["oversample"]),
                      capd["sampling"], tuple(pad) if pad is not None else None, geometry,
                      np.dtype(inp["dtype"]), (inp["min"], inp["max"], inp["mean"]),
                      sampler)
    except (ValueError, KeyError, TypeError) as exc:
        raise FormatError(f"{path}: capture file header is malformed ({exc})") from None
    except Exception as exc:  # a Header check failing on bad geometry
        raise FormatError(f"{path}: capture file header is malformed ({exc})") from None
    # the warp's default background: the input's own border value, as the capture found it
    # (files before 0.1.8 have none: from the stored input, which on a spanning grid holds
    # only its faces interpolated, and gave another background than a warp of the input)
    border = head["input"].get("border")
    cap.border = float(border) if border is not None else capture_border(cap)
    return cap


class StoredDomain:
    """A capture file's domain voxmap, read box by box from the file (never held whole).

    The sampler of :func:`open_capture_lazy`'s deferred capture: the same
    interface as :class:`~volwarp_cli.bspline.pullback.BoxSampler` (``box``, ``input_box``,
    ``shape``, ``dtype``, ``source``), but each domain voxel is
    stored, not gathered. ``portable``: picklable as the file's path and
    offset, so a block task in another process reads the file itself.
    """

    portable = True

    def __init__(self, array):
        self.source = array  # a FileArray of the payload (z, y, x)
        self.shape = tuple(array.shape)
        self.dtype = np.dtype(array.dtype).newbyteorder("=")

    @property
    def stored(self):
        """The payload, sliceable ``[z, y, x]`` (read box by box; picklable)."""
        return self.source

    def input_box(self, box):
        """The stored voxels ``box`` reads: its own."""
        return box

    def box(self, box) -> np.ndarray:
        """The domain samples of ``box`` (a :class:`~volwarp_cli.box.Box`, z y x), contiguous."""
        if box.empty:
            return np.empty(box.shape, dtype=self.dtype)
        return np.ascontiguousarray(self.source[box.slices], dtype=self.dtype)


#: payload bytes the checksum pass reads at a time, into one buffer (64 MiB reads, uncharged,
#: took a warp of a 256^3 capture to 98 MiB under --memory-limit 64M: a hunt)
_CRC_CHUNK = 1 << 20


def _check_payload(path, payload: dict, offset: int) -> None:
    """Refuse a truncated or altered payload: its CRC-32 in one streamed pass (bounded memory)."""
    crc = 0
    buffer = memoryview(bytearray(_CRC_CHUNK))
    with open(path, "rb") as fh:
        fh.seek(offset)
        left = int(payload["nbytes"])
        while left:
            n = fh.readinto(buffer[:min(left, _CRC_CHUNK)])
            if not n:
                raise FormatError(f"{path}: capture file is truncated")
            crc = zlib.crc32(buffer[:n], crc)
            left -= n
    if crc != int(payload["crc32"]):
        raise FormatError(f"{path}: capture file is corrupt (payload checksum mismatch)")


def open_capture_lazy(path: str | os.PathLike) -> Capture:
    """A capture file as a deferred :class:`~volwarp_cli.bspline.capture.Capture`: its domain left in the file.

    The same checks as :func:`read_capture` (magic, version, header, size,
    and the payload's CRC-32, in one streamed pass of bounded memory); the
    capture's ``sampler`` is a :class:`StoredDomain` reading boxes of the
    payload, so a warp by blocks never holds the domain.
    """
    from ..io.filearray import FileArray
    from ..io.mapped import watch

    # (its identity before the header and the checksum's pass: the blocks' tasks reopen
    # it by its path, and a capture replaced meanwhile, `volwarp capture -o` over it, gave
    # a mix of the two files, exit 0; the outputs are now refused, as a mapped volume's)
    with contextlib.suppress(OSError):  # (a missing file: read_header says so)
        watch(path)
    head, offset = read_header(path)
    pl = head["payload"]
    _check_payload(path, pl, offset)
    dtype = np.dtype(pl["dtype"]).newbyteorder("<")
    shape = tuple(int(v) for v in pl["shape"])[::-1]
    sampler = StoredDomain(FileArray(path, dtype, offset, shape))
    return _capture_of(head, None, path, sampler=sampler)


def read_capture_lattice(path: str | os.PathLike) -> Capture:
    """A capture file's set-up without its samples (the header only; the payload not read).

    For what depends on the deformation alone (moved points and meshes, the
    fields): the capture's grid, placement and pad, a domain of its shape only
    (:class:`~volwarp_cli.bspline.capture.NoSamples`). The file's size is checked, not its payload's checksum.
    """
    from ..bspline.capture import NoSamples

    head, _ = read_header(path)
    shape = tuple(int(v) for v in head["payload"]["shape"])[::-1]
    return _capture_of(head, None, path, sampler=NoSamples(shape))


def describe_capture(path: str | os.PathLike) -> dict:
    """The ``volwarp info SCENE.vwc --json`` description.

    Keys: the volume keys of the captured input (format "vwc", shape, dtype,
    spacing, origin, direction, space, min, max, mean, meta), then
    ``version``, ``lattice``, ``lattice_points`` (world x, y, z of control
    point (i, j, k) at ``lattice_points[i][j][k]``), ``placement``,
    ``oversample``, ``sampling``, ``pad``, ``granularity``, ``subdivision``
    (domain voxels per input voxel, 0 for a spanning grid), ``domain_shape``
    and ``domain_dtype``. A truncated or altered payload is refused, as a warp
    refuses it (the checksum in one streamed pass).
    """
    head, offset = read_header(path)
    _check_payload(path, head["payload"], offset)
    inp = head["input"]
    capd = head["capture"]
    # (as read_capture builds it: a version 1 file's frame name normalised to LPS)
    geometry = Header(xyz_to_zyx(inp["shape"]), np.float64, spacing=inp["spacing"],
                      origin=inp["origin"], direction=inp["direction"], space=inp["space"])
    grid = Lattice(tuple(inp["shape"]), tuple(capd["lattice"]), tuple(capd["granularity"]),
                int(capd["subdivision"]))
    from ..bspline.lattice import capture_offsets
    pts = grid.uniform_positions() + capture_offsets(grid, capd["placement"])  # (k, j, i, 3)
    world = geometry.index_to_world(pts.reshape(-1, 3)).reshape(pts.shape)
    world = np.transpose(world, (2, 1, 0, 3))  # [i][j][k]
    world = np.round(world, 9) + 0.0

    def num(v):
        return int(v) if np.dtype(inp["dtype"]).kind in "iu" else float(v)

    return {
        "format": "vwc",
        "shape": inp["shape"],
        "dtype": inp["dtype"],
        "spacing": inp["spacing"],
        "origin": inp["origin"],
        "direction": inp["direction"],
        "space": geometry.space,
        "min": num(inp["min"]),
        "max": num(inp["max"]),
        "mean": inp["mean"],
        "meta": inp["meta"],
        "version": head["version"],
        "lattice": capd["lattice"],
        "placement": capd["placement"],
        "oversample": capd["oversample"],
        "sampling": capd["sampling"],
        "pad": capd["pad"],
        "granularity": capd["granularity"],
        "subdivision": capd["subdivision"],
        "domain_shape": capd["domain_shape"],
        "domain_dtype": head["payload"]["dtype"],
        "lattice_points": world.tolist(),
    }
