"""YAML specs: safe loading, JSON Schema validation, errors with key path and line.

A spec is plain data (``yaml.safe_load``): it never runs code. Every error
names the offending key as ``steps[2].move[0].index`` and its line, so a user
can jump straight to it. Relative file names in a spec are relative to the
spec's own folder (so a spec and its data move together).
"""

from __future__ import annotations

import json
from functools import cache
from pathlib import Path
from typing import Any

import yaml

from ..errors import SpecError

Key = tuple  # a path into the document: ("steps", 2, "move", 0, "index")


def format_key(path: Key) -> str:
    """``("steps", 2, "move")`` -> ``steps[2].move``."""
    out = ""
    for part in path:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += ("." if out else "") + str(part)
    return out


class SpecDoc:
    """A loaded spec: ``data`` (plain Python values) plus the line of every key."""

    def __init__(self, data: Any, lines: dict[Key, int], file: str, base: Path):
        self.data = data
        self._lines = lines
        self.file = file
        self.base = base

    def line(self, path: Key) -> int | None:
        """Line of ``path``, or of its nearest ancestor that has one."""
        path = tuple(path)
        while True:
            if path in self._lines:
                return self._lines[path]
            if not path:
                return None
            path = path[:-1]

    def error(self, path: Key, message: str) -> SpecError:
        """A :class:`SpecError` pointing at ``path`` (raise it)."""
        return SpecError(message, file=self.file, key=format_key(path) or None,
                         line=self.line(path))

    def get(self, path: Key, default=None):
        node = self.data
        for part in path:
            try:
                node = node[part]
            except (KeyError, IndexError, TypeError):
                return default
        return node

    def resolve(self, name: str) -> Path:
        """A file name from the spec, relative to the spec's folder."""
        p = Path(name).expanduser()
        return p if p.is_absolute() else self.base / p


class _UniqueKeyLoader(yaml.SafeLoader):
    pass


def _collect_lines(node, path: Key, lines: dict[Key, int], file: str) -> None:
    if isinstance(node, yaml.MappingNode):
        seen = set()
        for key_node, value_node in node.value:
            key = key_node.value
            if key in seen:
                raise SpecError(f"duplicate key {key!r}", file=file,
                                key=format_key(path + (key,)), line=key_node.start_mark.line + 1)
            seen.add(key)
            lines[path + (key,)] = key_node.start_mark.line + 1
            _collect_lines(value_node, path + (key,), lines, file)
    elif isinstance(node, yaml.SequenceNode):
        for i, item in enumerate(node.value):
            lines[path + (i,)] = item.start_mark.line + 1
            _collect_lines(item, path + (i,), lines, file)


def parse_spec_text(text: str, file: str = "<spec>", base: Path | None = None) -> SpecDoc:
    """Parse YAML text into a :class:`SpecDoc` (no schema check)."""
    try:
        node = yaml.compose(text, Loader=_UniqueKeyLoader)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise SpecError(f"YAML syntax error: {problem}", file=file,
                        line=mark.line + 1 if mark else None) from None
    if node is None:
        raise SpecError("spec is empty", file=file)
    lines: dict[Key, int] = {(): node.start_mark.line + 1}
    _collect_lines(node, (), lines, file)
    try:
        data = yaml.load(text, Loader=_UniqueKeyLoader)
    except yaml.YAMLError as exc:  # pragma: no cover - compose already parsed it
        raise SpecError(f"YAML error: {exc}", file=file) from None
    if not isinstance(data, dict):
        raise SpecError("a spec must be a mapping of keys to values", file=file, line=1)
    return SpecDoc(data, lines, file, base or Path("."))


@cache
def load_schema(kind: str) -> dict:
    """The JSON Schema of spec kind ``kind`` (``warp``, ``morph``, ``sweep``, ...)."""
    name = f"{kind}.schema.json"
    path = Path(__file__).resolve().parent.parent / "schemas" / name
    if path.is_file():  # an installed package: no importlib.resources (zipfile: ~15 ms)
        text = path.read_text(encoding="utf-8")
    else:  # pragma: no cover - a zipped install
        from importlib import resources

        text = resources.files("volwarp_cli.schemas").joinpath(name).read_text()
    return json.loads(text)


def validate(doc: SpecDoc, schema: dict) -> None:
    """Raise a :class:`SpecError` for the first (most relevant) schema violation."""
    from .schema_subset import is_valid

    if is_valid(doc.data, schema):  # the usual case, without importing jsonschema (~0.1 s)
        return
    import jsonschema  # the authority: it finds and words the error (or finds none)

    validator = jsonschema.Draft202012Validator(schema)
    errors = sorted(validator.iter_errors(doc.data),
                    key=lambda e: (doc.line(tuple(e.absolute_path)) or 0, list(e.absolute_path)))
    if not errors:
        return
    err = jsonschema.exceptions.best_match(errors)
    # best_match prefers shallow errors; report the one the user reaches first
    # when several top-level problems exist.
    path = tuple(err.absolute_path)
    message = err.message
    if err.validator == "additionalProperties" and isinstance(err.instance, dict):
        allowed = set(err.schema.get("properties", {}))
        extra = sorted(k for k in err.instance if k not in allowed)
        if extra:
            path = path + (extra[0],)
            message = (f"unknown key {extra[0]!r}"
                       + (f" (allowed: {', '.join(sorted(allowed))})" if allowed else ""))
    elif err.validator == "required":
        message = err.message.replace("is a required property", "is required")
    elif err.validator in ("oneOf", "anyOf") and err.context:
        deepest = max(err.context, key=lambda e: len(e.absolute_path))
        if len(deepest.absolute_path) > len(err.absolute_path):
            path = tuple(deepest.absolute_path)
            message = deepest.message
    raise doc.error(path, message)


def load_spec(path: str | Path, kind: str | None = None) -> SpecDoc:
    """Read a YAML spec file, check it against ``kind``'s schema when given."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise SpecError("no such spec file", file=str(path)) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise SpecError(f"cannot read spec ({exc})", file=str(path)) from None
    doc = parse_spec_text(text, file=str(path), base=path.parent)
    if kind is not None:
        validate(doc, load_schema(kind))
    return doc
