"""Mesh files: PLY, STL, OBJ, VTP and legacy VTK, written atomically.

The format is chosen by the output's extension. Binary encodings are used
where the format has one (PLY binary little-endian, binary STL, VTP with raw
appended data, legacy VTK BINARY); OBJ is text by definition. Coordinates
and normals are stored as 32-bit floats, vertex indices as 32-bit integers
(64-bit in VTP). The writers are written here rather than taken from VTK so
that the bytes depend only on the mesh: no timestamps, version strings or
library-dependent layout, and the same mesh always gives the same file.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..errors import VolwarpError
from ..io.atomic import atomic_output, check_output_path
from .mesh import Mesh

#: extension -> format name
MESH_EXTENSIONS = {".ply": "ply", ".stl": "stl", ".obj": "obj", ".vtp": "vtp", ".vtk": "vtk"}

_INT32_MAX = np.iinfo(np.int32).max


def mesh_format(path: str | os.PathLike) -> str:
    """The mesh format of ``path`` by its extension, or raise listing the known ones."""
    ext = Path(path).suffix.lower()
    fmt = MESH_EXTENSIONS.get(ext)
    if fmt is None:
        known = " ".join(MESH_EXTENSIONS)
        shown = ext or "(none)"
        raise VolwarpError(f"{path}: unknown mesh extension {shown} (known: {known})")
    return fmt


def check_mesh_output(path: str | os.PathLike, option: str | None = None) -> str:
    """Fail early for an unknown extension or an unwritable place; return the format.

    ``option``: the output's option, for :func:`~volwarp_cli.io.atomic.check_output_path`.
    """
    fmt = mesh_format(path)
    check_output_path(path, option=option)
    return fmt


def write_mesh(mesh: Mesh, path: str | os.PathLike,
               comments: dict[str, str] | None = None) -> None:
    """Write ``mesh`` to ``path`` atomically, in the format its extension names.

    Normals are written when the mesh has them (PLY, OBJ, VTP, VTK); STL
    always stores each facet's normal computed from its winding.
    ``comments`` (provenance key/values) go where the format has room for
    text: ``comment key=value`` header lines in PLY, ``# key=value`` in OBJ,
    an XML comment in VTP; STL's 80-byte header and legacy VTK's title line
    are too small and keep their fixed text. PLY, OBJ, STL and VTK files say
    ``SPACE=LPS`` where 3D Slicer looks for it (:data:`SPACE_MARK`), and the
    comments say no other ``SPACE=`` (:func:`_no_space_mark`).
    """
    fmt = check_mesh_output(path)
    notes = [_no_space_mark(f"{k}={_one_line(v)}") for k, v in sorted((comments or {}).items())]
    writer = {"ply": _write_ply, "stl": _write_stl, "obj": _write_obj,
              "vtp": _write_vtp, "vtk": _write_vtk}[fmt]
    if mesh.n_vertices > _INT32_MAX:
        raise VolwarpError(f"{path}: {mesh.n_vertices} vertices are more than the "
                           f"{fmt.upper()} writer's 32-bit indices can address")
    _say_float32_rounding(mesh, path)
    with atomic_output(path) as tmp, open(tmp, "wb") as fh:
        if fmt in ("ply", "obj", "vtp"):
            writer(mesh, fh, notes)
        else:
            writer(mesh, fh)


#: rounding of the vertices to float32 said when its step reaches this share of an edge
FLOAT32_SAID = 0.01


def _say_float32_rounding(mesh: Mesh, path) -> None:
    """Say when float32 vertices (every format's) round a mesh far from the origin coarsely.

    A mesh of a volume whose origin lies 1e5 mm out kept a 0.01 mm voxel's ball in 24
    distinct x values of 290 (0.39 voxel off), its volume 0.7% smaller than the
    reported one, without a word. Said where float32's step at the farthest vertex
    reaches 1% of the mesh's median edge (a one-voxel label of a CT 1.25 m out is
    rounded by 0.02% of its edge: nothing said); measured on a subsample of faces.
    """
    if len(mesh.faces) == 0:
        return
    v = mesh.vertices
    faces = mesh.faces[::max(1, len(mesh.faces) // 20000)]
    edge = float(np.median(np.linalg.norm(v[faces[:, 1]] - v[faces[:, 0]], axis=1)))
    far = float(np.max(np.abs(v[faces.ravel()])))
    step = float(np.spacing(np.float32(far)))  # (float32's spacing there: rounding <= half)
    if edge > 0 and step > FLOAT32_SAID * edge:
        from ..progress import log

        log.warning("warning: %s: the vertices are stored as float32, whose steps %g mm from "
                    "the origin are %.2g mm, %.2g%% of the mesh's median edge (%.2g mm): its "
                    "shape is rounded (it lies far from the origin)", path, far, step,
                    100 * step / edge, edge)


#: The frame mark 3D Slicer writes and reads in mesh files (since 4.11: a comment of PLY
#: and OBJ, the header of STL and legacy VTK; a file without one is taken for LPS).
SPACE_MARK = "SPACE=LPS"


def _one_line(value) -> str:
    return " ".join(str(value).split())


def _no_space_mark(note: str) -> str:
    r"""``note`` with each ``SPACE=`` written ``SPACE\x3d``: no frame mark but volwarp's own.

    Slicer searches an OBJ's whole comment block for ``SPACE=RAS`` before
    ``SPACE=LPS`` (and takes a PLY's first comment holding either): an input
    named ``x_SPACE=RAS.nrrd`` in the provenance made it mirror the mesh.
    """
    return note.replace("SPACE=", "SPACE\\x3d")


def _xml_comment_text(text: str) -> str:
    """``text`` as an XML comment may hold it: control characters escaped, no "--".

    A control character of a file name made the VTP unreadable (VTK: "not
    well-formed"), written with exit 0. (Undecodable bytes, kept as surrogates,
    are escaped where the text is encoded, as in every format's comments.)
    """
    import re

    text = re.sub("[\x00-\x08\x0b\x0c\x0e-\x1f\ufffe\uffff]",
                  lambda m: f"\\u{ord(m.group()):04x}", text)
    return re.sub("-(?=-)", "- ", text)  # ("--" may not appear in a comment)


def _f32(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype="<f4")


#: rows converted per block: big meshes are written through one reused buffer
#: instead of a second full-size copy (fresh memory is slow to touch)
_BLOCK = 1 << 20


def _write_blocks(fh, n: int, dtype, fill) -> None:
    """Write ``n`` records of ``dtype`` in blocks; ``fill(buf, start, stop)`` fills a block."""
    buf = np.empty(min(n, _BLOCK), dtype=dtype)
    for start in range(0, n, _BLOCK):
        stop = min(start + _BLOCK, n)
        view = buf[:stop - start]
        fill(view, start, stop)
        fh.write(memoryview(view).cast("B"))


# -- PLY ---------------------------------------------------------------------
def _write_ply(mesh: Mesh, fh, notes: list[str]) -> None:
    has_n = mesh.normals is not None
    header = ["ply", "format binary_little_endian 1.0", "comment written by volwarp",
              f"comment {SPACE_MARK}", *(f"comment {n}" for n in notes),
              f"element vertex {mesh.n_vertices}",
              "property float x", "property float y", "property float z"]
    if has_n:
        header += ["property float nx", "property float ny", "property float nz"]
    header += [f"element face {mesh.n_faces}", "property list uchar int vertex_indices",
               "end_header"]
    # (a PLY header is ASCII, as plyfile reads it: a comment's other characters, a file
    # name's "ä", are written as Python's escapes, "\\xe4", never a failed write)
    fh.write(("\n".join(header) + "\n").encode("ascii", "backslashreplace"))

    def vertices(buf, a, b):
        buf[:, :3] = mesh.vertices[a:b]
        if has_n:
            buf[:, 3:] = mesh.normals[a:b]

    _write_blocks(fh, mesh.n_vertices, np.dtype(("<f4", (6 if has_n else 3,))), vertices)

    def faces(buf, a, b):
        buf["n"] = 3
        buf["v"] = mesh.faces[a:b]

    _write_blocks(fh, mesh.n_faces, np.dtype([("n", "u1"), ("v", "<i4", (3,))]), faces)


# -- STL ---------------------------------------------------------------------
def _write_stl(mesh: Mesh, fh) -> None:
    # The 80-byte header must not start with "solid" (readers take that for ASCII STL).
    head = f"binary STL written by volwarp; {SPACE_MARK}; units of the volume's world frame"
    head = head.encode("ascii")
    fh.write(head.ljust(80, b" "))
    fh.write(np.uint32(mesh.n_faces).astype("<u4").tobytes())

    def facets(buf, a, b):
        f = mesh.faces[a:b]
        corners = mesh.vertices[f]  # (k, 3, 3) float64
        n = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        length = np.linalg.norm(n, axis=1, keepdims=True)
        np.divide(n, length, out=n, where=length > 0)
        buf["n"] = n
        buf["v"] = corners
        buf["attr"] = 0

    _write_blocks(fh, mesh.n_faces, np.dtype([("n", "<f4", (3,)), ("v", "<f4", (3, 3)),
                                             ("attr", "<u2")]), facets)


# -- OBJ ---------------------------------------------------------------------
def _text_rows(prefix: str, values: np.ndarray, fmt: str, chunk: int = 200_000):
    """Yield encoded text lines ``prefix v0 v1 v2`` for rows of ``values``, in chunks."""
    line = f"{prefix} {fmt} {fmt} {fmt}\n"
    for start in range(0, len(values), chunk):
        block = values[start:start + chunk]
        yield ((line * len(block)) % tuple(block.ravel().tolist())).encode("ascii")


def _write_obj(mesh: Mesh, fh, notes: list[str]) -> None:
    fh.write(f"# written by volwarp\n# {SPACE_MARK}\n".encode("ascii"))
    for n in notes:
        fh.write(f"# {n}\n".encode("utf-8", "backslashreplace"))  # (a name not UTF-8: escaped)
    fh.write(f"# {mesh.n_vertices} vertices, {mesh.n_faces} triangles\n".encode("ascii"))
    # %.9g keeps a float32 exactly; coordinates are rounded to float32 first
    # so that every format stores the same numbers.
    for part in _text_rows("v", mesh.vertices.astype(np.float32).astype(np.float64), "%.9g"):
        fh.write(part)
    if mesh.normals is not None:
        for part in _text_rows("vn", mesh.normals.astype(np.float64), "%.7g"):
            fh.write(part)
        f1 = mesh.faces + 1
        line = "f %d//%d %d//%d %d//%d\n"
        for start in range(0, len(f1), 200_000):
            block = f1[start:start + 200_000]
            pairs = np.repeat(block, 2, axis=1)
            fh.write(((line * len(block)) % tuple(pairs.ravel().tolist())).encode("ascii"))
    else:
        for part in _text_rows("f", mesh.faces + 1, "%d"):
            fh.write(part)


# -- VTP (VTK XML PolyData, raw appended binary) -----------------------------
def _write_vtp(mesh: Mesh, fh, notes: list[str]) -> None:
    nv, nf = mesh.n_vertices, mesh.n_faces
    f3 = np.dtype(("<f4", (3,)))

    def floats(values):
        return lambda: _write_blocks(
            fh, nv, f3, lambda buf, a, b: buf.__setitem__(slice(None), values[a:b]))

    def connectivity():
        _write_blocks(fh, nf, np.dtype(("<i8", (3,))),
                      lambda buf, a, b: buf.__setitem__(slice(None), mesh.faces[a:b]))

    def offsets():
        _write_blocks(fh, nf, np.dtype("<i8"),
                      lambda buf, a, b: np.multiply(np.arange(a + 1, b + 1), 3, out=buf))

    # (section, DataArray attributes, bytes, writer)
    arrays = []
    if mesh.normals is not None:
        arrays.append(("PointData", 'type="Float32" Name="Normals" NumberOfComponents="3"',
                       12 * nv, floats(mesh.normals)))
    arrays.append(("Points", 'type="Float32" Name="Points" NumberOfComponents="3"',
                   12 * nv, floats(mesh.vertices)))
    arrays.append(("Polys", 'type="Int64" Name="connectivity"', 24 * nf, connectivity))
    arrays.append(("Polys", 'type="Int64" Name="offsets"', 8 * nf, offsets))
    offset = 0
    sections: dict[str, list[str]] = {"PointData": [], "Points": [], "Polys": []}
    for section, attrs, nbytes, _ in arrays:
        sections[section].append(f'        <DataArray {attrs} format="appended" '
                                 f'offset="{offset}"/>')
        offset += 8 + nbytes
    point_data = ('      <PointData Normals="Normals">\n' + "\n".join(sections["PointData"])
                  + "\n      </PointData>\n") if sections["PointData"] else ""
    comment = "".join(f"<!-- {_xml_comment_text(n)} -->\n" for n in notes)
    xml = (
        '<?xml version="1.0"?>\n' + comment +
        '<VTKFile type="PolyData" version="1.0" byte_order="LittleEndian" '
        'header_type="UInt64">\n'
        "  <PolyData>\n"
        f'    <Piece NumberOfPoints="{nv}" NumberOfVerts="0" '
        f'NumberOfLines="0" NumberOfStrips="0" NumberOfPolys="{nf}">\n'
        f"{point_data}"
        "      <Points>\n" + "\n".join(sections["Points"]) + "\n      </Points>\n"
        "      <Polys>\n" + "\n".join(sections["Polys"]) + "\n      </Polys>\n"
        "    </Piece>\n"
        "  </PolyData>\n"
        '  <AppendedData encoding="raw">\n   _'
    )
    fh.write(xml.encode("utf-8", "backslashreplace"))  # (UTF-8: a comment names "ä")
    for _, _, nbytes, write in arrays:
        fh.write(np.uint64(nbytes).astype("<u8").tobytes())
        write()
    fh.write(b"\n  </AppendedData>\n</VTKFile>\n")


# -- legacy VTK ------------------------------------------------------------------
def _write_vtk(mesh: Mesh, fh) -> None:
    """Legacy VTK, sections laid out as vtkPolyDataWriter (file version 4.2) lays them out.

    As that writer does, an empty section is left out: vtkPolyDataReader
    reports ``POLYGONS 0 0`` as an error ("Error reading polygons").
    """
    fh.write(f"# vtk DataFile Version 4.2\nvolwarp mesh {SPACE_MARK}\nBINARY\n"
             "DATASET POLYDATA\n".encode("ascii"))
    fh.write(f"POINTS {mesh.n_vertices} float\n".encode("ascii"))
    _write_blocks(fh, mesh.n_vertices, np.dtype((">f4", (3,))),
                  lambda buf, a, b: buf.__setitem__(slice(None), mesh.vertices[a:b]))
    fh.write(b"\n")
    if mesh.n_faces:
        fh.write(f"POLYGONS {mesh.n_faces} {4 * mesh.n_faces}\n".encode("ascii"))

        def cells(buf, a, b):
            buf[:, 0] = 3
            buf[:, 1:] = mesh.faces[a:b]

        _write_blocks(fh, mesh.n_faces, np.dtype((">i4", (4,))), cells)
        fh.write(b"\n")
    if mesh.normals is not None and mesh.n_vertices:
        fh.write(f"POINT_DATA {mesh.n_vertices}\nNORMALS Normals float\n".encode("ascii"))
        _write_blocks(fh, mesh.n_vertices, np.dtype((">f4", (3,))),
                      lambda buf, a, b: buf.__setitem__(slice(None), mesh.normals[a:b]))
        fh.write(b"\n")


# -- reading -----------------------------------------------------------------

_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2",
              "int16": "i2", "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4",
              "uint": "u4", "uint32": "u4", "float": "f4", "float32": "f4",
              "double": "f8", "float64": "f8"}


def read_mesh(path: str | os.PathLike) -> Mesh:
    """Read a triangle mesh from a PLY file (what ``volwarp mesh -o X.ply`` writes).

    Binary (either byte order) and ASCII PLY; vertex ``x y z`` and, when
    present, ``nx ny nz``; faces from their ``vertex_indices`` list, which
    must hold triangles. Other elements and properties (colours, texture
    coordinates, edges) are read past and dropped. Other formats are
    refused: read them with a mesh library (meshio, trimesh). A file 3D
    Slicer wrote in its RAS frame (a ``SPACE=RAS`` comment) is brought to
    LPS, as Slicer reads it (x and y negated); one without a mark is LPS.
    """
    path = Path(path)
    if path.suffix.lower() != ".ply":
        raise VolwarpError(f"{path}: volwarp reads meshes from PLY files only")
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise VolwarpError(f"{path}: cannot read ({exc.strerror})") from None
    header, body_at = _ply_header_lines(data)
    if header is None:
        raise VolwarpError(f"{path}: not a PLY file (no 'ply ... end_header' header)")
    fmt, elements = None, []  # elements: [name, count, [(prop, type, list_count_type | None)]]
    ras = None  # (Slicer's rule: the first comment that names a frame)
    for line in header[1:]:
        words = line.split()
        if words and words[0] == "comment" and ras is None:
            ras = True if "SPACE=RAS" in line else False if "SPACE=LPS" in line else None
        if not words or words[0] in ("comment", "obj_info"):
            continue
        try:
            if words[0] == "format":
                fmt = words[1]
            elif words[0] == "element":
                elements.append([words[1], int(words[2]), []])
                if elements[-1][1] < 0:
                    raise ValueError
            elif words[0] == "property" and words[1] == "list":
                elements[-1][2].append((words[4], _PLY_TYPES[words[3]],
                                        _PLY_TYPES[words[2]]))
            elif words[0] == "property":
                elements[-1][2].append((words[2], _PLY_TYPES[words[1]], None))
        except (IndexError, KeyError, ValueError):
            raise VolwarpError(f"{path}: bad PLY header line {line!r}") from None
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise VolwarpError(f"{path}: unknown PLY format {fmt!r}")
    try:
        parsed, left = _ply_elements(data[body_at:], fmt, elements)
    except (ValueError, IndexError) as exc:
        raise VolwarpError(f"{path}: the PLY data is truncated or does not match its "
                           f"header ({exc})") from None
    if left:  # (VTK's reader and plyfile drop it too: said, as it may be a header's mistake)
        from ..progress import log

        log.warning("warning: %s: %s after the elements its PLY header declares, ignored (a "
                    "header that counts too few?)", path, left)
    _say_ascii_cut(path, fmt, data[body_at:])
    vert = parsed.get("vertex")
    if vert is None or "face" not in parsed:
        raise VolwarpError(f"{path}: a PLY mesh needs vertex and face elements")
    try:
        vertices = np.stack([vert[k] for k in ("x", "y", "z")], axis=1).astype(np.float64)
    except KeyError:
        raise VolwarpError(f"{path}: vertices have no x, y, z") from None
    normals = None
    if all(k in vert for k in ("nx", "ny", "nz")):
        normals = np.stack([vert[k] for k in ("nx", "ny", "nz")], axis=1).astype(np.float32)
    face = parsed["face"]
    faces = face.get("vertex_indices", face.get("vertex_index"))
    if faces is None:
        raise VolwarpError(f"{path}: faces have no vertex_indices list")
    if len(faces) == 0:  # (an empty mesh, as --allow-empty and morph's empty frames write)
        faces = np.zeros((0, 3), np.int64)
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise VolwarpError(f"{path}: faces that are not triangles (volwarp reads triangle "
                           "meshes)")
    if faces.dtype.kind == "f" and not np.array_equal(faces, np.trunc(faces)):
        raise VolwarpError(f"{path}: face indices that are not whole numbers")  # (were cut)
    faces = faces.astype(np.int64)
    if faces.size and (faces.min() < 0 or faces.max() >= len(vertices)):
        raise VolwarpError(f"{path}: face indices outside the {len(vertices)} vertices")
    _check_finite_vertices(vertices, faces, path)
    _say_dropped(path, elements)
    if ras:  # (a half turn about z: the winding, and so the outside, stays)
        vertices[:, :2] *= -1
        if normals is not None:
            normals[:, :2] *= -1
    return Mesh(vertices, faces, normals)


#: what :func:`read_mesh` reads of each element; anything else is dropped, and said
_READ_PROPERTIES = {"vertex": {"x", "y", "z", "nx", "ny", "nz"},
                    "face": {"vertex_indices", "vertex_index"}}


def _say_dropped(path, elements) -> None:
    """Say the PLY's elements and properties the mesh read does not carry (colours, labels).

    They went without a word: a mesh moved by ``apply --mesh-in`` lost its vertex
    colours and face labels, exit 0.
    """
    dropped = [f"{name} {prop}" for name, count, props in elements if count
               for prop, _, _ in props if prop not in _READ_PROPERTIES.get(name, set())
               and name in _READ_PROPERTIES]
    dropped += [f"{count} {name}" for name, count, _ in elements
                if count and name not in _READ_PROPERTIES]
    if dropped:
        from ..progress import log

        log.warning("warning: %s: its %s %s not carried (volwarp reads a mesh's vertices, "
                    "normals and triangles; the output has none of the rest)", path,
                    ", ".join(dropped), "is" if len(dropped) == 1 else "are")


def _say_ascii_cut(path, fmt: str, body: bytes) -> None:
    """Say an ASCII PLY whose last value ends the file, without a line end after it.

    A file cut inside its last number read as a shorter number (a face's
    index 155 as 15), exit 0, without a word: every other cut runs out of
    values and is refused, but this one looks like a file without a final
    line end, which writers (VTK, meshio, trimesh, volwarp) all put.
    """
    end = body.rstrip(b"\x00\x1a")[-1:]
    if fmt == "ascii" and end and not end.isspace():
        from ..progress import log

        log.warning("warning: %s: the ASCII PLY ends inside a value, without a line end after "
                    "its last one: a file cut short there reads as a shorter number; check "
                    "that the file is whole", path)


def _check_finite_vertices(vertices, faces, path) -> None:
    """Refuse NaN or infinite vertices that faces use; say those no face uses.

    Moved, the used ones came out NaN without a word; the others go through
    as they are, as before.
    """
    from ..geometry import PLACEMENT_LIMIT

    used = np.zeros(len(vertices), bool)
    used[faces.ravel()] = True
    far = np.flatnonzero(used & (np.abs(np.where(np.isfinite(vertices), vertices, 0)) >
                                 PLACEMENT_LIMIT).any(axis=1))
    if far.size:  # (float32 outputs: 1e39 became inf, a file volwarp then refused to read)
        have = "vertex of its faces is" if far.size == 1 else "vertices of its faces are"
        raise VolwarpError(f"{path}: {far.size} {have} beyond {PLACEMENT_LIMIT:g} in magnitude "
                           f"(the first: vertex {far[0]}), volwarp's bound on placements: its "
                           "float32 mesh outputs would round them by 1e8 or more, or overflow")
    bad = ~np.isfinite(vertices).all(axis=1)
    if not bad.any():
        return
    in_faces = np.flatnonzero(bad & used)
    if in_faces.size:
        have = "vertex of its faces has" if in_faces.size == 1 else "vertices of its faces have"
        raise VolwarpError(f"{path}: {in_faces.size} {have} NaN or infinite coordinates (the "
                           f"first: vertex {in_faces[0]}); remove or mend them first")
    from ..progress import log

    count = int(bad.sum())
    log.warning("warning: %s: %d vert%s that no face uses %s NaN or infinite coordinates "
                "(kept as they are)", path, count, "ex" if count == 1 else "ices",
                "has" if count == 1 else "have")


def _ply_header_lines(data: bytes):
    """The header's lines and the body's offset, or (None, 0) when there is none."""
    if not data.startswith(b"ply"):
        return None, 0
    lines, at = [], 0
    while at < len(data) and len(lines) < 10000:
        nl = data.find(b"\n", at)
        end = len(data) if nl < 0 else nl + 1
        line = data[at:end].decode("ascii", "replace").strip()
        lines.append(line)
        at = end
        if line == "end_header":
            return lines, at
    return None, 0


#: what may follow a PLY's last element unsaid: blanks, NUL padding, an old DOS end (Ctrl-Z)
_PADDING = b" \t\r\n\x00\x1a"


def _ply_elements(body: bytes, fmt: str, elements) -> tuple[dict[str, dict[str, np.ndarray]],
                                                              str | None]:
    """Each element's properties as arrays, and what follows them (None: nothing but blanks).

    Lists as (N, k) arrays when every record has k items, else as a 1-D object
    array of rows (the caller refuses faces that are not triangles). What
    follows: "N bytes" (binary) or "N values" (ASCII) past the last element.
    """
    if fmt == "ascii":
        out, extra = _ply_ascii(body, elements)
        return out, (f"{len(extra)} value{'s' if len(extra) != 1 else ''}"
                     if b"".join(extra).strip(_PADDING) else None)
    order = "<" if fmt == "binary_little_endian" else ">"
    out, at = {}, 0
    for name, count, props in elements:
        if all(lt is None for _, _, lt in props):
            dt = np.dtype([(p, order + t) for p, t, _ in props])
            need = count * dt.itemsize
            if at + need > len(body):
                raise ValueError(f"element {name!r} needs {need} bytes")
            arr = np.frombuffer(body, dtype=dt, count=count, offset=at)
            at += need
            out[name] = {p: arr[p] for p, _, _ in props}
            continue
        cols, at = _ply_binary_lists(body, at, order, count, props, name)
        out[name] = cols
    rest = len(body) - at
    return out, (f"{rest} byte{'s' if rest != 1 else ''}" if body[at:].strip(_PADDING)
                 else None)


def _ply_binary_lists(body, at, order, count, props, name):
    """Records of an element with list properties, from offset ``at``.

    Fast path: every list has the length of the first record's (one
    structured read); otherwise record by record.
    """
    fields, pos = [], at
    for p, t, lt in props:  # the first record fixes the lengths
        if lt is None:
            fields.append((p, order + t))
            pos += np.dtype(t).itemsize
            continue
        n = int(np.frombuffer(body, dtype=order + lt, count=1, offset=pos)[0]) if count else 0
        fields.append((p + "#n", order + lt))
        fields.append((p, order + t, (n,)))
        pos += np.dtype(lt).itemsize + n * np.dtype(t).itemsize
    dt = np.dtype(fields)
    if at + count * dt.itemsize <= len(body):
        arr = np.frombuffer(body, dtype=dt, count=count, offset=at)
        same = all(np.all(arr[p + "#n"] == arr.dtype[p].shape[0])
                   for p, _, lt in props if lt is not None)
        if same:
            return {p: arr[p] for p, _, _ in props}, at + count * dt.itemsize
    cols = {p: [] for p, _, _ in props}
    for _ in range(count):
        for p, t, lt in props:
            if lt is None:
                cols[p].append(np.frombuffer(body, dtype=order + t, count=1, offset=at)[0])
                at += np.dtype(t).itemsize
                continue
            n = int(np.frombuffer(body, dtype=order + lt, count=1, offset=at)[0])
            at += np.dtype(lt).itemsize
            cols[p].append(np.frombuffer(body, dtype=order + t, count=n, offset=at))
            at += n * np.dtype(t).itemsize
    return {p: _stack(v) for p, v in cols.items()}, at


def _stack(values):
    """Rows of equal length as a 2-D array, else a 1-D object array (ragged lists)."""
    if values and isinstance(values[0], np.ndarray):
        if len({len(v) for v in values}) == 1:
            return np.stack(values)
        ragged = np.empty(len(values), dtype=object)
        ragged[:] = values
        return ragged
    return np.asarray(values)


def _ply_ascii(body: bytes, elements) -> tuple[dict[str, dict[str, np.ndarray]], list]:
    tokens = body.split()
    out, at = {}, 0
    for name, count, props in elements:
        cols = {p: [] for p, _, _ in props}
        for _ in range(count):
            for p, _, lt in props:
                if lt is None:
                    cols[p].append(float(tokens[at]))
                    at += 1
                    continue
                n = int(tokens[at])
                if at + 1 + n > len(tokens):
                    raise IndexError(f"a list of {n} items runs past the end")
                cols[p].append(np.array([float(v) for v in tokens[at + 1:at + 1 + n]]))
                at += 1 + n
        out[name] = {p: _stack(v) for p, v in cols.items()}
    return out, tokens[at:]
