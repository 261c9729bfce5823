"""A batch step's process runs volwarp, whatever lies in the manifest's folder.

Steps (and the report's previews) run in the manifest's folder; ``python -c``
put that folder first on ``sys.path``, so a ``volwarp_cli/`` or a
``numpy.py`` beside the manifest ran instead of the real one, and the batch
recorded what it wrote as the step's output (a review's finding).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from volwarp_cli.io import read_volume, write_volume

sys.path.insert(0, str(Path(__file__).parent))
from test_batch import scan_volume  # noqa: E402
from test_batch_report_html import Page  # noqa: E402

FAKE_MAIN = ("import sys\n"
             "open(sys.argv[sys.argv.index('-o') + 1], 'wb').write(b'not a volume\\n')\n")


@pytest.mark.parametrize("impostor", ["volwarp_cli", "numpy.py"])
def test_modules_beside_the_manifest_are_not_imported(run, tmp_path, impostor):
    (tmp_path / "scans").mkdir()
    write_volume(scan_volume(1), tmp_path / "scans" / "b.nrrd")
    if impostor == "volwarp_cli":
        (tmp_path / "volwarp_cli").mkdir()
        (tmp_path / "volwarp_cli" / "__init__.py").write_text("")
        (tmp_path / "volwarp_cli" / "__main__.py").write_text(FAKE_MAIN)
    else:
        (tmp_path / "numpy.py").write_text("raise SystemExit('numpy of the manifest folder')\n")
    (tmp_path / "m.yaml").write_text(
        "version: 1\ninputs: {glob: 'scans/*.nrrd'}\noutput_dir: out\nsteps:\n"
        "  - {name: conv, run: convert, output: '{stem}.nii.gz'}\n")
    res = run("batch", tmp_path / "m.yaml", "-q", "--report", tmp_path / "r.html")
    assert res.code == 0, res.stderr
    assert run("convert", tmp_path / "scans" / "b.nrrd", "-o", tmp_path / "want.nii.gz").code == 0
    got, want = read_volume(tmp_path / "out" / "b.nii.gz"), read_volume(tmp_path / "want.nii.gz")
    assert np.array_equal(got.data, want.data) and np.array_equal(got.spacing, want.spacing)
    page = Page()
    page.feed((tmp_path / "r.html").read_text())
    assert len(page.imgs) == 2  # the previews' process is volwarp's too: the scan's, the output's
