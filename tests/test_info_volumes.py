"""`volwarp info` of a file of several volumes: a displacement field, a 4-D series.

Every other command asks which one (--volume-index); info is how a user finds
out what the file holds, and it refused volwarp's own fields (exit 2, a user-day
review). It now describes volume 0 and says how many there are.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from volwarp_cli.io import write_volume
from volwarp_cli.io.nrrd import write_nrrd
from volwarp_cli.volume import Volume


def _field(tmp_path):
    rng = np.random.default_rng(2)
    comps = [rng.normal(size=(4, 5, 6)).astype(np.float32) for _ in range(3)]
    path = tmp_path / "d.nrrd"
    write_nrrd(Volume(comps[0], spacing=np.array([1.0, 1.5, 2.0])), path, components=comps,
               component_names=["x", "y", "z"])
    return path, comps


def test_info_of_a_vector_field_describes_volume_0_and_counts_them(run, tmp_path):
    path, comps = _field(tmp_path)
    res = run("info", path, "--json")
    assert res.code == 0, res.stderr
    d = json.loads(res.stdout)
    assert d["volumes"] == 3 and d["volume_index"] == 0
    assert d["shape"] == [6, 5, 4] and d["spacing"] == [1.0, 1.5, 2.0]
    assert d["min"] == pytest.approx(float(comps[0].min()))
    text = run("info", path)
    assert text.code == 0 and "volumes:   3 in the file" in text.stdout
    one = json.loads(run("info", path, "--volume-index", 2, "--json").stdout)
    assert one["max"] == pytest.approx(float(comps[2].max())) and "volumes" not in one
    assert run("info", path, "--volume-index", 3).code == 2


@pytest.mark.parametrize("count", [1, 2, 5, 9])
def test_info_counts_the_volumes_of_a_4d_nifti(run, tmp_path, count):
    nib = pytest.importorskip("nibabel")
    data = np.arange(3 * 4 * 5 * count, dtype=np.float32).reshape(5, 4, 3, count)
    path = tmp_path / "s.nii.gz"
    nib.save(nib.Nifti1Image(data, np.eye(4)), path)
    res = run("info", path, "--json")
    assert res.code == 0, res.stderr
    d = json.loads(res.stdout)
    if count == 1:
        assert "volumes" not in d
    else:
        assert d["volumes"] == count and d["min"] == 0.0


def test_a_plain_volume_says_no_count(run, tmp_path):
    write_volume(Volume(np.zeros((3, 4, 5), np.float32)), tmp_path / "v.nrrd")
    d = json.loads(run("info", tmp_path / "v.nrrd", "--json").stdout)
    assert "volumes" not in d and "volume_index" not in d
