"""A batch records a step's outputs only as made from what the step could have read.

A step's inputs are hashed before it runs. A scan replaced while the step read
it (a sync rewriting it in place, a second version copied over it), then put
back, left a record naming the hashed bytes for an output made of the others:
the next run skipped that output for good (exit 0, a wrong output).
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from test_batch import make_tree, scan_volume, summary, volwarp  # noqa: E402

from volwarp_cli.batch.manifest import find_scans, load_manifest  # noqa: E402
from volwarp_cli.io import read_volume, write_volume  # noqa: E402

sitk = pytest.importorskip("SimpleITK")

ONE_SCAN = """version: 1
inputs: {list: [scans/site-a/p02.nrrd]}
output_dir: out
steps:
  - {name: conv, run: convert, output: "{stem}.nrrd"}
"""


def test_a_scan_replaced_while_its_step_runs_then_put_back_is_made_again(tmp_path, monkeypatch):
    from volwarp_cli.batch.run import Batch, ScanRunner

    manifest = load_manifest(make_tree(tmp_path, ONE_SCAN))
    (scan,) = find_scans(manifest)
    own = scan.path.read_bytes()
    write_volume(scan_volume(3), tmp_path / "other.nrrd")
    real = ScanRunner._call

    def while_another_version_is_there(self, argv):
        shutil.copyfile(tmp_path / "other.nrrd", scan.path)  # (what the step reads)
        try:
            return real(self, argv)
        finally:
            scan.path.write_bytes(own)  # put back: the bytes that were hashed

    monkeypatch.setattr(ScanRunner, "_call", while_another_version_is_there)
    (result,), stop = Batch(manifest, [scan], jobs=1).run()
    assert stop is None
    assert result.status == "failed"
    assert "p02.nrrd changed while the step ran" in result.steps[0].error
    monkeypatch.setattr(ScanRunner, "_call", real)

    res = volwarp("batch", tmp_path / "manifest.yaml")
    assert summary(res) == "volwarp batch: 1 scan, 1 ok, 0 skipped, 0 failed", res.stderr
    out = read_volume(tmp_path / "out" / "scans" / "site-a" / "p02.nrrd").data
    want = sitk.GetArrayFromImage(sitk.ReadImage(str(scan.path)))  # (z, y, x), as volwarp's
    assert np.array_equal(out, want)


def test_a_step_whose_files_stay_put_is_recorded_and_skipped(tmp_path):
    """Reading a scan, a detached header's data file, a spec and an option's file moves none
    of their stamps: the step is recorded and the next run skips it."""
    manifest = make_tree(tmp_path, """version: 1
inputs: {glob: "scans/**/*.n*"}
output_dir: out
steps:
  - {name: warped, run: warp, spec: warp.yaml, output: "{stem}_w.nhdr"}
  - {name: moved, run: apply, input: warped, output: "{stem}_m.nrrd",
     options: [-t, a.tfm, --reference, scans/site-a/p02.nrrd]}
""")
    (tmp_path / "a.tfm").write_text(
        "#Insight Transform File V1.0\n#Transform 0\nTransform: AffineTransform_double_3_3\n"
        "Parameters: 1 0 0 0 1 0 0 0 1 1 2 3\nFixedParameters: 0 0 0\n")
    write_volume(scan_volume(5), tmp_path / "scans" / "site-b" / "p04.nhdr")
    res = volwarp("batch", manifest)
    assert summary(res) == "volwarp batch: 4 scans, 4 ok, 0 skipped, 0 failed", res.stderr
    res = volwarp("batch", manifest)
    assert summary(res) == "volwarp batch: 4 scans, 0 ok, 4 skipped, 0 failed", res.stderr
