"""Bad or unusual spec input: YAML 1.2 floats, non-finite numbers, alias bombs, deep
nesting, odd tags and keys, and error messages that stay one short line."""

from __future__ import annotations

import datetime
import json
import re
import time

import pytest
import yaml

from volwarp_cli.errors import SpecError
from volwarp_cli.spec import load_schema, load_spec, parse_spec_text, validate
from volwarp_cli.spec.loader import MAX_DEPTH, MAX_MESSAGE, MAX_QUOTE, MAX_VALUES

WARP = load_schema("warp")


def move_by(x: str) -> str:
    """A warp spec whose by[0] (line 4) is the YAML text ``x``."""
    return ("version: 1\nunits: voxel\nsteps:\n"
            f"  - move: [{{index: [2, 2, 2], by: [{x}, 0, 0]}}]\n")


def refused(text: str, schema: dict | None = None) -> SpecError:
    with pytest.raises(SpecError) as info:
        doc = parse_spec_text(text, file="s.yaml")
        if schema is not None:
            validate(doc, schema)
    return info.value


def short_line(err: SpecError) -> None:
    text = str(err)
    assert "\n" not in text
    assert len(err.message) <= MAX_MESSAGE
    assert len(text) < MAX_MESSAGE + 200


# --- 1. YAML 1.2 / JSON floats are numbers ------------------------------------------

@pytest.mark.parametrize("text, value", [
    ("1e1", 10.0), ("1E+3", 1000.0), ("-2.5e-05", -2.5e-05), (".5", 0.5), ("5.", 5.0),
    ("-.5", -0.5), ("+.5", 0.5), ("+1e2", 100.0), ("1.5e5", 150000.0), ("1e-05", 1e-05),
    ("0.0e0", 0.0), ("1.e3", 1000.0),
])
def test_yaml12_floats_are_numbers(text, value):
    doc = parse_spec_text(move_by(text))
    got = doc.data["steps"][0]["move"][0]["by"][0]
    assert type(got) is float and got == value
    validate(doc, WARP)  # was: '1e1' is not of type 'number'


def test_a_spec_written_by_json_dumps_loads(tmp_path):
    spec = {"version": 1, "units": "voxel", "background": 1e-05,
            "steps": [{"move": [{"index": [2, 2, 2], "by": [1e-05, -2.5e-05, 1e20]}]}]}
    path = tmp_path / "w.yaml"
    path.write_text(json.dumps(spec, indent=1))
    assert "1e-05" in path.read_text() and "1e+20" in path.read_text()
    doc = load_spec(path, "warp")
    assert doc.data == spec
    lines = path.read_text().splitlines()
    assert doc.line(("steps", 0, "move", 0, "by", 1)) == next(
        n for n, line in enumerate(lines, 1) if "-2.5e-05" in line)


@pytest.mark.parametrize("text", [
    "yes", "no", "on", "off", "true", "y", "n", "~", "null", "089", "0x1f",
    "12", "-12", "1.0", "1.0e+5", "1.0e5x", "1e", "e5",
    ".e5", "1e5.5", "1..5", ".", "+.", "'1e1'", '"1e1"', "2001-12-14", ".nan_", "1 e5",
    "1e+", "0.5.1", "!!str 1e1", "+", "-1", "+1", ".0", "0.", "1_0e1",
])
def test_other_scalars_resolve_as_pyyaml_does(text):
    """Only YAML 1.2 floats changed: everything else reads as PyYAML's safe_load reads it."""
    got = parse_spec_text(f"a: {text}\n").data["a"]
    want = yaml.safe_load(f"a: {text}\n")["a"]
    assert got == want and type(got) is type(want)


@pytest.mark.parametrize("text", ["0123", "0b11", "1_000", "1_000.5", "1:30", "1:30.5"])
def test_numbers_only_yaml_1_1_reads_so_are_refused(text):
    """A leading zero (0123 is 83), sexagesimal, underscores, binary: numbers to PyYAML's
    YAML 1.1, others (or strings) to YAML 1.2 and JSON; a spec error, not a guess."""
    with pytest.raises(SpecError, match=rf"a: {re.escape(text)} is .* to YAML 1\.1"):
        parse_spec_text(f"a: {text}\n", "x.yaml")


def test_yes_and_on_stay_booleans_and_timestamps_stay_dates():
    data = parse_spec_text("a: yes\nb: on\nc: 2001-12-14\nd: '1e1'\n").data
    assert data == {"a": True, "b": True, "c": datetime.date(2001, 12, 14), "d": "1e1"}


def test_lines_are_still_tracked():
    text = "version: 1\nsteps:\n  - move:\n      - index: [1, 2, 3]\n        by: [1e1, 0, 0]\n"
    doc = parse_spec_text(text)
    assert doc.line(("steps", 0, "move", 0, "by")) == 5
    assert doc.line(("steps", 0, "move", 0, "by", 0)) == 5
    assert doc.line(("steps", 0, "move", 0, "index")) == 4
    assert doc.line(("steps", 0, "move", 0, "nothing", 3)) == 4  # nearest ancestor
    assert doc.line(()) == 1


# --- 2. non-finite numbers are spec errors, with key path and line --------------------

@pytest.mark.parametrize("text", [
    ".nan", ".NaN", ".NAN", ".inf", "-.inf", "+.Inf", ".INF", "1e999", "-1.0e+999",
    "!!float nan", "!!float -infinity", "!!float .inf",
])
def test_non_finite_numbers_are_refused(text):
    err = refused(move_by(text))
    assert err.key == "steps[0].move[0].by[0]" and err.line == 4
    assert "must be a finite number" in err.message
    short_line(err)


@pytest.mark.parametrize("text, key, line", [
    ("version: 1\nsteps:\n  - drag:\n      - {from: [10, .nan, 10], to: [11, 10, 10]}\n",
     "steps[0].drag[0].from[1]", 4),
    ("version: 1\nsteps:\n  - move:\n      - {index: [2, 2, 2], to: [.nan, 0, 0]}\n",
     "steps[0].move[0].to[0]", 4),
    ("version: 1\nbackground: .nan\nsteps: []\n", "background", 2),
    ("version: 1\nsteps:\n  - drag: []\n    radius: .inf\n", "steps[0].radius", 4),
    ("version: 1\nx: &v .inf\nsteps:\n  - radius: *v\n", "x", 2),  # first use, at the anchor
    ("version: 1\nsteps: []\n.nan: 1\n", ".nan", 3),  # a key
])
def test_non_finite_numbers_are_refused_anywhere(text, key, line):
    err = refused(text)
    assert (err.key, err.line) == (key, line)
    assert "must be a finite number" in err.message


def test_background_nan_keeps_its_wording():
    err = refused("version: 1\nbackground: .nan\nsteps: []\n")
    assert str(err) == "s.yaml:2: background: must be a finite number, got .nan"


def test_integers_beyond_floats_are_refused_and_big_finite_numbers_load():
    err = refused(move_by("1" + "0" * 400))
    assert err.key == "steps[0].move[0].by[0]" and "too large" in err.message
    short_line(err)
    err = refused(move_by("9" * 5000))  # beyond Python's int() digit limit
    assert err.key == "steps[0].move[0].by[0]" and "cannot read" in err.message
    short_line(err)
    for text in ("1e300", "-1.5e-300", "5e-324", "1.7976931348623157e308", "1" + "0" * 300):
        validate(parse_spec_text(move_by(text)), WARP)


# --- 3. alias expansion is bounded; quoted values are cut short -----------------------

def bomb(levels: int, width: int, key: str = "name") -> str:
    lines = ["version: 1", "steps:", f"  - {key}: &a0 [{', '.join(['lol'] * width)}]",
             "    move: [{index: [2, 2, 2], by: [1, 0, 0]}]"]
    for i in range(1, levels):
        lines.append(f"  - {key}: &a{i} [{', '.join([f'*a{i - 1}'] * width)}]")
    return "\n".join(lines) + "\n"


def test_an_alias_bomb_is_refused_at_once():
    text = bomb(6, 10)  # 10**6 leaves: just over the limit
    start = time.perf_counter()
    err = refused(text)
    assert time.perf_counter() - start < 1.0
    assert err.message == f"spec too large (aliases expand to over {MAX_VALUES} values)"
    assert err.key == "steps[5].name" and err.line == 9  # the first part over the limit
    short_line(err)
    start = time.perf_counter()
    err = refused(bomb(30, 10))  # 10**30 values: the same answer, as fast
    assert time.perf_counter() - start < 1.0 and err.key == "steps[5].name"


def test_a_large_literal_list_is_refused_too(monkeypatch):
    from volwarp_cli.spec import loader

    monkeypatch.setattr(loader, "MAX_VALUES", 1000)  # (a million values parse slowly)
    parse_spec_text("version: 1\nsteps: []\nx: [" + ",".join(["1"] * 990) + "]\n")
    err = refused("version: 1\nsteps: []\nx: [" + ",".join(["[1, 2]"] * 400) + "]\n")
    assert err.key == "x" and err.line == 3
    assert err.message == "spec too large (over 1000 values)"


def test_expanded_values_in_messages_are_cut_short():
    text = bomb(5, 9)  # ~66 000 values, under the limit: a schema error quoting them
    err = refused(text, WARP)
    assert err.key.startswith("steps[") and err.key.endswith("].name")
    assert "is not of type 'string'" in err.message and "..." in err.message
    short_line(err)  # was a 428 KB line


@pytest.mark.parametrize("text, key, needle", [
    ("version: 1\nsteps:\n  - name: [" + "1, " * 5000 + "1]\n", "steps[0].name",
     "is not of type 'string'"),
    ("version: 1\nsteps: []\n" + "k" * 1000 + ": 1\n", "k" * 37 + "...", "unknown key 'kkk"),
    ("version: 1\nsteps: []\nunits: " + "w" * 5000 + "\n", "units", "is not one of"),
    ("version: 1\nsteps: []\n" + "k" * 1000 + ": 1\n" + "k" * 1000 + ": 2\n", "k" * 37 + "...",
     "duplicate key"),
    ("version: 1\nsteps: []\nx: *" + "a" * 5000 + "\n", None, "YAML syntax error"),
])
def test_long_values_are_cut_short_in_messages(text, key, needle):
    err = refused(text, WARP)
    assert err.key == key and needle in err.message
    short_line(err)
    assert len(err.message) < MAX_QUOTE + 150


def test_doc_error_messages_are_cut_short():
    doc = parse_spec_text("version: 1\nsteps: []\n", file="s.yaml")
    err = doc.error(("steps",), "x" * 10000)
    assert err.key == "steps" and err.line == 2 and len(err.message) == MAX_MESSAGE
    short_line(err)


def test_a_recursive_alias_is_refused():
    err = refused("version: 1\nsteps: &s\n  - move: *s\n")
    assert err.key == "steps[0].move" and "recursive" in err.message


def test_deep_nesting_is_refused_and_the_limit_itself_validates():
    ok = "version: 1\nsteps: " + "[" * (MAX_DEPTH - 1) + "]" * (MAX_DEPTH - 1) + "\n"
    err = refused(ok, WARP)  # a schema error, not a RecursionError
    assert err.key == "steps[0]" and "..." in err.message
    for depth in (MAX_DEPTH, 100_000):
        start = time.perf_counter()
        err = refused("version: 1\nsteps: " + "[" * depth + "]" * depth + "\n")
        assert time.perf_counter() - start < 2.0
        assert err.line == 2 and f"nested more than {MAX_DEPTH} levels deep" in err.message
        assert err.key.startswith("steps[0][0]")
        short_line(err)
    chain = "".join(f"x{i}: &a{i} [*a{i - 1}]\n" for i in range(1, MAX_DEPTH + 5))
    err = refused("version: 1\nsteps: []\nx0: &a0 [1]\n" + chain)  # deep through aliases
    assert "nested more than" in err.message and err.key.startswith(f"x{MAX_DEPTH + 4}[0]")


@pytest.mark.parametrize("text, key, needle", [
    (move_by("!!float abc"), "steps[0].move[0].by[0]", "cannot read 'abc' as !!float"),
    (move_by("!!int 1.5"), "steps[0].move[0].by[0]", "cannot read '1.5' as !!int"),
    (move_by("!foo 1"), "steps[0].move[0].by[0]", "could not determine a constructor"),
    ("version: !!python/tuple [1]\nsteps: []\n", "version", "cannot read a sequence tagged"),
    ("version: 1\nsteps: !foo {}\n", "steps", "cannot read a mapping tagged '!foo'"),
    ("version: 1\nsteps: []\n? [a]\n: 1\n", None, "a key must be a name"),
    ("version: 1\nsteps: []\ntrue: 1\n1: 2\n", "1", "duplicate key '1'"),  # the dict keeps one
])
def test_odd_tags_and_keys_are_spec_errors(text, key, needle):
    err = refused(text)
    assert err.key == key and needle in err.message and err.line is not None


# --- the command line: exit 2, one line with key path and line, nothing written --------

@pytest.mark.parametrize("text, where", [
    (move_by(".nan"), ":4: steps[0].move[0].by[0]: must be a finite number, got .nan"),
    (bomb(9, 9), ":10: steps[6].name: spec too large (aliases expand to over "),
])
def test_cli_refuses_bad_specs_with_one_line(run, data_dir, tmp_path, text, where):
    spec = tmp_path / "s.yaml"
    spec.write_text(text)
    out = tmp_path / "o.nrrd"
    start = time.perf_counter()
    res = run("warp", data_dir / "ball_30_uint8.nrrd", "--spec", spec, "-o", out)
    assert time.perf_counter() - start < 5.0
    assert res.code == 2, res.stderr
    assert res.stderr.count("\n") == 1 and len(res.stderr) < 400
    assert res.stderr.startswith(f"volwarp: error: {spec}{where}")
    assert not out.exists()


def test_cli_reads_a_yaml12_float(run, data_dir, tmp_path):
    spec = tmp_path / "s.yaml"
    spec.write_text(move_by("1e0"))
    out = tmp_path / "o.nrrd"
    res = run("warp", data_dir / "ball_30_uint8.nrrd", "--spec", spec, "-o", out)
    assert res.code == 0, res.stderr
    assert out.exists()
