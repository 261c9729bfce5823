"""Large specs are composed by libyaml: the same data, the same lines and the same errors
as the pure-Python loader."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

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
