"""Specs are read from libyaml's events (plain ones) or composed by libyaml: the same data,
the same lines and the same errors as the pure-Python loader."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from volwarp_cli.errors import SpecError
from volwarp_cli.spec import loader

ROOT = Path(__file__).resolve().parents[1]
SPECS = sorted((ROOT / "specs").glob("*.yaml"))
PAD = "# padding\n" * 1000  # past FAST_MIN_BYTES: the libyaml path

pytestmark = pytest.mark.skipif(loader._FastSpecLoader is None, reason="PyYAML without libyaml")


def paths(data, prefix=()):
    if isinstance(data, dict):
        for k, v in data.items():
            yield prefix + (k,)
            yield from paths(v, prefix + (k,))
    elif isinstance(data, list):
        for i, v in enumerate(data):
            yield prefix + (i,)
            yield from paths(v, prefix + (i,))


def both(text, monkeypatch):
    fast = loader.parse_spec_text(text, "s.yaml")
    monkeypatch.setattr(loader, "FAST_MIN_BYTES", 1 << 60)
    slow = loader.parse_spec_text(text, "s.yaml")
    monkeypatch.undo()
    return fast, slow


@pytest.mark.parametrize("spec", SPECS, ids=lambda p: p.name)
def test_same_data_and_lines(spec, monkeypatch):
    text = PAD + spec.read_text()
    assert len(text) >= loader.FAST_MIN_BYTES
    fast, slow = both(text, monkeypatch)
    assert fast.data == slow.data
    keys = list(paths(slow.data))
    assert keys and [fast.line(k) for k in keys] == [slow.line(k) for k in keys]


def test_yaml_12_floats_and_big_move_lists(monkeypatch):
    moves = "".join(f"      - {{index: [{i % 9}, {i // 9 % 9}, 0], by: [1e-05, 2E+1, -.5]}}\n"
                    for i in range(400))
    text = f"version: 1\nsteps:\n  - move:\n{moves}"
    fast, slow = both(text, monkeypatch)
    assert fast.data == slow.data
    assert fast.data["steps"][0]["move"][3]["by"] == [1e-05, 20.0, -0.5]


@pytest.mark.parametrize("bad", [
    "version: 1\nsteps: [\n",                       # syntax error
    "version: 1\na: 1\na: 2\n",                     # duplicate key
    "version: 1\nx: .nan\n",                        # not finite
    "version: 1\nx: " + "[" * 70 + "]" * 70 + "\n",  # too deep
    "version: 1\nx: !!float abc\n",                 # a tag that cannot read its value
])
def test_same_errors(bad, monkeypatch):
    text = PAD + bad
    errors = []
    for threshold in (0, 1 << 60):
        monkeypatch.setattr(loader, "FAST_MIN_BYTES", threshold)
        with pytest.raises(SpecError) as info:
            loader.parse_spec_text(text, "s.yaml")
        errors.append(str(info.value))
    assert errors[0] == errors[1]


def test_the_fast_path_is_taken(monkeypatch):
    made = []
    real = loader._FastSpecLoader

    class Spy(real):
        def __init__(self, stream):
            made.append(1)
            super().__init__(stream)

    monkeypatch.setattr(loader, "_FastSpecLoader", Spy)
    loader.parse_spec_text(PAD + "version: 1\n", "s.yaml")
    assert made
    assert isinstance(yaml.CSafeLoader, type)


# Plain scalars whose type YAML 1.1 (and the spec's 1.2 floats) decide by their text, and
# (fewer) texts that are not plain data or not YAML.
SCALARS = ["yes", "No", "on", "OFF", "y", "~", "null", "Null", "true", "False", "1e5", "1.5e5",
           "-.5", "+.5", ".5", "3.", "-0", "+1", "0x1F", "0o17", "017", "089", "0b101",
           "1_000", "1:30", "-1:30.5", "2001-12-14", "2001-12-14t21:59:43.10-05:00", "=",
           "abc", "a b", "é", "'q'", '"d"', "'1'", '"yes"', "1.0", "12", "[1, 2]", "{a: 1}"]
HAZARDS = [".inf", "-.Inf", ".NaN", "1e999", "9" * 400, "<<", "&x 1", "*x", "!!str 5",
           "!!float 1", "!!int 1.5", "a: b", "- x", "[", "'q"]
KEYS = st.sampled_from(["a", "b", "c", "d", "e", "1", "2", "yes", "true", "~", "1.0", "'a'"] * 4
                      + ["<<", "=", "[x]"])
TEXTS = st.sampled_from(SCALARS * 6 + HAZARDS)


def typed(value):
    """``value`` with every scalar's type kept apart (``1 == True == 1.0`` in Python)."""
    if isinstance(value, dict):
        return ("map", [(typed(k), typed(v)) for k, v in value.items()])
    if isinstance(value, list):
        return ("seq", [typed(v) for v in value])
    return (type(value).__name__, repr(value))


def _block(draw, depth, indent):
    pad = " " * indent
    lines = []
    distinct = draw(st.integers(0, 9)) > 0  # (else duplicate keys are likely)
    for key in draw(st.lists(KEYS, min_size=1, max_size=3, unique=distinct)):
        if depth < 3 and draw(st.booleans()):
            if draw(st.booleans()):
                lines.append(f"{pad}{key}:")
                lines.extend(_block(draw, depth + 1, indent + 2))
            else:
                items = draw(st.lists(TEXTS, min_size=0, max_size=3))
                lines.append(f"{pad}{key}: [{', '.join(items)}]")
        elif depth < 3 and draw(st.booleans()):
            lines.append(f"{pad}{key}:")
            for item in draw(st.lists(TEXTS, min_size=1, max_size=3)):
                lines.append(f"{pad}  - {item}")
        else:
            lines.append(f"{pad}{key}: {draw(TEXTS)}")
    return lines


@st.composite
def spec_texts(draw):
    head = draw(st.sampled_from(["", "", "", "---\n", "version: 1\n", "- 1\n", "%YAML 1.1\n---\n"]))
    tail = draw(st.sampled_from(["", "", "", "", "", "...\n", "---\nb: 2\n", "x: &r [1]\ny: *r\n"]))
    return head + "\n".join(_block(draw, 0, 0)) + "\n" + tail


def _outcome(text, threshold):
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(loader, "FAST_MIN_BYTES", threshold)
        try:
            doc = loader.parse_spec_text(text, "s.yaml")
        except SpecError as exc:
            return "error", str(exc)
    keys = list(paths(doc.data))
    return typed(doc.data), [doc.line(k) for k in keys]


@settings(max_examples=300, deadline=None)
@given(text=spec_texts())
def test_events_read_what_the_python_loader_reads(text):
    """Data with types and lines, or the error word for word: as the pure-Python loader."""
    assert _outcome(text, 0) == _outcome(text, 1 << 60)


def test_a_plain_spec_is_read_from_events_and_composed_only_for_a_line(monkeypatch):
    text = SPECS[0].read_text()
    composed = []
    real = loader._compose
    monkeypatch.setattr(loader, "_compose", lambda t: composed.append(1) or real(t))
    doc = loader.parse_spec_text(text, "s.yaml")
    assert not composed  # (the data came from the events)
    key = list(paths(doc.data))[-1]
    line = doc.line(key)
    assert composed == [1] and doc.line(key) == line and composed == [1]
    monkeypatch.undo()
    monkeypatch.setattr(loader, "FAST_MIN_BYTES", 1 << 60)
    assert loader.parse_spec_text(text, "s.yaml").line(key) == line


@pytest.mark.parametrize("text", [
    "a: &x [1, 2]\nb: *x\n",          # an alias
    "base: &b {k: 1}\nm:\n  <<: *b\n  j: 2\n",  # a merge
    "a: !!str 5\n",                    # a tag
    "[1, 2]: 3\n",                     # a list as a key
    "a: 1\n---\nb: 2\n",               # two documents
])
def test_what_is_not_plain_goes_to_the_composing_loader(text, monkeypatch):
    assert loader._plain_data(text) is loader._NOT_PLAIN
    assert _outcome(text, 0) == _outcome(text, 1 << 60)


def test_a_spec_read_from_events_pickles_with_its_lines():
    """A manifest's SpecDoc travels to batch workers: plain pickle, lines still answered."""
    import pickle

    doc = loader.parse_spec_text("version: 1\nsteps:\n  - move: []\n  - drag: []\n", "s.yaml")
    back = pickle.loads(pickle.dumps(doc))
    assert back.data == doc.data and back.line(("steps", 1)) == 4 == doc.line(("steps", 1))


@pytest.mark.parametrize("bad", ["\x07", "\x1b", "\ufffe", "\x7f"])
def test_an_unprintable_character_is_named_by_the_python_reader(bad, monkeypatch):
    """PyYAML's pure-Python reader (its check compiled at first use, not at import) names
    the character, for a short spec and a long one read by libyaml first."""
    import yaml.reader

    for text in (f"version: 1\nx: a{bad}b\n", PAD + f"version: 1\nx: a{bad}b\n"):
        with pytest.raises(SpecError, match=f"unacceptable character #x{ord(bad):04x}"):
            loader.parse_spec_text(text, "s.yaml")
    assert yaml.reader.Reader.NON_PRINTABLE.search(f"ok{bad}").start() == 2
    assert yaml.reader.Reader.NON_PRINTABLE.search("plain text\t\n") is None


def test_a_lone_surrogate_is_a_spec_error():
    """libyaml cannot take one (UnicodeEncodeError): the Python loader words the error."""
    with pytest.raises(SpecError, match="unacceptable character"):
        loader.parse_spec_text("a: \ud800\n", "s.yaml")


NUMBERISH = st.text(alphabet="0123456789-+._eE", min_size=1, max_size=8)


@settings(max_examples=300, deadline=None)
@given(texts=st.lists(st.one_of(NUMBERISH, st.sampled_from([
    "-0", "0.0", "-0.0", "007", "010", "-010", "089", "01.5", "-00.5", "00", "1.", "-1.",
    ".5", "+1.5", "+7", "1_0.5", "1.5_0", "1_000",
    "0.1234567890123456789", "-9" * 30 + ".5", "9" * 400, "9" * 400 + ".0"])),
    min_size=1, max_size=12))
def test_numbers_read_from_events_are_the_resolvers(texts):
    """Plain decimals and integers, read by float() and int() without the resolvers: the
    same values and types as the pure-Python loader's resolvers and constructors give."""
    text = "x: [" + ", ".join(texts) + "]\ny:\n" + "".join(f"  - {t}\n" for t in texts)
    assert _outcome(text, 0) == _outcome(text, 1 << 60)


def test_the_lazily_compiled_check_copies_and_pickles_as_the_expression():
    import copy
    import pickle

    import yaml.reader

    check = yaml.reader.Reader.NON_PRINTABLE
    for other in (copy.copy(check), copy.deepcopy(check), pickle.loads(pickle.dumps(check))):
        assert other.search("ok\x07").start() == 2 and other.search("plain") is None


def test_yaml_blocked_or_imported_elsewhere_is_imported_as_an_import_statement_would(monkeypatch):
    """Once PyYAML is in sys.modules (or being imported by another thread), the loader's
    import is a plain ``import yaml``: it waits for that import, and a blocked one fails."""
    import yaml

    assert loader._import_yaml() is yaml
    monkeypatch.setitem(__import__("sys").modules, "yaml", None)
    with pytest.raises(ImportError):
        loader._import_yaml()
