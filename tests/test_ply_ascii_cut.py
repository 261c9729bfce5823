"""Mesh files cut short or otherwise damaged: read right, refused, or said (hunt meshio43)."""

from __future__ import annotations

import numpy as np

from volwarp_cli.surface.mesh_io import read_mesh


def _ascii_ply(tmp_path):
    """An ASCII PLY (trimesh's writer) of a sphere whose last face's last index is >= 100."""
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=2, radius=5.0)
    sphere.faces[-1] = sphere.faces[-1][::-1]  # (any face; its last index made 3 digits)
    sphere.faces[-1, 2] = 155
    data = trimesh.exchange.ply.export_ply(sphere, encoding="ascii")
    assert data.endswith(b" 155\n")
    return data, sphere


def test_ascii_ply_cut_inside_its_last_value_is_said(tmp_path, caplog):
    """A download cut inside the last number read "15" for "155", exit 0, without a word.

    Every other cut of an ASCII PLY runs out of values and is refused; this one
    cannot be told from a file without a final line end, so it is said.
    """
    import trimesh

    data, sphere = _ascii_ply(tmp_path)
    whole = tmp_path / "whole.ply"
    whole.write_bytes(data)
    ref = trimesh.load(whole, process=False, force="mesh")
    assert np.array_equal(read_mesh(whole).faces, ref.faces)
    assert "cut" not in caplog.text

    cut = tmp_path / "cut.ply"
    cut.write_bytes(data[:-2])  # "... 15"
    mesh = read_mesh(cut)
    assert mesh.faces[-1, 2] == 15 != ref.faces[-1, 2]  # (what any reader makes of it)
    assert "cut.ply" in caplog.text and "line end" in caplog.text

    caplog.clear()
    (tmp_path / "spaced.ply").write_bytes(data[:-1] + b" \r\n\x00")  # (blanks, padding: whole)
    read_mesh(tmp_path / "spaced.ply")
    assert "line end" not in caplog.text
