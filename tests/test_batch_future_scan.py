"""An output `inputs.glob` matches is refused on the first run, not from the second on.

A step's output option without `{stem}` is the manifest folder's file; where the
scans' glob matches it (`--displacement-to disp.nrrd` beside `*.nrrd` scans),
the first run wrote it, and every later run took it for a scan and refused the
step that writes it ("would overwrite the scan 'disp'", exit 2): a batch that
worked once and never again. It is refused before any work of the first run.
:func:`volwarp_cli.batch.manifest.glob_would_match` says whether the glob would
list a file that does not exist yet: checked against `glob.glob` itself.
"""

from __future__ import annotations

import glob
import os
import sys
from pathlib import Path

from hypothesis import given, settings
from hypothesis import strategies as st

sys.path.insert(0, str(Path(__file__).parent))
from test_batch import scan_volume, volwarp  # noqa: E402

from volwarp_cli.batch.manifest import glob_would_match  # noqa: E402
from volwarp_cli.io import write_volume  # noqa: E402

SPEC = ("version: 1\nunits: voxel\ncapture: {lattice: 5, oversample: 1}\npushforward: box\n"
        "steps:\n  - move:\n      - {index: [2, 2, 2], by: [1.0, 0.5, 0.2]}\n")


def _tree(root: Path, glob_pattern: str, scan: str, option_value: str) -> Path:
    write_volume(scan_volume(0), root / scan)
    (root / "w.yaml").write_text(SPEC)
    manifest = root / "m.yaml"
    manifest.write_text(
        f"version: 1\ninputs: {{glob: '{glob_pattern}'}}\noutput_dir: out\nsteps:\n"
        f"  - {{name: w, run: warp, spec: w.yaml, output: '{{stem}}_w.nrrd', "
        f"options: [--displacement-to, '{option_value}']}}\n")
    return manifest


def test_an_output_the_glob_matches_is_refused_on_the_first_run(tmp_path):
    """Before: exit 0 and disp.nrrd written; every run after it exit 2."""
    manifest = _tree(tmp_path, "*.nrrd", "a.nrrd", "disp.nrrd")
    res = volwarp("batch", manifest)
    assert res.returncode == 2, res.stderr
    assert "disp.nrrd: inputs.glob" in res.stderr and "--displacement-to" in res.stderr
    assert "the next run would take it for a scan" in res.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.nrrd", "m.yaml", "w.yaml"]


def test_a_recursive_glob_and_the_output_folder(tmp_path):
    """`scans/**/*.nrrd`: an output in a folder below is refused; one under output_dir
    (inside the glob's folder: left out of the glob) and one beside it are not."""
    (tmp_path / "scans" / "sub").mkdir(parents=True)
    manifest = _tree(tmp_path, "scans/**/*.nrrd", "scans/a.nrrd", "scans/sub/deep/disp.nrrd")
    res = volwarp("batch", manifest)
    assert res.returncode == 2 and "inputs.glob" in res.stderr, res.stderr
    manifest.write_text(manifest.read_text().replace("scans/sub/deep/disp.nrrd", "disp.nrrd"))
    res = volwarp("batch", manifest)
    assert res.returncode == 0, res.stderr
    assert volwarp("batch", manifest).returncode == 0  # (and the next run too)
    manifest.write_text(manifest.read_text().replace("output_dir: out", "output_dir: scans/out")
                        .replace("disp.nrrd", "{stem}_disp.nrrd"))
    res = volwarp("batch", manifest)
    assert res.returncode == 0, res.stderr
    assert (tmp_path / "scans" / "out" / "a_disp.nrrd").exists()


NAMES = st.sampled_from(["a", "b", ".h", "ab", "a.nrrd", "b.nii", ".x.nrrd", "c.nrrd"])
PARTS = st.sampled_from(["*", "**", "a", "a*", "*.nrrd", "?", "[ab]", ".*", "*.n*", "b.nii"])


@settings(max_examples=60, deadline=None)
@given(files=st.lists(st.lists(NAMES, min_size=1, max_size=4), min_size=1, max_size=8),
       pattern=st.lists(PARTS, min_size=1, max_size=4))
def test_glob_would_match_is_what_glob_lists(tmp_path_factory, files, pattern):
    """For every file of a random tree, whether glob.glob(pattern, recursive=True) lists it."""
    root = tmp_path_factory.mktemp("tree")
    made = []
    for parts in files:
        path = root.joinpath(*parts)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.touch()
        except (FileExistsError, NotADirectoryError, IsADirectoryError):
            continue  # (a name taken by a folder, or a folder by a file)
        if path.is_file():
            made.append(path)
    full = os.path.join(str(root), *pattern)
    listed = {os.path.normpath(p) for p in glob.glob(full, recursive=True)}
    for path in made:
        assert glob_would_match(full, path) == (os.path.normpath(path) in listed), (full, path)
