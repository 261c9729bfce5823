"""Every subcommand's --help, its examples, the option registry, and the renamed options."""

from __future__ import annotations

import importlib
import re
import shlex

import click
import numpy as np
import pytest

from volwarp_cli.cli import options as options_module
from volwarp_cli.cli.main import _SHORT_HELP, COMMANDS
from volwarp_cli.io import read_volume, write_volume
from volwarp_cli.volume import Volume


def command_of(name: str) -> click.Command:
    return importlib.import_module(f"volwarp_cli.cli.{name}").command


def visible_options(cmd: click.Command) -> set[str]:
    return {o for p in cmd.params if isinstance(p, click.Option) and not p.hidden
            for o in p.opts + p.secondary_opts} | {"-h", "--help"}


def example_lines(help_text: str) -> list[str]:
    """The command lines after the last 'Examples:' heading, which must end the help."""
    assert "Examples:" in help_text, help_text[-300:]
    tail = help_text.rsplit("Examples:", 1)[1]
    lines = [line.strip() for line in tail.strip().splitlines()]
    assert lines and all(line.startswith("volwarp ") for line in lines), lines
    return lines


def test_every_command_has_a_short_help():
    assert list(_SHORT_HELP) == list(COMMANDS)


@pytest.mark.parametrize("name", list(COMMANDS))
def test_help_ends_with_examples_that_parse(run, name):
    """`volwarp NAME --help` works (the module imports), ends with one or two example
    lines, and each example parses: its options exist (visible, not an old spelling)
    and their values pass the options' own checks."""
    cmd = command_of(name)
    assert cmd.name == name
    res = run(name, "--help")
    assert res.code == 0, res.stderr
    lines = example_lines(res.stdout)
    assert 1 <= len(lines) <= 2
    known = visible_options(cmd)
    for line in lines:
        argv = shlex.split(line)
        assert argv[:2] == ["volwarp", name], line
        used = {a.split("=")[0] for a in argv[2:] if re.match(r"-[-a-zA-Z]", a)}
        assert used <= known, (line, used - known)
        with cmd.make_context(f"volwarp {name}", argv[2:]) as ctx:  # usage errors raise
            assert ctx.params is not None


def test_group_help_lists_every_command(run):
    res = run("--help")
    assert res.code == 0
    for name in COMMANDS:
        assert f"\n  {name} " in res.stdout


def test_bare_volwarp_prints_the_whole_help(run):
    """Not a one-line error: the help a newcomer needs (on stdout, so `volwarp | less` shows
    it; exit 2: a script that lost its arguments still fails)."""
    res = run()
    assert res.code == 2
    assert res.stdout.startswith("Usage: ") and res.stderr == ""
    for name in COMMANDS:
        assert f"\n  {name} " in res.stdout


# ---- the option registry ----------------------------------------------------------------------

def _registry_rows(section: str) -> dict[str, str]:
    doc = options_module.__doc__
    body = doc.split(section, 1)[1].split("\n\n", 2)[1]
    rows = {}
    last = None
    for line in body.splitlines():
        m = re.match(r"    (\S+)\s{2,}(.*)$", line)
        if m:
            last = m.group(1)
            rows[last] = m.group(2)
        elif line.strip() and last:
            rows[last] += " " + line.strip()
    return rows


def test_option_registry_lists_every_option_and_its_commands():
    """cli/options.py's docstring names every visible option with the commands taking
    it, in the commands' order; '(every command)' for the options all of them take."""
    uses: dict[str, list[str]] = {}
    for name in COMMANDS:
        for p in command_of(name).params:
            if isinstance(p, click.Option) and not p.hidden and p.name != "help":
                uses.setdefault("/".join(p.opts + p.secondary_opts), []).append(name)
    expected = {label: "(every command)" if names == list(COMMANDS) else " ".join(names)
                for label, names in uses.items()}
    assert _registry_rows("commands that take it") == expected


def test_option_registry_lists_every_old_spelling():
    rows = _registry_rows("Old spellings")
    hidden: dict[str, list[str]] = {}
    for name in COMMANDS:
        for p in command_of(name).params:
            if isinstance(p, click.Option) and p.hidden:
                for o in p.opts:
                    hidden.setdefault(o, []).append(name)
    assert set(rows) == set(hidden)
    for old, names in hidden.items():
        assert all(n in rows[old] for n in names), (old, rows[old])


# ---- renamed options ----------------------------------------------------------------------------

@pytest.fixture
def ball_file(tmp_path):
    z, y, x = np.mgrid[:24, :24, :24]
    data = ((x - 11.5) ** 2 + (y - 11.5) ** 2 + (z - 11.5) ** 2 < 64).astype(np.uint8) * 200
    path = tmp_path / "ball.nrrd"
    write_volume(Volume(data), path)
    return path


def test_render_size_has_one_default_everywhere():
    defaults = {}
    for name in ("mesh", "morph", "sweep"):
        (p,) = [p for p in command_of(name).params if p.name == "render_size"]
        defaults[name] = p.default
    assert set(defaults.values()) == {options_module.DEFAULT_RENDER_SIZE}, defaults


def test_old_size_spelling_still_works_with_one_warning(run, ball_file, tmp_path):
    from volwarp_cli.io.images import read_image

    old, new = tmp_path / "old.png", tmp_path / "new.png"
    res = run("mesh", ball_file, "--iso", 100, "--render", old, "--size", "64x48")
    assert res.code == 0, res.stderr
    assert res.stderr.strip().splitlines() == ["volwarp: warning: --size is now --render-size"]
    res = run("mesh", ball_file, "--iso", 100, "--render", new, "--render-size", "64x48")
    assert res.code == 0 and res.stderr == "", res.stderr
    assert read_image(old).shape == (48, 64, 3)
    assert old.read_bytes() == new.read_bytes()
    # -q: errors only
    res = run("mesh", ball_file, "--iso", 100, "--render", old, "--size", "64x48", "-q")
    assert res.code == 0 and res.stderr == "", res.stderr


def test_old_spellings_are_hidden_from_help(run):
    mesh = run("mesh", "--help").stdout
    assert "--render-size" in mesh and "--background-color" in mesh
    assert not re.search(r"--size\b", mesh) and not re.search(r"--background\b(?!-)", mesh)
    warp = run("warp", "--help").stdout
    assert "--background-value" in warp and not re.search(r"--background\b(?!-)", warp)
    assert not re.search(r"--size\b", run("morph", "--help").stdout)


def test_both_spellings_at_once_are_a_usage_error(run, ball_file, tmp_path):
    for order in (("--size", "10x10", "--render-size", "20x20"),
                  ("--render-size", "20x20", "--size", "10x10")):
        res = run("mesh", ball_file, "--iso", 100, "--render", tmp_path / "x.png", *order)
        assert res.code == 2 and "--size is the old name of --render-size" in res.stderr
    assert not (tmp_path / "x.png").exists()


def test_a_bad_value_under_the_old_spelling_names_it(run, ball_file, tmp_path):
    res = run("mesh", ball_file, "--iso", 100, "--render", tmp_path / "x.png", "--size", "big")
    assert res.code == 2 and "'--size'" in res.stderr and "WIDTHxHEIGHT" in res.stderr


def test_mesh_background_color_and_its_old_spelling(run, ball_file, tmp_path):
    from volwarp_cli.io.images import read_image

    a, b = tmp_path / "a.png", tmp_path / "b.png"
    assert run("mesh", ball_file, "--iso", 100, "--render", a, "--render-size", "40x30",
               "--background-color", "#ff0000").code == 0
    res = run("mesh", ball_file, "--iso", 100, "--render", b, "--render-size", "40x30",
              "--background", "#ff0000")
    assert res.code == 0 and "--background is now --background-color" in res.stderr
    assert a.read_bytes() == b.read_bytes()
    assert tuple(read_image(a)[0, 0]) == pytest.approx((1.0, 0.0, 0.0), abs=0.01)
    res = run("mesh", ball_file, "--iso", 100, "--render", a, "--background-color", "5")
    assert res.code == 2 and "--background-color" in res.stderr


def test_warp_background_value_and_its_old_spelling(run, data_dir, tmp_path):
    spec = tmp_path / "w.yaml"
    spec.write_text("version: 1\nunits: voxel\ncapture: {lattice: 6, oversample: 1}\nsteps:\n"
                    "  - move:\n      - {index: [2, 2, 2], by: [1.5, 0, 0]}\n")
    src = data_dir / "ball_30_uint8.nrrd"
    new, old = tmp_path / "new.nrrd", tmp_path / "old.nrrd"
    # (the ball is a 0/200 mask: as intensities, on a grown grid, so [0, 0, 0] is padding)
    as_density = ("--values", "intensity", "--grid", "grow")
    res = run("warp", src, "--spec", spec, "-o", new, "--background-value", "250", *as_density)
    assert res.code == 0 and res.stderr == "", res.stderr
    res = run("warp", src, "--spec", spec, "-o", old, "--background", "250", *as_density)
    assert res.code == 0, res.stderr
    assert "volwarp: warning: --background is now --background-value" in res.stderr
    assert read_volume(new).data[0, 0, 0] == 250
    assert new.read_bytes() == old.read_bytes()
    res = run("warp", src, "--spec", spec, "-o", new, "--background", "nan")
    assert res.code == 2 and "'--background'" in res.stderr and "finite" in res.stderr


def test_morph_takes_the_shared_output_and_write_options(run, ball_file, tmp_path):
    """morph's -o is the shared output option (a pattern: its extension checked at once)
    with the shared --dtype/--compress/--byte-order."""
    cmd = command_of("morph")
    names = {p.name for p in cmd.params}
    assert {"output", "dtype", "compress", "byte_order", "render_size"} <= names
    res = run("morph", ball_file, ball_file, "--frames", 2, "--iso", 100,
              "-o", tmp_path / "f_{i}.nrrd", "--dtype", "int16", "--byte-order", "big")
    assert res.code == 0, res.stderr
    f0 = read_volume(tmp_path / "f_0.nrrd")
    assert f0.data.dtype == np.int16 and (f0.data < 0).any()
    assert b"endian: big" in (tmp_path / "f_0.nrrd").read_bytes()[:2000]
    res = run("morph", ball_file, ball_file, "--frames", 2, "--iso", 100,
              "-o", tmp_path / "g_{i}.xyz")
    assert res.code == 2 and "'-o'" in res.stderr
    assert not list(tmp_path.glob("g_*"))
