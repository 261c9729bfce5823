"""What a newcomer runs first works as shipped (issue 28, item 7).

Every `volwarp ...` command line in README.md's code blocks runs, in order, in a
scratch folder holding copies of the bundled data and of specs/. A path the README
names must be shipped; a bare file name that stands for the user's own file
(`before.nrrd`, the worked example's `ex.yaml`) is made from the bundled data by
:data:`PLACEHOLDERS` and nothing else. An unknown option, a missing file or any
failure fails the test with the README's line.

Every spec in specs/ runs where it is shipped (its templates and inputs beside it),
at a reduced size where the command allows it.
"""

from __future__ import annotations

import re
import shlex
import shutil
from pathlib import Path

import numpy as np
import pytest

from volwarp_cli.io import read_volume, write_volume
from volwarp_cli.io.images import read_image

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
SPECS = ROOT / "specs"
DATA = ROOT / "tests" / "data"
BALL = DATA / "ball_30_uint8.nrrd"
HEAD = DATA / "mri_t1_head_coronal_2x2x3mm.nrrd"


# -- the README's command lines ------------------------------------------------------------
def code_blocks(text: str) -> list[tuple[int, str, list[tuple[int, str]]]]:
    """Fenced blocks: ``(line of the fence, info string, [(line, text), ...])``."""
    blocks, current = [], None
    for n, line in enumerate(text.splitlines(), 1):
        if line.startswith("```"):
            if current is None:
                current = (n, line[3:].strip(), [])
            else:
                blocks.append(current)
                current = None
        elif current is not None:
            current[2].append((n, line))
    assert current is None, f"README.md: the block opened at line {current[0]} is not closed"
    return blocks


def command_lines(lines: list[tuple[int, str]]) -> list[tuple[int, list[str]]]:
    """The ``volwarp ...`` commands of a block (continued lines joined): ``(line, argv)``."""
    commands, pending = [], None
    for n, line in lines:
        text = line.strip()
        if pending is not None:
            pending = (pending[0], pending[1] + " " + text.rstrip("\\"))
        elif re.match(r"(\$ )?volwarp(\s|$)", text):
            pending = (n, text.removeprefix("$ ").rstrip("\\"))
        if pending is not None and not text.endswith("\\"):
            commands.append((pending[0], shlex.split(pending[1], comments=True)))
            pending = None
    return commands


def readme_commands() -> list[tuple[int, list[str], int]]:
    """Every command line of the README: ``(line, argv without 'volwarp', fence line)``."""
    out = []
    for fence, _info, lines in code_blocks(README.read_text()):
        out += [(n, argv[1:], fence) for n, argv in command_lines(lines)]
    return out


def yaml_block_before(line: int) -> str:
    """The last ```yaml block that opens before README line ``line`` (a worked example's spec)."""
    found = [body for fence, info, body in code_blocks(README.read_text())
             if info == "yaml" and fence < line]
    assert found, f"README.md:{line}: no yaml block before it for its spec"
    return "\n".join(text for _, text in found[-1]) + "\n"


def _moved_ball(path: Path, _line: int) -> None:
    vol = read_volume(BALL)
    vol.origin = tuple(np.asarray(vol.origin) + (3.0, 0.0, 0.0))
    write_volume(vol, path)


#: bare file names the README uses for the user's own files, and how each is made here
PLACEHOLDERS = {
    "before.nrrd": lambda path, _line: shutil.copy(BALL, path),
    "after.nrrd": _moved_ball,
    "ex.yaml": lambda path, line: path.write_text(yaml_block_before(line)),
    "p.csv": lambda path, _line: path.write_text("x,y,z\n14.5,14.5,24.0\n14.5,14.5,5.0\n"),
}


def workspace(tmp_path: Path) -> Path:
    """A scratch folder with copies of the bundled data and of specs/, as a clone has them."""
    work = tmp_path / "work"
    shutil.copytree(DATA, work / "tests" / "data",
                    ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copytree(SPECS, work / "specs", symlinks=True)
    return work


def snapshot(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def test_the_readme_has_commands_of_every_kind():
    commands = readme_commands()
    names = {argv[0] for _, argv, _ in commands if argv}
    assert {"capture", "warp", "mesh", "distance", "morph", "sweep"} <= names, names


def test_every_readme_command_line_runs(run, tmp_path, monkeypatch):
    work = workspace(tmp_path)
    shipped = snapshot(work)
    monkeypatch.chdir(work)
    used = set()
    for line, argv, _fence in readme_commands():
        for word in argv:
            if word in PLACEHOLDERS and not (work / word).exists():
                PLACEHOLDERS[word](work / word, line)
                used.add(word)
        res = run(*argv)
        assert res.code == 0, (f"README.md:{line}: volwarp {shlex.join(argv)}\n"
                               f"exit {res.code}: {res.stderr}")
    after = snapshot(work)
    assert {k: v for k, v in after.items() if k in shipped} == shipped  # (inputs untouched)
    assert used == set(PLACEHOLDERS), f"placeholders no README line uses: {set(PLACEHOLDERS) - used}"


@pytest.mark.parametrize("text, words", [
    ("```sh\nvolwarp sweep sweep/sweep-bottle.yaml -o 'b_{field}.nrrd'\n```\n", "no such"),
    ("```sh\nvolwarp mesh tests/data/ball_30_uint8.nrrd -o b.ply \\\n    --no-such-option\n```\n",
     "no such option"),
], ids=["missing-file", "unknown-option"])
def test_a_missing_file_or_an_unknown_option_fails(run, tmp_path, monkeypatch, text, words):
    """The runner above fails on these (the README's sweep line used to name sweep/...)."""
    work = workspace(tmp_path)
    monkeypatch.chdir(work)
    [(fence, _info, lines)] = code_blocks(text)
    [(_line, argv)] = command_lines(lines)
    res = run(*argv[1:])
    assert res.code == 2 and words in res.stderr.lower(), res.stderr


# -- every spec in specs/ ----------------------------------------------------------------------
def _sweep(spec, out):
    return ["sweep", spec, "-o", out / "o_{field}.nrrd", "--shape", 24, 24, 24,
            "--render", out / "r.png", "--render-size", "48x48"]


def _morph(spec, out):
    return ["morph", "--spec", spec, "-o", out / "f_{i:02d}.nrrd",
            "--mesh-to", out / "f_{i:02d}.ply"]


def _transform(spec, out):
    return ["distance", "--update", out / "d0.nrrd", "--transform", spec, "-o", out / "d1.nrrd"]


#: how each spec kind runs, and the inputs a warp spec is written for (its comment names them)
RUNS = {"sweep": _sweep, "morph": _morph, "transform": _transform}
WARP_INPUTS = {"warp-head.yaml": HEAD, "warp-ball.yaml": BALL, "warp-ball-voxel.yaml": BALL}


def _check_sweep(out):
    o = read_volume(out / "o_opacity.nrrd")
    assert o.shape_xyz[0] <= 24 and o.data.max() > 0.2
    assert read_image(out / "r.png").max() > 0.1


def _check_morph(out):
    frames = sorted(f for f in out.glob("f_*.nrrd") if f.stem.count("_") == 1)
    assert len(frames) >= 4
    for f in frames:
        vol = read_volume(f)
        inside = (vol.data > 0.5) if "density" in vol.meta["volwarp_morph"] else (vol.data < 0)
        assert inside.any() and not inside.all(), f.name
        assert f.with_suffix(".ply").stat().st_size > 1000


def _run_manifest(run, spec, out):
    """The batch manifest on a CT-like scan (the bundled head, x4: its iso 300 is tissue)."""
    shutil.copy(spec, out / spec.name)
    shutil.copy(SPECS / "warp-head.yaml", out / "warp-head.yaml")
    head = read_volume(HEAD)
    head.data = head.data.astype(np.int16) * 4
    (out / "scans" / "site-a").mkdir(parents=True)
    write_volume(head, out / "scans" / "site-a" / "p01.nii.gz")
    res = run("batch", out / spec.name)
    assert res.code == 0, res.stderr
    for name in ("p01_warped.nrrd", "p01_sdf.nrrd", "p01.ply", "p01.png"):
        assert (out / "processed" / "site-a" / name).stat().st_size > 0, name


SPEC_FILES = sorted(SPECS.glob("*.yaml"))


@pytest.mark.parametrize("spec", SPEC_FILES, ids=[p.stem for p in SPEC_FILES])
def test_every_shipped_spec_runs_where_it_is(run, tmp_path, spec):
    kind = spec.name.split("-")[0]
    before = snapshot(SPECS)
    if kind == "manifest":
        _run_manifest(run, spec, tmp_path)
    else:
        if kind == "warp":
            assert spec.name in WARP_INPUTS, f"{spec.name}: say which bundled input it warps"
            argv = ["warp", WARP_INPUTS[spec.name], "--spec", spec, "-o", tmp_path / "w.nrrd"]
        else:
            assert kind in RUNS, f"{spec.name}: no way to run a '{kind}' spec here: add one"
            argv = RUNS[kind](spec, tmp_path)
        if kind == "transform":
            assert run("distance", BALL, "-o", tmp_path / "d0.nrrd").code == 0
        res = run(*argv)
        assert res.code == 0, f"{spec.name}: exit {res.code}: {res.stderr}"
        {"sweep": _check_sweep, "morph": _check_morph}.get(kind, lambda out: None)(tmp_path)
        assert any(p.suffix == ".nrrd" and p.stat().st_size for p in tmp_path.iterdir())
    assert snapshot(SPECS) == before  # (nothing written beside the specs)
