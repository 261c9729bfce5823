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
import operator
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
        return _Compiled(schema).check(schema)(instance)
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


def _true(x):
    return True


def _false(x):
    return False


def _number(x) -> bool:
    return type(x) in (int, float) or (isinstance(x, numbers.Number) and not isinstance(x, bool))


#: each type's test: ``integer`` accepts 1.0, and neither ``integer`` nor ``number`` a bool
_TYPE_TESTS = {
    "object": lambda x: isinstance(x, dict),
    "array": lambda x: isinstance(x, list),
    "string": lambda x: isinstance(x, str),
    "null": lambda x: x is None,
    "boolean": lambda x: isinstance(x, bool),
    "number": _number,
    "integer": lambda x: type(x) is int or not isinstance(x, bool) and (
        isinstance(x, int) or (isinstance(x, float) and x.is_integer())),
}


_ABSENT = object()
#: each bound's keyword and the comparison that puts a number outside it
_OUT_OF_BOUNDS = (("minimum", operator.lt), ("maximum", operator.gt),
                  ("exclusiveMinimum", operator.le), ("exclusiveMaximum", operator.ge))


class _Compiled:
    """A schema as nested closures, one per subschema: each keyword's lookup made once.

    A spec of a registration's 729 moves was checked keyword by keyword on each
    of its 20,000 values (20 ms); the closures make the same tests in the same
    order (the verdict of the former keyword-walking check, which the tests hold
    against jsonschema) at a fraction of the cost.
    """

    def __init__(self, root: dict):
        self.root = root
        self.done: dict[int, object] = {}  # id(subschema) -> its test

    def check(self, s):
        """The test of subschema ``s`` (built once; a ``$ref`` cycle goes through a cell)."""
        if s is True or s is False:
            return _true if s else _false
        made = self.done.get(id(s))
        if made is not None:
            return made
        cell: list = []
        self.done[id(s)] = lambda x: cell[0](x)  # (while s is built: a recursive $ref)
        test = self._build(s)
        cell.append(test)
        self.done[id(s)] = test
        return test

    def _build(self, s):
        pre = []  # the tests of any instance, in _valid's order
        if "$ref" in s:
            pre.append(self.check(_resolve(s["$ref"], self.root)))
        if "type" in s:
            t = s["type"]
            tests = tuple(_TYPE_TESTS[each] for each in ([t] if isinstance(t, str) else t))
            pre.append(tests[0] if len(tests) == 1 else lambda x: any(f(x) for f in tests))
        if "enum" in s:
            enum = s["enum"]
            pre.append(lambda x: any(_equal(each, x) for each in enum))
        if "const" in s:
            const = s["const"]
            pre.append(lambda x: _equal(x, const))
        if "not" in s:
            negated = self.check(s["not"])
            pre.append(lambda x: not negated(x))
        if "anyOf" in s:
            any_of = [self.check(sub) for sub in s["anyOf"]]
            pre.append(lambda x: any(f(x) for f in any_of))
        if "oneOf" in s:
            one_of = [self.check(sub) for sub in s["oneOf"]]

            def exactly_one(x):
                n = 0
                for f in one_of:
                    if f(x):
                        n += 1
                return n == 1
            pre.append(exactly_one)
        of_object, of_array = self._object(s), self._array(s)
        of_string, of_number = self._string(s), self._number(s)
        if of_object is None and of_array is None and of_string is None and of_number is None:
            if not pre:
                return _true
            if len(pre) == 1:  # ({"type": "number"}: the type's own test, no layer)
                return pre[0]
        if of_object is None and of_array is None and of_string is None and len(pre) == 1 \
                and s.get("type") in ("number", "integer"):
            # a number's bounds alone ({"type": "integer", "minimum": 0}: each index of a
            # registration's 729 moves): the type's test, then the bounds, in one layer
            is_type = pre[0]
            return lambda x: is_type(x) and of_number(x)

        def test(x):
            for f in pre:
                if not f(x):
                    return False
            if isinstance(x, dict):
                return of_object is None or of_object(x)
            if isinstance(x, list):
                return of_array is None or of_array(x)
            if isinstance(x, str):
                return of_string is None or of_string(x)
            return of_number is None or not _number(x) or of_number(x)
        return test

    def _object(self, s):
        keys = ("properties", "required", "minProperties", "maxProperties",
                "additionalProperties", "propertyNames")
        if not any(k in s for k in keys):
            return None
        props = {k: self.check(v) for k, v in s.get("properties", {}).items()}
        required = tuple(s.get("required", ()))
        lo, hi = s.get("minProperties", 0), s.get("maxProperties", _ABSENT)
        extra = self.check(s.get("additionalProperties", True))
        names = self.check(s.get("propertyNames", True))

        get = props.get

        def test(x):
            for k in required:
                if k not in x:
                    return False
            if not lo <= len(x) <= (len(x) if hi is _ABSENT else hi):
                return False
            for k, v in x.items():
                if not get(k, extra)(v):
                    return False
            return names is _true or all(map(names, x))
        return test

    def _array(self, s):
        if not any(k in s for k in ("items", "minItems", "maxItems")):
            return None
        lo, hi = s.get("minItems", 0), s.get("maxItems", _ABSENT)
        items = self.check(s.get("items", True))
        return lambda x: (lo <= len(x) <= (len(x) if hi is _ABSENT else hi)
                          and all(map(items, x)))

    def _string(self, s):
        if "minLength" not in s and "pattern" not in s:
            return None
        least = s.get("minLength", 0)
        pattern = re.compile(s["pattern"]) if "pattern" in s else None
        return lambda x: len(x) >= least and (pattern is None or pattern.search(x) is not None)

    def _number(self, s):
        fails = [(op, s[k]) for k, op in _OUT_OF_BOUNDS if k in s]
        if not fails:
            return None
        if len(fails) == 1:
            (op, bound), = fails
            return lambda x: not op(x, bound)
        return lambda x: not any(op(x, bound) for op, bound in fails)
