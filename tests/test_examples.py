"""Every example pipeline under examples/, run through make at reduced size.

Each example folder follows one convention (see examples/README.md): a Makefile
with `all` and `clean`, outputs under `out/`, `SIZE=small` for a reduced run.
The tests copy the folder into a temporary tree (next to links to the repo's
`specs/` and `tests/`, which examples reach as `../../specs` and
`../../tests/data`), build it with `make -j2`, check every picture and mesh
it made, and check that a second `make` has nothing to do.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from volwarp_cli.io.images import read_image

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = sorted(p.parent.name for p in (ROOT / "examples").glob("*/Makefile")
                  if p.parent.name != "batch")  # batch: tests/test_examples_batch.py
BIN = Path(sys.executable).parent

pytestmark = pytest.mark.examples


def make_args(**extra) -> list[str]:
    args = [f"VOLWARP={BIN / 'volwarp'}", f"PYTHON={sys.executable}"]
    return args + [f"{k}={v}" for k, v in extra.items()]


def run_make(folder: Path, *args: str, timeout: int = 400) -> subprocess.CompletedProcess:
    if shutil.which("make") is None:
        pytest.fail("make is not installed (the README's install needs it)")
    env = dict(os.environ, PATH=f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}")
    return subprocess.run(["make", "--no-print-directory", "-C", str(folder), *args],
                          capture_output=True, text=True, timeout=timeout, env=env)


def copy_example(name: str, tmp_path: Path) -> Path:
    (tmp_path / "examples").mkdir()
    for shared in ("specs", "tests"):
        (tmp_path / shared).symlink_to(ROOT / shared)
    work = tmp_path / "examples" / name
    shutil.copytree(ROOT / "examples" / name, work,
                    ignore=shutil.ignore_patterns("out", "__pycache__"))
    return work


def snapshot(folder: Path) -> dict[str, tuple[int, int]]:
    return {str(p.relative_to(folder)): (p.stat().st_mtime_ns, p.stat().st_size)
            for p in folder.rglob("*") if p.is_file()}


def assert_picture_shows_something(path: Path) -> None:
    img = read_image(path)[..., :3]
    background = img[0, 0]
    differs = np.any(np.abs(img - background) > 0.05, axis=-1)
    assert differs.mean() > 0.02, f"{path.name}: almost all background"
    assert img.std() > 0.02, f"{path.name}: flat picture"


def assert_mesh_is_closed(path: Path) -> None:
    import trimesh

    mesh = trimesh.load(str(path), force="mesh", process=True)
    assert len(mesh.faces) > 0, f"{path.name}: empty mesh"
    assert mesh.is_watertight, f"{path.name}: not closed"


@pytest.mark.parametrize("name", EXAMPLES)
def test_example_pipeline(name, tmp_path):
    work = copy_example(name, tmp_path)
    res = run_make(work, "-j2", "SIZE=small", *make_args())
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]

    out = work / "out"
    pngs = sorted(out.rglob("*.png"))
    meshes = sorted(out.rglob("*.ply"))
    assert pngs, f"{name}: no picture in out/"
    for p in pngs:
        assert_picture_shows_something(p)
    for m in meshes:
        assert_mesh_is_closed(m)

    before = snapshot(work)
    again = run_make(work, "-q", "SIZE=small", *make_args())
    assert again.returncode == 0, f"{name}: make -q says something is out of date"
    rerun = run_make(work, "SIZE=small", *make_args())
    assert rerun.returncode == 0, rerun.stderr[-3000:]
    assert snapshot(work) == before, f"{name}: a second make changed files"


def test_every_example_documents_its_picture():
    """Each example's README shows its figure from the committed gallery."""
    for name in EXAMPLES:
        readme = (ROOT / "examples" / name / "README.md").read_text()
        shown = re.findall(r"!\[[^\]]*\]\(([^)\s]*docs/gallery/[^)\s]*)\)", readme)
        assert shown, f"examples/{name}/README.md shows no gallery picture"
        for target in shown:
            assert (ROOT / "examples" / name / target).resolve().is_file(), (name, target)
