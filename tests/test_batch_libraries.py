"""An output made with other libraries is made again, as one made by other code is.

A batch recorded volwarp's version and code as what an output is made from, not
the libraries it runs on: after an upgrade of scipy (interpolation), vtk
(renders), isal (gzip bytes) or OpenImageIO, every recorded output was skipped,
though the same step would now write other bytes. The versions of volwarp's
requirements (and its dicom and scale extras), Python's and zlib's are part of
what a step's outputs are made from (:func:`volwarp_cli.batch.plan.library_versions`).
"""

from __future__ import annotations

import sys
import zlib
from pathlib import Path

import numpy as np
import scipy

sys.path.insert(0, str(Path(__file__).parent))
from test_batch import CONVERT_MANIFEST, make_tree  # noqa: E402

from volwarp_cli.batch import plan  # noqa: E402
from volwarp_cli.batch.manifest import find_scans, load_manifest  # noqa: E402


def _first_step(manifest):
    from volwarp_cli.batch.run import Batch

    (result,), stop = Batch(manifest, find_scans(manifest)[:1], jobs=1).run()
    assert stop is None
    return result.steps[0]


def test_the_versions_are_the_installed_ones():
    versions = plan.library_versions()
    assert versions["numpy"] == np.__version__ and versions["scipy"] == scipy.__version__
    assert versions["zlib"] == zlib.ZLIB_RUNTIME_VERSION
    assert versions["python"] == ".".join(map(str, sys.version_info[:3]))
    assert "volwarp-cli" not in versions and "pytest" not in versions


def test_a_step_made_with_another_scipy_is_made_again(tmp_path, monkeypatch):
    """Before: skipped (the record named volwarp's code only)."""
    manifest = load_manifest(make_tree(tmp_path, CONVERT_MANIFEST))
    assert _first_step(manifest).status == "ok"
    assert _first_step(manifest).status == "skipped"
    upgraded = {**getattr(plan, "library_versions", dict)(), "scipy": "99.0.0"}
    monkeypatch.setattr(plan, "library_versions", lambda: upgraded, raising=False)
    step = _first_step(manifest)
    assert step.status == "ok", step
    assert step.reason == (f"the libraries it runs on changed (scipy {scipy.__version__} "
                           "-> 99.0.0)"), step.reason
    assert _first_step(manifest).status == "skipped"
