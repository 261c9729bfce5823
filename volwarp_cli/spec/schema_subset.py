"""A fast exact check of a spec against the subset of JSON Schema our schemas use.

Importing jsonschema (and with it referencing, rpds, attrs and
jsonschema_specifications) costs ~0.1 s of every spec command, to check a small
spec that is nearly always valid. :func:`is_valid` gives the verdict
``jsonschema.Draft202012Validator(schema).is_valid(instance)`` would, for the
keywords listed below only, without importing it. jsonschema stays the reference
and the error reporter: :func:`..loader.validate` calls it whenever this check
does not answer True.

Semantics follow jsonschema 4 (``_keywords.py``, ``_types.py``, ``_utils.py``):
a keyword constrains only instances of its type; ``integer`` accepts 1.0 and
neither ``integer`` nor ``number`` accepts bools; ``enum``/``const`` tell True
from 1 but not 1 from 1.0.
"""

from __future__ import annotations

import numbers
import re
from collections.abc import Mapping, Sequence
from urllib.parse import unquote

_ANNOTATIONS = {"description", "default", "title", "$schema", "$id", "$comment", "examples"}
_SUPPORTED = _ANNOTATIONS | {
    "type", "$ref", "$defs", "properties", "required", "additionalProperties", "items",
    "minItems", "maxItems", "enum", "const", "oneOf", "anyOf", "not", "minimum", "maximum",
    "exclusiveMinimum", "exclusiveMaximum", "minProperties", "maxProperties", "minLength",
    "pattern", "propertyNames",
}
_TYPES = ("object", "array", "string", "null", "boolean", "number", "integer")


class _Undecidable(Exception):
    pass


def is_valid(instance, schema: dict) -> bool | None:
    """The jsonschema 2020-12 verdict on ``instance``, or None if this subset cannot tell."""
    try:
        _check(schema, schema, set())
        return _valid(instance, schema, schema)
    except Exception:  # anything odd (a self-containing YAML value: RecursionError,
        return None  # a malformed schema): jsonschema decides, and raises as it did


def _resolve(ref, root):
    """The target of a local ``#/a/b`` reference (as referencing resolves it)."""
    if not isinstance(ref, str) or not ref.startswith("#") or ref[1:2] not in ("", "/"):
        raise _Undecidable(ref)
    node = root
    for part in unquote(ref[2:]).split("/") if len(ref) > 1 else ():
        try:
            node = node[int(part)] if isinstance(node, Sequence) else node[
                part.replace("~1", "/").replace("~0", "~")]
        except (LookupError, TypeError, ValueError):
            raise _Undecidable(ref) from None
    return node


def _check(schema, root, seen):
    """Raise _Undecidable if ``schema`` (or any subschema) leaves the subset."""
    if isinstance(schema, bool) or id(schema) in seen:
        return
    if not isinstance(schema, dict) or not schema.keys() <= _SUPPORTED or (
            "$id" in schema and schema is not root):  # a nested $id moves the base URI
        raise _Undecidable(schema)
    seen.add(id(schema))
    types = schema.get("type", ())
    if not all(t in _TYPES for t in ([types] if isinstance(types, str) else types)):
        raise _Undecidable(types)
    subs = [schema.get(k, True) for k in ("additionalProperties", "items", "not",
                                          "propertyNames")]
    for k in ("properties", "$defs"):
        subs += schema.get(k, {}).values()
    subs += schema.get("oneOf", []) + schema.get("anyOf", [])
    if "$ref" in schema:
        subs.append(_resolve(schema["$ref"], root))
    for sub in subs:
        _check(sub, root, seen)


def _is_type(x, t):
    if t == "object":
        return isinstance(x, dict)
    if t == "array":
        return isinstance(x, list)
    if t == "string":
        return isinstance(x, str)
    if t == "null":
        return x is None
    if t == "boolean" or isinstance(x, bool):
        return isinstance(x, bool) and t == "boolean"
    if t == "number":
        return isinstance(x, numbers.Number)
    return isinstance(x, int) or (isinstance(x, float) and x.is_integer())  # integer


def _equal(a, b):
    """Equality as jsonschema's ``_utils.equal`` has it: 1 == 1.0, True != 1.

    Lists and dicts are compared recursively.
    """
    if a is b:
        return True
    if isinstance(a, str) or isinstance(b, str):
        return a == b
    if isinstance(a, Sequence) and isinstance(b, Sequence):
        return len(a) == len(b) and all(_equal(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, Mapping) and isinstance(b, Mapping):
        return len(a) == len(b) and all(k in b and _equal(v, b[k]) for k, v in a.items())
    if isinstance(a, bool) or isinstance(b, bool):
        return False  # (a is b was tested above)
    return a == b


def _valid(x, s, root):
    if s is True or s is False:
        return s
    if "$ref" in s and not _valid(x, _resolve(s["$ref"], root), root):
        return False
    if "type" in s:
        t = s["type"]
        if not any(_is_type(x, each) for each in ([t] if isinstance(t, str) else t)):
            return False
    if "enum" in s and not any(_equal(each, x) for each in s["enum"]):
        return False
    if "const" in s and not _equal(x, s["const"]):
        return False
    if "not" in s and _valid(x, s["not"], root):
        return False
    if "anyOf" in s and not any(_valid(x, sub, root) for sub in s["anyOf"]):
        return False
    if "oneOf" in s and sum(bool(_valid(x, sub, root)) for sub in s["oneOf"]) != 1:
        return False
    if isinstance(x, dict):
        props = s.get("properties", {})
        if not all(k in x for k in s.get("required", ())):
            return False
        if not s.get("minProperties", 0) <= len(x) <= s.get("maxProperties", len(x)):
            return False
        if not all(_valid(v, props[k], root) for k, v in x.items() if k in props):
            return False
        extra = s.get("additionalProperties", True)
        if not all(_valid(v, extra, root) for k, v in x.items() if k not in props):
            return False
        names = s.get("propertyNames", True)
        return all(_valid(k, names, root) for k in x)
    if isinstance(x, list):
        return (s.get("minItems", 0) <= len(x) <= s.get("maxItems", len(x))
                and all(_valid(item, s.get("items", True), root) for item in x))
    if isinstance(x, str):
        return len(x) >= s.get("minLength", 0) and ("pattern" not in s
                                                    or re.search(s["pattern"], x) is not None)
    if _is_type(x, "number"):
        return not (("minimum" in s and x < s["minimum"])
                    or ("maximum" in s and x > s["maximum"])
                    or ("exclusiveMinimum" in s and x <= s["exclusiveMinimum"])
                    or ("exclusiveMaximum" in s and x >= s["exclusiveMaximum"]))
    return True
