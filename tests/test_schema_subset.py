"""The fast schema check (spec/schema_subset.py) agrees with jsonschema, exactly."""

from __future__ import annotations

import copy
import datetime
import json
import math
import subprocess
import sys
from decimal import Decimal
from fractions import Fraction
from pathlib import Path

import jsonschema
import pytest
from hypothesis import HealthCheck, event, find, given, settings
from hypothesis import strategies as st

from volwarp_cli.spec.loader import parse_spec_text
from volwarp_cli.spec.schema_subset import is_valid

ROOT = Path(__file__).resolve().parent.parent
SCHEMAS = {p.name.split(".")[0]: json.loads(p.read_text())
           for p in sorted((ROOT / "volwarp_cli" / "schemas").glob("*.schema.json"))}
VALIDATORS = {kind: jsonschema.Draft202012Validator(s) for kind, s in SCHEMAS.items()}
#: (not the examples' outputs: `make examples` copies sweep specs into their out/ folders)
SPEC_FILES = sorted(p for folder in ("specs", "examples") for ext in ("yaml", "yml")
                    for p in (ROOT / folder).rglob(f"*.{ext}")
                    if "out" not in p.relative_to(ROOT).parts)
SPECS = {str(p.relative_to(ROOT)): parse_spec_text(p.read_text(), file=str(p)).data
         for p in SPEC_FILES}


def kind_of(name: str) -> str:
    """specs/<kind>-*.yaml; the examples' specs are all warp specs."""
    prefix = Path(name).name.split("-")[0]
    return prefix if prefix in SCHEMAS else "warp"


def agree(name, doc) -> bool:
    """is_valid == jsonschema for every schema; returns the verdict under the doc's kind."""
    for kind, schema in SCHEMAS.items():
        assert is_valid(doc, schema) is VALIDATORS[kind].is_valid(doc), (kind, doc)
    return VALIDATORS[kind_of(name)].is_valid(doc)


def test_the_project_specs_are_found():
    assert len(SPECS) >= 15 and {kind_of(n) for n in SPECS} == set(SCHEMAS)


def test_schemas_are_inside_the_subset():
    for schema in SCHEMAS.values():  # None would send every spec to jsonschema
        assert is_valid({}, schema) is False


@pytest.mark.parametrize("name", SPECS)
def test_project_specs(name):
    doc = SPECS[name]
    for kind, schema in SCHEMAS.items():
        assert is_valid(doc, schema) is VALIDATORS[kind].is_valid(doc), kind
    assert is_valid(doc, SCHEMAS[kind_of(name)]) is True


# --- random mutations of the project's specs -------------------------------------------

def _names(schema) -> list[str]:
    """Every property name and string constant of a schema (mutations that may stay valid)."""
    out: set = set()

    def walk(node):
        if isinstance(node, dict):
            out.update(node.get("properties", {}))
            out.update(v for v in node.get("enum", []) if isinstance(v, str))
            for value in node.values():
                walk(value)
        elif isinstance(node, list):
            for value in node:
                walk(value)
    walk(schema)
    return sorted(out)


NAMES = sorted({n for s in SCHEMAS.values() for n in _names(s)})
SCALARS = (st.none() | st.booleans() | st.integers(-3, 20) | st.integers()
           | st.sampled_from([0, -1, 1.0, 0.0, -0.0, 2.5, 4.0, 16, 16.5, 10000, 10001,
                              2**70, 1e308, float("inf"), float("nan"), True, False])
           | st.floats() | st.text(max_size=4) | st.sampled_from(NAMES + ["", "a b", "1"]))
VALUES = st.recursive(
    SCALARS,
    lambda inner: (st.lists(inner, max_size=5)
                   | st.lists(st.integers(-1, 12) | st.floats(-5, 30), min_size=2, max_size=5)
                   | st.dictionaries(st.sampled_from(NAMES) | st.text(max_size=3), inner,
                                     max_size=4)),
    max_leaves=8)


def _paths(node, path=()):
    yield path
    if isinstance(node, dict):
        for k, v in node.items():
            yield from _paths(v, path + (k,))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            yield from _paths(v, path + (i,))


def _at(doc, path):
    for part in path:
        doc = doc[part]
    return doc


@st.composite
def mutated(draw):
    name = draw(st.sampled_from(sorted(SPECS)))
    doc = copy.deepcopy(SPECS[name])
    for _ in range(draw(st.sampled_from([1, 1, 1, 2, 3]))):
        path = draw(st.sampled_from(list(_paths(doc))))
        node = _at(doc, path)
        op = draw(st.sampled_from(["delete", "add", "replace", "copy", "graft", "tweak"]))
        if op == "graft" and path:  # a value from a valid spec, often of the right shape
            other = SPECS[draw(st.sampled_from(sorted(SPECS)))]
            donor = _at(other, draw(st.sampled_from(list(_paths(other)))))
            _at(doc, path[:-1])[path[-1]] = copy.deepcopy(donor)
        elif op == "tweak" and path and isinstance(node, int | float):  # around the bounds
            _at(doc, path[:-1])[path[-1]] = draw(st.sampled_from(
                [node + 1, node - 1, -node, node * 1.0, 0, 0.5,
                 float(round(node)) if math.isfinite(node) else node]))  # an earlier nan/inf
        elif op == "delete" and path:
            del _at(doc, path[:-1])[path[-1]]
        elif op == "add" and isinstance(node, dict):
            node[draw(st.sampled_from(NAMES) | st.text(max_size=3))] = draw(VALUES)
        elif op == "add" and isinstance(node, list):
            node.insert(draw(st.integers(0, len(node))), draw(VALUES))
        elif op == "copy" and isinstance(node, list) and node:  # keeps items valid, resizes
            node.append(copy.deepcopy(draw(st.sampled_from(node))))
        elif path:
            _at(doc, path[:-1])[path[-1]] = draw(VALUES)
    return name, doc


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(mutated())
def test_mutated_specs_agree_with_jsonschema(sample):
    name, doc = sample
    event("valid" if agree(name, doc) else "invalid")


@pytest.mark.parametrize("want", [True, False])
def test_mutations_give_both_verdicts(want):
    def verdict(sample):
        name, doc = sample
        return doc != SPECS[name] and VALIDATORS[kind_of(name)].is_valid(doc) is want
    name, doc = find(mutated(), verdict, settings=settings(max_examples=500, database=None))
    assert is_valid(doc, SCHEMAS[kind_of(name)]) is want


# --- jsonschema's semantics, one trap at a time ---------------------------------------

@pytest.mark.parametrize("schema,instance", [
    ({"type": "integer"}, 1.0), ({"type": "integer"}, True), ({"type": "integer"}, 1.5),
    ({"type": "integer"}, 2**80), ({"type": "integer"}, float("inf")),
    ({"type": "number"}, True), ({"type": "number"}, False), ({"type": "number"}, 0),
    ({"type": "boolean"}, 0), ({"type": "null"}, None), ({"type": "null"}, 0),
    ({"type": ["string", "null"]}, None), ({"type": []}, 1), ({"type": "array"}, (1, 2)),
    ({"type": "object"}, []), ({"type": "string"}, b"ab"), ({"type": "number"}, Decimal("1.5")),
    ({"type": "integer"}, Fraction(2)), ({"minimum": 1}, Decimal("0.5")),
    ({"enum": [1]}, True), ({"enum": [True]}, 1), ({"enum": [1]}, 1.0), ({"enum": [0]}, False),
    ({"enum": [[1, 2]]}, [1.0, 2]), ({"enum": [[1, 2]]}, [True, 2]), ({"enum": [[1, 2]]}, (1, 2)),
    ({"enum": [[97, 98]]}, b"ab"), ({"enum": [{"a": 1}]}, {"a": 1.0}), ({"enum": [{"a": 1}]},
                                                                       {"a": True}),
    ({"const": 1}, True), ({"const": 1}, 1.0), ({"const": False}, 0), ({"const": None}, None),
    ({"const": "1"}, 1),
    ({"minimum": 4}, "a string"), ({"minimum": 4}, 3), ({"minimum": 4}, 4.0), ({"minimum": 4}, True),
    ({"minimum": 0}, float("nan")), ({"exclusiveMinimum": 0}, 0), ({"exclusiveMinimum": 0}, 1e-300),
    ({"exclusiveMaximum": 16}, 16), ({"maximum": 16}, 16.0), ({"maximum": 16}, 2**70),
    ({"minItems": 3}, "abc"), ({"minItems": 1}, []), ({"maxItems": 1}, [1, 2]),
    ({"minItems": 1}, {"a": 1}), ({"minLength": 2}, "é"), ({"minLength": 1}, "😀"),
    ({"minLength": 2}, ["a"]), ({"pattern": "^a"}, "ba"), ({"pattern": "b"}, "abc"),
    ({"pattern": "^a"}, 5), ({"minProperties": 1}, {}), ({"minProperties": 1}, []),
    ({"maxProperties": 1}, {"a": 1, "b": 2}),
    ({"propertyNames": {"pattern": "^[a-z]+$"}}, {"ab": 1, "Cd": 2}),
    ({"propertyNames": {"pattern": "^[a-z]+$"}}, {1: 1}),
    ({"propertyNames": {"type": "string"}}, {1: 1}),
    ({"required": ["a"]}, ["a"]), ({"required": ["a"]}, {"b": 1}),
    ({"properties": {"a": {"type": "string"}}}, {"a": 1}),
    ({"properties": {"a": {"type": "string"}}}, {1: 1}),
    ({"additionalProperties": False}, {}), ({"additionalProperties": False}, {"x": 1}),
    ({"properties": {"a": True}, "additionalProperties": {"type": "integer"}}, {"a": "s", "b": 1}),
    ({"properties": {"a": True}, "additionalProperties": {"type": "integer"}}, {"a": 1, "b": "s"}),
    ({"additionalProperties": {"type": "integer"}}, [1, "s"]),
    ({"items": {"type": "integer"}}, [1, 2.0, 3]), ({"items": {"type": "integer"}}, [1, "2"]),
    ({"items": False}, []), ({"items": False}, [1]), ({"items": {"type": "integer"}}, "ab"),
    ({"oneOf": [{"type": "integer"}, {"type": "number"}]}, 1),
    ({"oneOf": [{"type": "integer"}, {"type": "number"}]}, 1.5),
    ({"oneOf": [{"type": "integer"}, {"type": "number"}]}, "1"),
    ({"oneOf": [{"required": ["by"]}, {"required": ["to"]}]}, {"by": 1, "to": 1}),
    ({"oneOf": [{"required": ["by"]}, {"required": ["to"]}]}, []),
    ({"oneOf": [{"required": ["by"]}, {"required": ["to"]}]}, "not an object"),
    ({"anyOf": [{"type": "string"}, {"minimum": 3}]}, 2),
    ({"anyOf": [{"type": "string"}, {"minimum": 3}]}, None),
    ({"not": {"required": ["a", "b"]}}, {"a": 1}), ({"not": {"required": ["a", "b"]}},
                                                     {"a": 1, "b": 2}),
    ({"not": {"required": ["a"]}}, 5), ({"not": True}, 1), ({"not": False}, 1),
    ({"$defs": {"n": {"type": "number"}}, "$ref": "#/$defs/n", "minimum": 2}, 1),
    ({"$defs": {"n": {"type": "number"}}, "$ref": "#/$defs/n", "minimum": 2}, "x"),
    ({"$defs": {"n": {"type": "number"}}, "$ref": "#/$defs/n", "minimum": 2}, 3),
    ({"$defs": {"a/b": {"type": "number"}}, "$ref": "#/$defs/a~1b"}, "x"),
    ({"$defs": {"a%b": {"type": "number"}}, "$ref": "#/$defs/a%25b"}, "x"),
    ({"anyOf": [{"type": "null"}, {"type": "number"}], "$ref": "#/anyOf/1"}, None),
    ({"type": "object", "properties": {"n": {"$ref": "#"}}}, {"n": {"n": {"n": 1}}}),
    ({"type": "object", "properties": {"n": {"$ref": "#"}}}, {"n": {"n": {}}}),
    ({"$id": "https://example/x.json", "$defs": {"n": {"type": "number"}},
      "items": {"$ref": "#/$defs/n"}}, [1, "2"]),
    ({"description": "d", "default": 3, "title": "t", "$comment": "c", "examples": [1]}, "x"),
    ({"type": "string"}, datetime.date(2024, 1, 2)), ({"enum": ["2024-01-02"]},
                                                       datetime.date(2024, 1, 2)),
    ({"type": "array"}, {1, 2}), ({"minimum": 1}, datetime.date(2024, 1, 2)),
    (True, 1), (False, None), ({}, {"anything": [1]}),
])
def test_traps(schema, instance):
    expected = jsonschema.Draft202012Validator(schema).is_valid(instance)
    assert is_valid(instance, schema) is expected


def test_traps_verdicts():  # the traps above, spelled out
    assert is_valid(1.0, {"type": "integer"}) is True
    assert is_valid(True, {"type": "integer"}) is False
    assert is_valid(True, {"enum": [1]}) is False
    assert is_valid(1.0, {"const": 1}) is True
    assert is_valid("a string", {"type": "string", "minimum": 4}) is True
    assert is_valid(1, {"oneOf": [{"type": "integer"}, {"type": "number"}]}) is False
    assert is_valid(1, True) is True and is_valid(1, False) is False
    assert is_valid({"a": 1, "b": "s"}, {"additionalProperties": {"type": "integer"}}) is False


@pytest.mark.parametrize("schema", [
    {"type": "string", "format": "date"},
    {"prefixItems": [{"type": "integer"}]},
    {"items": [{"type": "integer"}]},
    {"patternProperties": {"^a": {}}, "additionalProperties": False},
    {"$ref": "https://example.com/other.json#/$defs/x"},
    {"$ref": "other.json"},
    {"$ref": "#anchor", "$defs": {"x": {"$anchor": "anchor"}}},
    {"$ref": "#/$defs/missing"},
    {"properties": {"a": {"allOf": [{"type": "integer"}]}}},
    {"$defs": {"unused": {"uniqueItems": True}}},
    {"$defs": {"x": {"$id": "x.json", "type": "integer"}}, "$ref": "#/$defs/x"},
    {"type": "float"},
    {"unknownKeyword": 1},
])
def test_unsupported_keywords_cannot_decide(schema):
    assert is_valid({"a": [1]}, schema) is None
    assert is_valid(5, schema) is None


def test_self_containing_yaml_value_is_left_to_jsonschema():
    import yaml

    doc = yaml.safe_load("a: &x [*x]\n")
    assert is_valid(doc, {"$defs": {"l": {"items": {"$ref": "#/$defs/l"}}},
                          "properties": {"a": {"$ref": "#/$defs/l"}}}) is None


# --- validate(): no jsonschema import for a valid spec, the same errors otherwise -----

WARP_BALL = ROOT / "specs" / "warp-ball.yaml"
BAD = {  # message recorded from validate() before the fast path existed
    ("colour: red\n", None):
        "bad.yaml:17: colour: unknown key 'colour' (allowed: background, capture, "
        "evaluator, grid, pushforward, steps, units, values, version)",
    ("version: 1", "version: '1'"): "bad.yaml:3: version: 1 was expected",
    ("frames: 4", "frames: true"): "bad.yaml:16: steps[1].frames: True is not of type 'integer'",
    ("[4, 6, 5]", "[4, 6.5, 5]"):
        "bad.yaml:11: steps[0].move[1].index[1]: 6.5 is not of type 'integer'",
    ("by: [0.0, -3.0, 0.0]", "by: [0.0, -3.0, 0.0], to: [1, 2, 3]"):
        "bad.yaml:10: steps[0].move[0]: {'index': [4, 6, 4], 'by': [0.0, -3.0, 0.0], "
        "'to': [1, 2, 3]} is valid under each of {'required': ['to']}, {'required': ['by']}",
}
SCRIPT = """
import json, sys
from pathlib import Path
from volwarp_cli.errors import SpecError
from volwarp_cli.spec.loader import load_schema, load_spec, parse_spec_text, validate

validate(load_spec(sys.argv[1]), load_schema("warp"))
validate(parse_spec_text(Path(sys.argv[1]).read_text().replace("[4, 6, 5]", "[4, 6.0, 5]")),
         load_schema("warp"))
out = {"imported": "jsonschema" in sys.modules, "errors": []}
for text in json.loads(sys.argv[2]):
    try:
        validate(parse_spec_text(text, file="bad.yaml"), load_schema("warp"))
        out["errors"].append(None)
    except SpecError as exc:
        out["errors"].append(str(exc))
out["imported_after"] = "jsonschema" in sys.modules
print(json.dumps(out))
"""


def test_validate_skips_jsonschema_for_valid_specs_and_keeps_its_errors():
    text = WARP_BALL.read_text()
    bad = [text + old if new is None else text.replace(old, new) for old, new in BAD]
    assert all(b != text for b in bad)
    proc = subprocess.run([sys.executable, "-c", SCRIPT, str(WARP_BALL), json.dumps(bad)],
                          cwd=ROOT, capture_output=True, text=True, check=True)
    out = json.loads(proc.stdout)
    assert out["imported"] is False
    assert out["errors"] == list(BAD.values())
    assert out["imported_after"] is True


def test_validate_falls_back_to_jsonschema_when_undecided():
    from volwarp_cli.errors import SpecError
    from volwarp_cli.spec.loader import validate

    schema = {"type": "object", "properties": {"n": {"prefixItems": [{"type": "integer"}]}}}
    validate(parse_spec_text("n: [1, 'x']\n"), schema)
    with pytest.raises(SpecError, match="is not of type 'integer'"):
        validate(parse_spec_text("n: ['x', 1]\n"), schema)
