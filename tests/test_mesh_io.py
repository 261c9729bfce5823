"""Mesh files re-read by independent readers (meshio, trimesh, pyvista); deterministic bytes."""

from __future__ import annotations

import numpy as np
import pytest

from volwarp_cli.errors import VolwarpError
from volwarp_cli.surface.isosurface import isosurface
from volwarp_cli.surface.mesh import Mesh
from volwarp_cli.surface.mesh_io import MESH_EXTENSIONS, write_mesh
from volwarp_cli.volume import Volume

FORMATS = sorted(ext.lstrip(".") for ext in MESH_EXTENSIONS)


@pytest.fixture(scope="module")
def blob() -> Mesh:
    """Two separate ellipsoids, world geometry with a non-trivial origin and spacing."""
    z, y, x = np.indices((20, 24, 30)).astype(np.float32)
    f = np.maximum(1 - ((x - 9) / 6) ** 2 - ((y - 11) / 7) ** 2 - ((z - 9) / 5) ** 2,
                   1 - ((x - 22) / 4) ** 2 - ((y - 12) / 4) ** 2 - ((z - 10) / 4) ** 2)
    vol = Volume(f, spacing=(0.7, 0.8, 1.1), origin=(-120.5, 33.25, 1000.0))
    mesh = isosurface(vol, 0.0)
    assert mesh.n_faces > 1000
    return mesh


def _read_meshio(path):
    import meshio

    m = meshio.read(path)
    tri = [c.data for c in m.cells if c.type == "triangle"]
    return np.asarray(m.points, dtype=np.float64), np.concatenate(tri).astype(np.int64)


def _read_trimesh(path):
    import trimesh

    m = trimesh.load(path, process=False, force="mesh")
    return np.asarray(m.vertices, dtype=np.float64), np.asarray(m.faces, dtype=np.int64)


def _read_pyvista(path):
    import pyvista as pv

    m = pv.read(path)
    faces = np.asarray(m.faces).reshape(-1, 4)
    assert np.all(faces[:, 0] == 3)
    return np.asarray(m.points, dtype=np.float64), faces[:, 1:].astype(np.int64)


READERS = {
    "ply": [_read_meshio, _read_trimesh, _read_pyvista],
    "stl": [_read_meshio, _read_trimesh, _read_pyvista],
    "obj": [_read_meshio, _read_trimesh, _read_pyvista],
    # meshio reads neither VTP nor legacy POLYDATA; VTK's own readers are the reference
    "vtp": [_read_pyvista],
    "vtk": [_read_pyvista],
}


def _same_triangles(mesh: Mesh, points: np.ndarray, faces: np.ndarray):
    """Compare triangle corner positions, independently of vertex numbering."""
    ours = mesh.vertices[mesh.faces].astype(np.float32).astype(np.float64)
    theirs = points[faces]
    np.testing.assert_allclose(theirs, ours, rtol=0, atol=1e-3)


@pytest.mark.parametrize("fmt", FORMATS)
def test_independent_readers_agree(blob, tmp_path, fmt):
    path = tmp_path / f"blob.{fmt}"
    # provenance comments (with awkward characters) must not disturb any reader, nor fail
    # the write (a non-ASCII file name failed PLY and VTP writes: UnicodeEncodeError)
    write_mesh(blob, path, comments={"volwarp_input": "a b--c Läsion.nrrd", "volwarp_iso": "0.5"})
    for reader in READERS[fmt]:
        points, faces = reader(str(path))
        assert len(faces) == blob.n_faces, reader.__name__
        if fmt == "stl":
            # STL stores every corner; the readers merge equal positions back
            if reader is _read_trimesh:
                assert len(points) == 3 * blob.n_faces
            else:
                assert len(points) == blob.n_vertices, reader.__name__
        else:
            assert len(points) == blob.n_vertices, reader.__name__
        _same_triangles(blob, points, faces)
    if fmt == "ply":  # (and volwarp's own reader: --mesh-in)
        from volwarp_cli.surface.mesh_io import read_mesh

        back = read_mesh(path)
        _same_triangles(blob, back.vertices, back.faces)


@pytest.mark.parametrize("fmt", ["ply", "obj", "vtp", "vtk"])
def test_normals_stored(blob, tmp_path, fmt):
    import pyvista as pv

    path = tmp_path / f"blob.{fmt}"
    write_mesh(blob, path)
    m = pv.read(str(path))
    normals = m.point_data.get("Normals")
    if normals is None:
        normals = m.point_normals if fmt == "obj" else None
    assert normals is not None
    np.testing.assert_allclose(np.asarray(normals), blob.normals, atol=2e-6)


def test_stl_facet_normals_outward(blob, tmp_path):
    import trimesh

    path = tmp_path / "blob.stl"
    write_mesh(blob, path)
    raw = np.frombuffer(path.read_bytes()[84:], dtype=np.dtype(
        [("n", "<f4", (3,)), ("v", "<f4", (3, 3)), ("a", "<u2")]))
    np.testing.assert_allclose(raw["n"], blob.face_normals(), atol=1e-5)
    # trimesh agrees the STL is watertight and encloses positive volume
    m = trimesh.load(str(path), force="mesh")  # merges the corners
    assert m.is_watertight and m.is_winding_consistent and m.volume > 0


@pytest.mark.parametrize("fmt", FORMATS)
def test_deterministic_bytes(blob, tmp_path, fmt):
    a, b = tmp_path / f"a.{fmt}", tmp_path / f"b.{fmt}"
    write_mesh(blob, a)
    copy = Mesh(blob.vertices.copy(), blob.faces.copy(), blob.normals.copy())
    write_mesh(copy, b)
    assert a.read_bytes() == b.read_bytes()


@pytest.mark.parametrize("fmt", FORMATS)
def test_empty_mesh_is_a_valid_file(tmp_path, fmt):
    import meshio

    path = tmp_path / f"empty.{fmt}"
    write_mesh(Mesh.empty(), path)
    if fmt == "stl":
        assert path.stat().st_size == 84
    elif fmt in ("vtp", "vtk"):
        import pyvista as pv

        m = pv.read(str(path))
        assert m.n_points == 0 and m.n_cells == 0
    elif fmt == "ply":
        m = meshio.read(str(path))
        assert len(m.points) == 0
    else:  # OBJ: comments only
        assert all(line.startswith(b"#") for line in path.read_bytes().splitlines())


def test_empty_legacy_vtk_is_what_vtks_writer_writes(tmp_path):
    """vtkPolyDataReader reads an empty mesh's .vtk without an error event (``POLYGONS 0 0``
    was "Error reading polygons", and 3D Slicer refused the file), and every line after
    the title is vtkPolyDataWriter's for an empty polydata (file version 4.2)."""
    from vtkmodules.vtkCommonCore import vtkFloatArray, vtkPoints
    from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkPolyData
    from vtkmodules.vtkIOLegacy import vtkPolyDataReader, vtkPolyDataWriter

    path = tmp_path / "empty.vtk"
    write_mesh(Mesh.empty(), path)  # (with its empty normals)
    reader = vtkPolyDataReader()
    reader.SetFileName(str(path))
    errors = []
    reader.AddObserver("ErrorEvent", lambda obj, event: errors.append(event))
    reader.Update()
    assert errors == []
    assert reader.GetOutput().GetNumberOfPoints() == 0
    empty = vtkPolyData()
    empty.SetPoints(vtkPoints())
    empty.SetPolys(vtkCellArray())
    normals = vtkFloatArray()
    normals.SetNumberOfComponents(3)
    empty.GetPointData().SetNormals(normals)
    writer = vtkPolyDataWriter()
    writer.SetInputData(empty)
    writer.SetFileTypeToBinary()
    writer.SetFileVersion(42)
    writer.WriteToOutputStringOn()
    writer.Write()
    theirs = writer.GetOutputStdString().encode("ascii").split(b"\n")
    assert path.read_bytes().split(b"\n")[2:] == theirs[2:]


def test_binary_sizes(blob, tmp_path):
    """Binary encodings: sizes are exactly header + records."""
    write_mesh(blob, tmp_path / "m.ply")
    data = (tmp_path / "m.ply").read_bytes()
    header_end = data.index(b"end_header\n") + len(b"end_header\n")
    assert b"binary_little_endian" in data[:header_end]
    assert len(data) - header_end == blob.n_vertices * 24 + blob.n_faces * 13
    write_mesh(blob, tmp_path / "m.stl")
    assert (tmp_path / "m.stl").stat().st_size == 84 + 50 * blob.n_faces


def test_unknown_extension_and_missing_folder(blob, tmp_path):
    with pytest.raises(VolwarpError, match="unknown mesh extension"):
        write_mesh(blob, tmp_path / "m.off")
    with pytest.raises(VolwarpError, match="does not exist"):
        write_mesh(blob, tmp_path / "nope" / "m.ply")
    assert list(tmp_path.iterdir()) == []


def test_failed_write_leaves_existing_file(blob, tmp_path, monkeypatch):
    from volwarp_cli.surface import mesh_io

    path = tmp_path / "m.ply"
    path.write_bytes(b"old")

    def boom(mesh, fh, notes):
        fh.write(b"partial")
        raise RuntimeError("disk full")

    monkeypatch.setattr(mesh_io, "_write_ply", boom)
    with pytest.raises(RuntimeError):
        write_mesh(blob, path)
    assert path.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["m.ply"]


@pytest.mark.parametrize("fmt", ["ply", "obj", "vtp"])
def test_provenance_comments_are_kept(blob, tmp_path, fmt):
    path = tmp_path / f"blob.{fmt}"
    write_mesh(blob, path, comments={"volwarp_spec_sha256": "ab" * 32, "volwarp_input": "x y.nrrd"})
    head = path.read_bytes()[:2000]
    assert b"volwarp_spec_sha256=" + b"ab" * 32 in head
    assert b"volwarp_input=x y.nrrd" in head



@pytest.mark.parametrize("fmt", ["ply", "obj", "vtp"])
def test_an_input_name_not_utf8_is_escaped_in_the_comments(blob, tmp_path, fmt):
    """An input named ``caf\\xe9.nrrd`` (bytes that are not UTF-8) made .obj and .vtp an
    internal error; the comment now escapes it, and the mesh reads as before."""
    import os

    pv = pytest.importorskip("pyvista")
    named, plain = tmp_path / f"n.{fmt}", tmp_path / f"p.{fmt}"
    write_mesh(blob, named, comments={"volwarp_input": os.fsdecode(b"caf\xe9.nrrd")})
    write_mesh(blob, plain, comments={"volwarp_input": "cafe.nrrd"})
    assert b"volwarp_input=caf\\udce9.nrrd" in named.read_bytes()[:2000]
    a, b = pv.read(str(named)), pv.read(str(plain))
    np.testing.assert_array_equal(a.points, b.points)
    assert a.n_cells == b.n_cells == blob.n_faces

def test_read_mesh_round_trip(blob, tmp_path):
    from volwarp_cli.surface.mesh_io import read_mesh

    path = tmp_path / "m.ply"
    write_mesh(blob, path, comments={"volwarp_input": "x.nrrd"})
    back = read_mesh(path)
    np.testing.assert_array_equal(back.faces, blob.faces)
    np.testing.assert_array_equal(back.vertices, blob.vertices.astype(np.float32))
    np.testing.assert_array_equal(back.normals, blob.normals)


@pytest.mark.parametrize("encoding", ["ascii", "binary_big_endian"])
def test_read_mesh_reads_other_writers_ply(blob, tmp_path, encoding):
    """ASCII PLY from meshio, and big-endian PLY with double coordinates, read the same."""
    import meshio

    from volwarp_cli.surface.mesh_io import read_mesh

    path = tmp_path / "m.ply"
    if encoding == "ascii":
        meshio.write(path, meshio.Mesh(blob.vertices, [("triangle", blob.faces.astype(np.int32))]),
                     binary=False)
        assert b"format ascii" in path.read_bytes()[:200]
    else:
        _write_big_endian(path, blob)
    back = read_mesh(path)
    np.testing.assert_array_equal(back.faces, blob.faces)
    np.testing.assert_allclose(back.vertices, blob.vertices, atol=1e-9)
    assert back.normals is None


def _write_big_endian(path, mesh):
    """The same mesh as a big-endian PLY with double coordinates and int list counts."""
    header = (f"ply\nformat binary_big_endian 1.0\nelement vertex {mesh.n_vertices}\n"
              "property double x\nproperty double y\nproperty double z\n"
              f"element face {mesh.n_faces}\nproperty list int int vertex_indices\n"
              "end_header\n").encode()
    faces = np.empty(mesh.n_faces, dtype=[("n", ">i4"), ("v", ">i4", (3,))])
    faces["n"] = 3
    faces["v"] = mesh.faces
    path.write_bytes(header + mesh.vertices.astype(">f8").tobytes() + faces.tobytes())


def test_read_mesh_refuses_bad_files(blob, tmp_path):
    from volwarp_cli.surface.mesh_io import read_mesh

    path = tmp_path / "m.ply"
    write_mesh(blob, path)
    good = path.read_bytes()
    path.write_bytes(good[:len(good) // 2])
    with pytest.raises(VolwarpError, match="truncated"):
        read_mesh(path)
    path.write_bytes(b"solid nothing\n")
    with pytest.raises(VolwarpError, match="not a PLY"):
        read_mesh(path)
    with pytest.raises(VolwarpError, match="PLY files only"):
        read_mesh(tmp_path / "m.stl")


def test_read_mesh_refuses_what_it_took_silently(blob, tmp_path, caplog):
    """NaN or infinite vertices (moved, they came out NaN without a word), face indices
    that are not whole numbers (cut to integers), and data past what the header declares
    (a header counting too few faces gave an open mesh, exit 0: now said)."""
    from volwarp_cli.surface.mesh_io import read_mesh

    path = tmp_path / "m.ply"
    for bad in (np.nan, np.inf):
        vertices = blob.vertices.copy()
        vertices[7, 1] = bad
        write_mesh(Mesh(vertices, blob.faces, blob.normals), path)
        with pytest.raises(VolwarpError, match=r"1 vertex of its faces has NaN or infinite "
                                               r"coordinates \(the first: vertex 7\)"):
            read_mesh(path)
    # a NaN vertex no face uses: read as before (it goes through as it is), and said
    vertices = np.vstack([blob.vertices, [[np.nan, 0.0, 0.0]]])
    write_mesh(Mesh(vertices, blob.faces), path)
    caplog.clear()
    assert read_mesh(path).n_vertices == len(vertices)
    assert "1 vertex that no face uses has NaN" in caplog.text
    head = ("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
            "property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
            "end_header\n0 0 0\n1 0 0\n0 1 0\n")
    path.write_text(head + "3 0.7 1.9 2\n")
    with pytest.raises(VolwarpError, match="not whole numbers"):
        read_mesh(path)
    path.write_text(head + "3 0 1.0 2\n")  # (whole numbers written as floats: taken)
    np.testing.assert_array_equal(read_mesh(path).faces, [[0, 1, 2]])
    caplog.clear()
    path.write_text(head + "3 0 1 2\n3 0 2 1\n")  # (a face more than declared)
    assert read_mesh(path).n_faces == 1
    assert "4 values after the elements its PLY header declares" in caplog.text
    caplog.clear()
    path.write_text(head + "3 0 1 2\n\x1a")  # (an old DOS end: nothing to say)
    read_mesh(path)
    assert "header declares" not in caplog.text
    write_mesh(blob, path)
    good = path.read_bytes()
    caplog.clear()
    path.write_bytes(good + b"\n")  # (a trailing newline: nothing to say)
    read_mesh(path)
    assert "header declares" not in caplog.text
    path.write_bytes(good + bytes(16))  # (NUL padding: nothing to say)
    read_mesh(path)
    assert "header declares" not in caplog.text
    path.write_bytes(good + b"garbage" * 2)
    read_mesh(path)
    assert "14 bytes after the elements its PLY header declares" in caplog.text


TRI_ASCII = """ply
format ascii 1.0
comment a line mentioning end_header is still a comment
element vertex 4
property float x
property float y
property float z
property uchar red
element face 2
property list uchar int vertex_indices
property list uchar float texcoord
property uchar flags
element edge 1
property list uchar int vertex_pair
end_header
0 0 0 255
1 0 0 255
0 1 0 255
0 0 1 255
3 0 1 2 6 0 0 1 0 0 1 7
3 0 3 1 6 0 0 1 0 0 1 7
2 0 3
"""


def test_read_mesh_skips_other_properties_and_elements(tmp_path, caplog):
    from volwarp_cli.surface.mesh_io import read_mesh

    path = tmp_path / "t.ply"
    path.write_text(TRI_ASCII)
    m = read_mesh(path)
    # said, once: a mesh moved by apply --mesh-in lost its colours and labels without a word
    said = [r.getMessage() for r in caplog.records if "not carried" in r.getMessage()]
    assert len(said) == 1 and "vertex red" in said[0] and "1 edge" in said[0], said
    assert m.faces.tolist() == [[0, 1, 2], [0, 3, 1]]
    assert m.vertices.shape == (4, 3) and m.normals is None
    # the same as binary big-endian, per-face extras included
    head, body = TRI_ASCII.split("end_header\n")
    head = head.replace("format ascii 1.0", "format binary_big_endian 1.0")
    verts = np.zeros(4, dtype=[("x", ">f4"), ("y", ">f4"), ("z", ">f4"), ("red", "u1")])
    verts["x"], verts["y"], verts["z"] = [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]
    face = np.zeros(2, dtype=[("n", "u1"), ("v", ">i4", (3,)), ("m", "u1"), ("t", ">f4", (6,)),
                              ("f", "u1")])
    face["n"], face["m"], face["f"] = 3, 6, 7
    face["v"] = [[0, 1, 2], [0, 3, 1]]
    edge = np.zeros(1, dtype=[("n", "u1"), ("v", ">i4", (2,))])
    edge["n"], edge["v"] = 2, [[0, 3]]
    path.write_bytes((head + "end_header\n").encode() + verts.tobytes() + face.tobytes()
                     + edge.tobytes())
    mb = read_mesh(path)
    assert mb.faces.tolist() == m.faces.tolist()
    np.testing.assert_array_equal(mb.vertices, m.vertices)


TETRA = ("ply\nformat ascii 1.0\nelement vertex 4\nproperty double x\nproperty double y\n"
         "property double z\nelement face 4\nproperty list uchar int vertex_indices\n"
         "end_header\n0 0 0\n{v} 0 0\n0 1 0\n0 0 1\n{faces}")


@pytest.mark.parametrize("text, match", [
    # beyond float32: every output held inf (and volwarp refused to read it back)
    (TETRA.format(v="1e39", faces="3 0 2 1\n3 0 1 3\n3 0 3 2\n3 1 2 3\n"), "beyond 1e"),
    (TETRA.format(v="1e20", faces="3 0 2 1\n3 0 1 3\n3 0 3 2\n3 1 2 3\n"), "beyond 1e"),
    # four faces of no vertices: read as an empty mesh, exit 0
    (TETRA.format(v="1", faces="0\n0\n0\n0\n"), "not triangles"),
    (TRI_ASCII.replace("3 0 3 1 6 0 0 1 0 0 1 7\n2 0 3\n", "3 0 3"), "truncated"),
    (TRI_ASCII.replace("3 0 1 2 6", "4 0 1 2 3 6"), "not triangles"),
    ("ply\nformat ascii 1.0\nelement vertex 0\nend_header", "needs vertex and face"),
    ("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x", "not a PLY"),
])
def test_read_mesh_bad_ascii_is_a_clear_error(tmp_path, text, match):
    from volwarp_cli.surface.mesh_io import read_mesh

    path = tmp_path / "b.ply"
    path.write_text(text)
    with pytest.raises(VolwarpError, match=match):
        read_mesh(path)


def test_a_slicer_ras_ply_is_read_in_lps_and_every_file_says_lps(blob, tmp_path, run):
    """3D Slicer writes 'comment SPACE=RAS' (or LPS) in a PLY and reads a file without a
    mark as LPS. read_mesh took a RAS file's vertices for LPS: a mesh moved by apply
    came out mirrored in x and y, in a file without a mark (found by a review)."""
    import SimpleITK as sitk

    from volwarp_cli.surface.mesh_io import read_mesh

    ras = (TRI_ASCII.replace("comment a line", "comment 3D Slicer output. SPACE=RAS\ncomment a")
           .replace("property float z\n", "property float z\nproperty float nx\n"
                    "property float ny\nproperty float nz\n"))
    rows = ras.split("end_header\n")[1].splitlines()
    verts = ["0 0 0 0 0 1 255", "1 2 0 0 0 1 255", "0 1 3 -1 0 0 255", "4 0 1 0 1 0 255"]
    (tmp_path / "ras.ply").write_text(ras.split("end_header\n")[0] + "end_header\n"
                                      + "\n".join(verts + rows[4:]) + "\n")
    m = read_mesh(tmp_path / "ras.ply")
    np.testing.assert_array_equal(m.vertices, [[0, 0, 0], [-1, -2, 0], [0, -1, 3], [-4, 0, 1]])
    np.testing.assert_array_equal(m.normals, [[0, 0, 1], [0, 0, 1], [1, 0, 0], [0, -1, 0]])
    assert m.faces.tolist() == [[0, 1, 2], [0, 3, 1]]  # (a half turn: the winding stays)
    lps = read_mesh(tmp_path / "ras.ply").vertices
    (tmp_path / "lps.ply").write_text((tmp_path / "ras.ply").read_text().replace("RAS", "LPS"))
    assert read_mesh(tmp_path / "lps.ply").vertices.tolist() == (lps * [-1, -1, 1]).tolist()
    # through apply (an identity): the output in LPS, and saying so where Slicer looks
    tfm = tmp_path / "id.tfm"
    sitk.WriteTransform(sitk.AffineTransform(3), str(tfm))
    res = run("apply", "-t", tfm, "--mesh-in", tmp_path / "ras.ply",
              "--mesh-to", tmp_path / "out.ply")
    assert res.code == 0, res.stderr
    out = read_mesh(tmp_path / "out.ply")
    np.testing.assert_allclose(out.vertices, m.vertices, atol=1e-6)
    for fmt, where in (("ply", 400), ("obj", 200), ("stl", 80), ("vtk", 80)):
        write_mesh(blob, tmp_path / f"b.{fmt}")
        assert b"SPACE=LPS" in (tmp_path / f"b.{fmt}").read_bytes()[:where], fmt


def test_float32_rounding_far_from_the_origin_is_said(run, tmp_path):
    """Every mesh format stores float32 vertices: a 0.01 mm voxel's ball of a volume placed
    1e5 mm out kept 24 distinct x values of 290 (0.39 voxel off), without a word. Said, with
    float32's step there; a scan near the origin, or a CT's 1.25 m out with 0.6 mm voxels
    (0.02% of an edge), says nothing."""
    from volwarp_cli.io import write_volume

    z, y, x = np.mgrid[:18, :18, :18]
    ball = (100 - 12 * np.sqrt((x - 8.5) ** 2 + (y - 8.5) ** 2 + (z - 8.5) ** 2)).astype(
        np.float32)
    for origin, spacing, said in (((1e5, 0.0, 0.0), 0.01, True),
                                  ((-120.0, 80.0, 300.0), 0.01, False),
                                  ((-180.0, -200.0, -1250.0), 0.6, False)):  # (a CT's table)
        src = tmp_path / "ball.nrrd"
        write_volume(Volume(ball, spacing=(spacing,) * 3, origin=origin), src)
        out = tmp_path / "ball.ply"
        res = run("mesh", src, "--iso", "50", "-o", out)
        assert res.code == 0 and out.exists(), res.stderr
        assert ("stored as float32, whose steps 100000 mm from the origin are 0.0078 mm"
                in res.stderr) is said, res.stderr
        if said:  # (and it is so: the file's x values are float32's steps there)
            from volwarp_cli.surface.mesh_io import read_mesh

            xs = np.unique(read_mesh(out).vertices[:, 0])
            assert np.all(np.diff(xs) >= 0.0078)


def test_a_vtp_comment_holds_any_file_name(blob, tmp_path):
    """A control character or "--" in a provenance value made an unreadable VTP (exit 0)."""
    import vtk

    path = tmp_path / "m.vtp"
    write_mesh(blob, path, comments={"volwarp_input": "b\x01a--ll---.nrrd"})
    reader = vtk.vtkXMLPolyDataReader()
    reader.SetFileName(str(path))
    reader.Update()
    assert reader.GetOutput().GetNumberOfPoints() == blob.n_vertices
    assert "b\\u0001a- -ll- - -.nrrd" in path.read_bytes()[:400].decode()
