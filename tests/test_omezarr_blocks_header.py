"""An OME-Zarr output written by blocks records what the in-memory one records.

The ``volwarp`` attribute holds the input's own frame (``file_space``): a
NIfTI input's right-anterior-superior. Written by blocks, the output's header
was rebuilt from its grid and ``space`` alone, and said left-posterior-superior.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import SimpleITK as sitk

from volwarp_cli.io import read_volume, write_volume
from volwarp_cli.volume import Volume

RAS = "right-anterior-superior"
SPEC = """version: 1
capture: {lattice: 5, oversample: 1}
steps:
  - move:
      - {index: [2, 2, 2], by: [1.5, -1, 2]}
"""


def _scan(path, shape):
    z, y, x = np.meshgrid(*[np.linspace(-1, 1, n) for n in shape], indexing="ij")
    blob = 1000 * np.exp(-((x - 0.2) ** 2 + y * y + z * z) / 0.2)
    c, s = np.cos(0.3), np.sin(0.3)
    write_volume(Volume(blob.astype(np.int16), spacing=np.array([0.8, 0.9, 1.1]),
                        origin=np.array([10.0, -5.0, 3.0]),
                        direction=np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])),
                 path)
    assert read_volume(path).file_space == RAS
    return path


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    folder = tmp_path_factory.mktemp("frame")
    sitk.WriteTransform(sitk.Transform(3, sitk.sitkIdentity), str(folder / "id.tfm"))
    (folder / "warp.yaml").write_text(SPEC)
    return {"folder": folder, "id": folder / "id.tfm", "spec": folder / "warp.yaml",
            "scan": _scan(folder / "scan.nii.gz", (17, 19, 23))}


def _commands(p, out):
    return {
        "apply": ["apply", p["scan"], "-t", p["id"], "-o", out],
        "distance": ["distance", p["scan"], "--iso", "300", "--surface", "voxel", "-o", out],
        "warp": ["warp", p["scan"], "--spec", p["spec"], "-o", out],
    }


@pytest.mark.parametrize("command", ["apply", "distance", "warp"])
@pytest.mark.parametrize("version", ["0.5", "0.4"])
def test_the_output_by_blocks_records_the_inputs_frame_as_in_memory(run, inputs, tmp_path,
                                                                   command, version):
    mem, blk = tmp_path / "m.ome.zarr", tmp_path / "b.ome.zarr"
    common = ["--ome-zarr-version", version]
    res = run(*_commands(inputs, mem)[command], *common)
    assert res.code == 0, res.stderr
    res = run(*_commands(inputs, blk)[command], *common, "--chunked", "--memory-limit", "4G")
    assert res.code == 0, res.stderr
    group = "zarr.json" if version == "0.5" else ".zattrs"
    assert (blk / group).read_bytes() == (mem / group).read_bytes()
    attrs = json.loads((mem / group).read_text())
    # (the store's own frame: its numbers are LPS; the input's RAS made info say "the
    # file's own: right-anterior-superior" of the store)
    assert attrs.get("attributes", attrs)["volwarp"]["file_space"] == "left-posterior-superior"
    res = run("info", mem, "--json")
    assert res.code == 0 and json.loads(res.stdout)["file_space"] == "left-posterior-superior"
    np.testing.assert_array_equal(read_volume(blk).data, read_volume(mem).data)
