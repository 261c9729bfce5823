"""YAML specs: safe loading, JSON Schema validation, errors with key path and line.

A spec is plain data (PyYAML's safe loader): it never runs code. Every error
names the offending key as ``steps[2].move[0].index`` and its line, so a user
can jump straight to it. Relative file names in a spec are relative to the
spec's own folder (so a spec and its data move together).

Scalars resolve as in YAML 1.1 (PyYAML's default: ``yes``/``on`` are booleans),
plus the floats of YAML 1.2 and JSON that 1.1 reads as strings (``1e-05``,
``1E+3``, ``-.5``), so a spec written by ``json.dumps`` loads. A spec is checked
before anything reads it: no non-finite number (``.nan``, ``.inf``, ``1e999``),
no recursive alias, at most :data:`MAX_VALUES` values with every alias expanded
(a "billion laughs" spec is refused in time proportional to its text) and at
most :data:`MAX_DEPTH` levels of nesting. Values quoted in error messages are
cut short, so an error is always one short line.
"""

from __future__ import annotations

import json
import math
import re
import sys
from collections.abc import Callable
from functools import cache
from pathlib import Path
from typing import Any

from ..errors import SpecError

_compile = re.compile  # (the real one, whatever :func:`_import_yaml` puts in its place)


class _CompiledLater:
    """A regular expression compiled at its first use (:func:`_import_yaml`)."""

    _made = None  # (class defaults: a copy made without __init__ finds them too)
    pattern, flags = "", 0

    def __init__(self, pattern, flags):
        self.pattern, self.flags = pattern, flags

    def __getattr__(self, name):  # (search, match, ...: the compiled expression's)
        if self._made is None:
            self._made = _compile(self.pattern, self.flags)
        return getattr(self._made, name)

    def __reduce__(self):  # (copied or pickled: the compiled expression)
        return _compile, (self.pattern, self.flags)


def _import_yaml():
    """PyYAML, its pure-Python reader's check for unprintable characters compiled when used.

    That one expression (the ranges of every printable code point) took 3 ms to compile
    at import: a third of PyYAML's import, 2% of a small warp. Only the pure-Python
    reader uses it, which reads a spec only to word its error.
    """
    if "yaml" in sys.modules:  # (imported, or being imported by another thread: waited for)
        import yaml

        return yaml

    def compile_later(pattern, flags=0):
        if isinstance(pattern, str) and pattern.startswith("[^\x09\x0A\x0D\x20-\x7E\x85"):
            return _CompiledLater(pattern, flags)
        return _compile(pattern, flags)

    re.compile = compile_later
    try:
        import yaml
    finally:
        re.compile = _compile
    return yaml


yaml = _import_yaml()

Key = tuple  # a path into the document: ("steps", 2, "move", 0, "index")

MAX_VALUES = 1_000_000  # values in a spec, counting every expansion of an alias
MAX_DEPTH = 64  # levels of nesting (jsonschema and the readers recurse on them)
MAX_QUOTE = 100  # characters of a value quoted in an error message
MAX_MESSAGE = 300  # characters of an error message (file, line and key apart)


def format_key(path: Key) -> str:
    """``("steps", 2, "move")`` -> ``steps[2].move``."""
    out = ""
    for part in path:
        if isinstance(part, int) and not isinstance(part, bool):  # (a key on: is True)
            out += f"[{part}]"
        else:
            out += ("." if out else "") + str(part)
    return out


def clip(text: Any, limit: int = MAX_QUOTE) -> str:
    """``str(text)`` cut to at most ``limit`` characters, ending in ``...`` when cut."""
    text = str(text)
    return text if len(text) <= limit else text[:max(limit - 3, 0)] + "..."


def _quote(value: Any) -> str:
    """``repr(value)``, cut short for an error message."""
    return clip(repr(value))


def _error_key(path: Key) -> str | None:
    """The key path of an error: long key names and very deep paths shortened."""
    key = format_key(tuple(clip(p, 40) if isinstance(p, str) else p for p in path))
    if len(key) > 120:
        key = key[:60] + "..." + key[-57:]
    return key or None


class SpecDoc:
    """A loaded spec: ``data`` (plain Python values) plus the line of every key.

    ``lines`` is the document's YAML node tree (lines are looked up in it on
    demand, so an alias costs no memory per expansion), a function composing
    that tree (called at the first line asked: a valid spec never composes
    it), or a dict mapping key paths to lines.
    """

    def __init__(self, data: Any, lines: yaml.Node | dict[Key, int] | Callable[[], yaml.Node],
                 file: str, base: Path):
        self.data = data
        self._lines = lines
        self.file = file
        self.base = base

    def line(self, path: Key) -> int | None:
        """Line of ``path``, or of its nearest ancestor that has one."""
        path = tuple(path)
        lines = self._lines  # (read once: another thread may compose the tree meanwhile)
        if callable(lines):
            lines = self._lines = lines()
        if isinstance(lines, yaml.Node):
            return _node_line(lines, path)
        while True:
            if path in lines:
                return lines[path]
            if not path:
                return None
            path = path[:-1]

    def error(self, path: Key, message: str) -> SpecError:
        """A :class:`SpecError` pointing at ``path`` (raise it)."""
        return SpecError(clip(message, MAX_MESSAGE), file=self.file, key=_error_key(path),
                         line=self.line(path))

    def get(self, path: Key, default=None):
        """The value at key ``path`` of the data, or ``default`` where the path leaves it."""
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

    def input_file(self, name: str) -> Path:
        """:meth:`resolve` for a file the spec reads, declared as the run's input.

        Then no output of the run may replace it (:mod:`volwarp_cli.io.inputs`).
        """
        from ..io.inputs import declare_input

        path = self.resolve(name)
        declare_input(path)
        return path


def _node_line(node: yaml.Node, path: Key) -> int:
    """The line of ``path`` in a node tree.

    That of its key in a mapping, of the item in a list; of the nearest ancestor
    found when the path leaves the tree.
    """
    line = node.start_mark.line + 1
    for part in path:
        found = None
        if isinstance(node, yaml.MappingNode):
            for key_node, value_node in node.value:  # the last one: merged keys come first
                if isinstance(key_node, yaml.ScalarNode) and _is_key(key_node, part):
                    found = value_node, key_node.start_mark.line + 1
        elif (isinstance(node, yaml.SequenceNode) and isinstance(part, int)
              and not isinstance(part, bool) and 0 <= part < len(node.value)):
            found = node.value[part], node.value[part].start_mark.line + 1
        if found is None:
            break
        node, line = found
    return line


def _is_key(key_node: yaml.ScalarNode, part) -> bool:
    """Whether ``key_node`` is the key ``part`` of the data.

    A key YAML reads as a boolean, a number or null (``on:``, ``1:``, ``~:``) is
    not its text in the data: compared as read, so an error about it names its
    own line, not its mapping's.
    """
    if isinstance(part, str):
        return key_node.value == part
    try:
        value = yaml.constructor.SafeConstructor().construct_object(key_node)
    except (yaml.YAMLError, ValueError, TypeError, ArithmeticError):
        return False
    return value == part and isinstance(value, bool) == isinstance(part, bool)


class _TooDeep(Exception):
    def __init__(self, path: Key, mark):
        self.path, self.mark = path, mark


class _SpecLoader(yaml.SafeLoader):
    """PyYAML's safe loader, also reading YAML 1.2 / JSON floats such as ``1e-05``.

    It stops composing past :data:`MAX_DEPTH` levels: PyYAML's scanner costs time
    in proportion to text size times nesting, and its composer recurses per level.
    """

    def __init__(self, stream):
        super().__init__(stream)
        self._path: list = []  # key path of the node being composed

    def compose_node(self, parent, index):
        # index: the key node of a mapping value, the number of a list item, None
        # for the root and for keys
        self._path.append(index.value if isinstance(index, yaml.ScalarNode) else index)
        try:
            if len(self._path) > MAX_DEPTH + 1:  # the root is level 0
                path = tuple(self._path[1:])
                raise _TooDeep(path[:path.index(None)] if None in path else path,
                               self.peek_event().start_mark)
            return super().compose_node(parent, index)
        finally:
            self._path.pop()


# YAML 1.2 core schema floats that YAML 1.1 reads as strings: an exponent without a
# dot or without a sign (1e5, 1.5e5), a signed leading dot (-.5). Only strings with a
# dot or an exponent, so 089 stays a string; tried after 1.1's own int and float.
_FLOAT_12 = re.compile(r"^[-+]?(?:(?:\.[0-9]+|[0-9]+\.[0-9]*)(?:[eE][-+]?[0-9]+)?"
                       r"|[0-9]+[eE][-+]?[0-9]+)$")
_SpecLoader.add_implicit_resolver("tag:yaml.org,2002:float", _FLOAT_12, list("-+.0123456789"))

#: Specs from this size on are read by libyaml (when PyYAML has it): every spec. A plain
#: one is built from its events (:func:`_plain_data`), any other composed by libyaml. A
#: registration's 729 control-point moves (40 kB) take 0.24 s in the pure-Python
#: composer, 0.04 s composed in C, 0.008 s from the events; a one-move spec 0.9 ms,
#: 0.25 ms composed. Any text libyaml finds fault with is read again by the Python
#: loader, whose errors and their wording are the ones reported
#: (``tests/test_spec_fast_path.py``).
FAST_MIN_BYTES = 0

if getattr(yaml, "__with_libyaml__", False):
    class _FastSpecLoader(yaml.CSafeLoader):
        """libyaml's parser and composer with the same resolvers (tags resolve in Python)."""

    _FastSpecLoader.add_implicit_resolver("tag:yaml.org,2002:float", _FLOAT_12,
                                          list("-+.0123456789"))
else:  # pragma: no cover - PyYAML built without libyaml
    _FastSpecLoader = None


def _too_deep(text: str) -> bool:
    """Whether ``text`` nests collections over :data:`MAX_DEPTH` levels (libyaml's events)."""
    depth = 0
    starts = (yaml.MappingStartEvent, yaml.SequenceStartEvent)
    ends = (yaml.MappingEndEvent, yaml.SequenceEndEvent)
    for event in yaml.parse(text, Loader=_FastSpecLoader):
        if isinstance(event, starts):
            depth += 1
            if depth > MAX_DEPTH:
                return True
        elif isinstance(event, ends):
            depth -= 1
    return False


def _compose(text: str):
    """``(loader, node)``: the document's node tree.

    Composed by libyaml for a valid spec (of at least :data:`FAST_MIN_BYTES`);
    by the pure-Python loader otherwise, and for any text libyaml finds fault
    with (so that every error, and its wording, is the Python loader's).
    """
    if _FastSpecLoader is not None and len(text) >= FAST_MIN_BYTES:
        loader = None
        try:
            if not _too_deep(text):
                loader = _FastSpecLoader(text)
                return loader, loader.get_single_node()
        except (yaml.YAMLError, RecursionError, UnicodeEncodeError):  # (a lone surrogate)
            pass
        if loader is not None:
            loader.dispose()
    loader = _SpecLoader(text)  # (a control character: ReaderError, here)
    try:
        return loader, loader.get_single_node()
    except BaseException:
        loader.dispose()
        raise

_MAX_FLOAT = sys.float_info.max
#: plain numbers YAML 1.1 (PyYAML) reads otherwise than YAML 1.2 and JSON: a leading
#: zero (010 is 8), sexagesimal (1:30 is 90), underscores (1_000), binary (0b11)
_YAML11_ONLY = re.compile(r"^[-+]?(?:0[0-9_]+|0b[01_]+|[0-9][0-9_]*:[0-5]?[0-9].*"
                          r"|[0-9]*_[0-9_]*(?:\.[0-9_]*)?(?:[eE][-+]?[0-9]+)?)$")

#: Plain scalars the resolvers make a float or an int that float() or int() makes alike
#: (a test holds them to the resolvers and constructors): a registration's spec has
#: thousands of distinct numbers, resolved and constructed one by one in Python before
#: (729 moves of 4-decimal offsets: 12.0 ms to read before, 8.8 ms now)
_PLAIN_FLOAT = re.compile(r"-?[0-9]+\.[0-9]+")
_PLAIN_INT = re.compile(r"-?(?:0|[1-9][0-9]*)")

# keys the constructor reads itself when it flattens a mapping (<< merges, = values)
_SPECIAL_KEY_TAGS = {"tag:yaml.org,2002:merge", "tag:yaml.org,2002:value"}


def _children(node: yaml.Node, path: Key) -> list:
    """``(child node, its key path)`` of a collection node, in document order."""
    if isinstance(node, yaml.SequenceNode):
        return [(item, path + (i,)) for i, item in enumerate(node.value)]
    if isinstance(node, yaml.MappingNode):
        return [(v, path + (k.value,)) for k, v in node.value]
    return []


def _check_tree(loader: _SpecLoader, root: yaml.Node, file: str) -> None:
    """Refuse a node tree that is not plain, finite, bounded data, before it is read.

    One walk over the distinct nodes (an alias is not walked again), so the cost
    is that of the text whatever the aliases expand to. Refused, with key path and
    line: a scalar its tag cannot read (``!!float abc``), a non-finite float, a
    list or mapping as a key, a duplicate key, an alias inside the value it names,
    over :data:`MAX_VALUES` values with aliases expanded, over :data:`MAX_DEPTH`
    levels of nesting.
    """
    def fail(path, node, message):
        raise SpecError(clip(message, MAX_MESSAGE), file=file, key=_error_key(path),
                        line=node.start_mark.line + 1)

    def scalar(node, path):
        try:
            value = loader.construct_object(node)
        except yaml.YAMLError as exc:
            fail(path, node, f"cannot read {_quote(node.value)}: "
                             f"{clip(getattr(exc, 'problem', None) or exc)}")
        except (ValueError, TypeError, ArithmeticError):  # !!int 1.5, 5000 digits
            fail(path, node, f"cannot read {_quote(node.value)} as "
                             f"!!{node.tag.rsplit(':', 1)[-1]}")
        if isinstance(value, float) and not math.isfinite(value):
            said = node.value.lower().lstrip("+-.") in ("nan", "inf", "infinity")
            fail(path, node, f"must be a finite number, got {clip(node.value)}"
                             + ("" if said else f" (= {value})"))
        if type(value) is int and not -_MAX_FLOAT <= value <= _MAX_FLOAT:
            fail(path, node, f"number too large: {clip(node.value)} (the limit is "
                             f"{_MAX_FLOAT:.4g})")
        if isinstance(value, int | float) and not isinstance(value, bool) \
                and not node.style and _YAML11_ONLY.match(node.value):
            fail(path, node, f"{node.value} is {value!r} to YAML 1.1 and not that number to YAML "
                             "1.2 or JSON (a leading zero, ':', '_' or 0b): write the number "
                             f"meant plainly (as YAML 1.1 reads it: {value!r})")
        return value

    size: dict[int, int] = {}  # id(node) -> values in its expansion (capped)
    height: dict[int, int] = {}  # id(node) -> levels of nesting below it
    open_: set[int] = set()  # nodes on the walk's current path
    aliased = False
    stack: list = [("node", root, (), None)]
    while stack:
        what, node, path, seen = stack.pop()
        nid = id(node)
        if what == "key":
            if not isinstance(node, yaml.ScalarNode):
                fail(path, node, f"a key must be a name, not a {node.id}")
            key = node.value if node.tag in _SPECIAL_KEY_TAGS else scalar(node, path + (node.value,))
            try:
                duplicate = key in seen
            except TypeError:  # unhashable: the constructor says so
                duplicate = False
            if duplicate:
                fail(path + (node.value,), node, f"duplicate key {_quote(node.value)}")
            else:
                seen.add(key)
        elif what == "exit":
            if isinstance(node, yaml.MappingNode):
                kids = [size[id(v)] + 1 for _, v in node.value]  # + 1: the key
            else:
                kids = [size[id(v)] for v in node.value]
            size[nid] = min(1 + sum(kids), MAX_VALUES + 1)
            height[nid] = 1 + max((height[id(v)] for v, _ in _children(node, ())), default=0)
            open_.discard(nid)
        elif nid in size or nid in height:
            aliased = True  # an alias of a node already walked
        elif nid in open_:
            fail(path, node, "an alias here names a value that contains it (a recursive "
                             "value)")
        elif isinstance(node, yaml.ScalarNode):
            scalar(node, path)
            size[nid], height[nid] = 1, 0
        elif node.tag not in loader.yaml_constructors:  # !!python/tuple [..], !foo {..}
            fail(path, node, f"cannot read a {node.id} tagged {_quote(node.tag)}")
        else:
            open_.add(nid)
            stack.append(("exit", node, path, None))
            items: list = []
            seen_keys: set = set()
            if isinstance(node, yaml.MappingNode):
                for key_node, value_node in node.value:
                    items.append(("key", key_node, path, seen_keys))
                    key = key_node.value if isinstance(key_node, yaml.ScalarNode) else None
                    items.append(("node", value_node, path + (key,), None))
            else:
                items = [("node", item, path + (i,), None) for i, item in enumerate(node.value)]
            stack.extend(reversed(items))

    if size[id(root)] > MAX_VALUES:
        node, path = root, ()
        while True:  # point at the smallest part that is too large by itself
            big = [(c, p) for c, p in _children(node, path) if size[id(c)] > MAX_VALUES]
            if not big:
                break
            node, path = big[0]
        fail(path, node, (f"spec too large (aliases expand to over {MAX_VALUES} values)"
                          if aliased else f"spec too large (over {MAX_VALUES} values)"))
    if height[id(root)] > MAX_DEPTH:
        node, path = root, ()
        while len(path) < MAX_DEPTH:  # follow the deepest branch down to the limit
            node, path = max(_children(node, path), key=lambda cp: height[id(cp[0])])
        fail(path, node, f"nested more than {MAX_DEPTH} levels deep")


class _NotPlain(Exception):
    """A document :func:`_plain_data` leaves to the composing loader."""


_NO_KEY = object()  # a mapping waiting for its next key


def _plain_data(text: str) -> Any:
    """The data of a plain spec, built straight from libyaml's events; ``_NOT_PLAIN`` if not.

    Plain: one document of mappings, lists and untagged scalars, no anchor or
    alias, no merge key, distinct scalar keys, finite numbers, at most
    :data:`MAX_DEPTH` levels and :data:`MAX_VALUES` values. Scalars resolve and
    construct exactly as the composing loader's do (its resolvers and
    constructors, each distinct scalar once), so the data is the same. Anything
    else, and any text libyaml finds fault with, is the composing loader's to
    read and word the error of. Composing a node tree (with two marks per
    node) and walking it was most of a large spec's reading: 729 moves, 43 ms
    against 8 ms this way.
    """
    try:
        loader = _FastSpecLoader(text)
    except UnicodeEncodeError:  # (a lone surrogate: the Python loader words its error)
        return _NOT_PLAIN
    try:
        return _data_from_events(loader)
    except (_NotPlain, yaml.YAMLError, ValueError, TypeError, ArithmeticError, KeyError):
        return _NOT_PLAIN
    finally:
        loader.dispose()


_NOT_PLAIN = object()


def _data_from_events(loader) -> Any:
    next_event = loader.get_event
    resolve, constructors = loader.resolve, loader.yaml_constructors
    scalar_node = yaml.ScalarNode
    plain_float, plain_int = _PLAIN_FLOAT.fullmatch, _PLAIN_INT.fullmatch
    scalars: dict = {}  # (text, implicit) -> value
    open_: list = []  # [collection, its pending key] from the root down
    values = 0
    root = None
    if not isinstance(next_event(), yaml.StreamStartEvent) or \
            not isinstance(next_event(), yaml.DocumentStartEvent):
        raise _NotPlain  # (an empty text)
    while True:
        event = next_event()
        kind = type(event)
        if kind is yaml.ScalarEvent:
            if event.anchor is not None or event.tag is not None:
                raise _NotPlain
            key = (event.value, event.implicit)
            value = scalars.get(key, _NO_KEY)
            if value is _NO_KEY:
                text = event.value
                if event.implicit[0] and plain_float(text):  # (the resolvers' answer too)
                    value = float(text)
                elif event.implicit[0] and plain_int(text):
                    value = int(text)
                else:
                    tag = resolve(scalar_node, text, event.implicit)
                    if tag in _SPECIAL_KEY_TAGS:
                        raise _NotPlain
                    value = constructors[tag](loader, scalar_node(tag, text, None, None,
                                                                  event.style))
                if isinstance(value, float) and not math.isfinite(value):
                    raise _NotPlain
                if type(value) is int and not -_MAX_FLOAT <= value <= _MAX_FLOAT:
                    raise _NotPlain
                if isinstance(value, int | float) and not isinstance(value, bool) and \
                        event.implicit[0] and _YAML11_ONLY.match(text):
                    raise _NotPlain  # (the composing loader says why, with its line)
                scalars[key] = value
        elif kind is yaml.MappingStartEvent or kind is yaml.SequenceStartEvent:
            if event.anchor is not None or event.tag is not None or len(open_) >= MAX_DEPTH:
                raise _NotPlain
            open_.append([{} if kind is yaml.MappingStartEvent else [], _NO_KEY])
            continue
        elif kind is yaml.MappingEndEvent or kind is yaml.SequenceEndEvent:
            value = open_.pop()[0]
        elif kind is yaml.DocumentEndEvent and not open_:
            if not isinstance(next_event(), yaml.StreamEndEvent):
                raise _NotPlain  # (a second document)
            return root
        else:  # an alias
            raise _NotPlain
        values += 1
        if values > MAX_VALUES:
            raise _NotPlain
        if not open_:
            root = value
            continue
        parent = open_[-1]
        collection, key = parent
        if type(collection) is list:
            collection.append(value)
        elif key is not _NO_KEY:
            collection[key] = value
            parent[1] = _NO_KEY
        elif type(value) in (dict, list) or value in collection:
            raise _NotPlain  # a collection as a key, a duplicate key
        else:
            parent[1] = value


class _TreeLater:
    """The node tree of a text :func:`_plain_data` read, composed at the first line asked.

    (A class, not a closure: a :class:`SpecDoc` pickles, as a batch's manifest is sent.)
    """

    def __init__(self, text: str):
        self.text = text

    def __call__(self):
        try:
            loader, node = _compose(self.text)
        except (yaml.YAMLError, RecursionError, _TooDeep):  # pragma: no cover - read once
            return {}
        loader.dispose()
        return node


def parse_spec_text(text: str, file: str = "<spec>", base: Path | None = None) -> SpecDoc:
    """Parse YAML text into a :class:`SpecDoc` (no schema check)."""
    if _FastSpecLoader is not None and len(text) >= FAST_MIN_BYTES:
        data = _plain_data(text)
        if isinstance(data, dict):
            return SpecDoc(data, _TreeLater(text), file, base or Path("."))
    loader = None
    try:
        try:
            loader, node = _compose(text)
        except yaml.YAMLError as exc:
            mark = getattr(exc, "problem_mark", None)
            problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
            raise SpecError(f"YAML syntax error: {clip(problem)}", file=file,
                            line=mark.line + 1 if mark else None) from None
        except _TooDeep as exc:
            raise SpecError(f"nested more than {MAX_DEPTH} levels deep", file=file,
                            key=_error_key(exc.path), line=exc.mark.line + 1) from None
        except RecursionError:  # pragma: no cover - _TooDeep comes first
            raise SpecError(f"nested more than {MAX_DEPTH} levels deep", file=file,
                            line=loader.get_mark().line + 1 if loader else None) from None
        if node is None:
            raise SpecError("spec is empty", file=file)
        _check_tree(loader, node, file)
        try:
            data = loader.construct_document(node)
        except (yaml.YAMLError, ValueError, TypeError, OverflowError) as exc:  # a bad << merge
            mark = getattr(exc, "problem_mark", None)
            problem = getattr(exc, "problem", None) or exc
            raise SpecError(f"YAML error: {clip(problem)}", file=file,
                            line=mark.line + 1 if mark else None) from None
    finally:
        if loader is not None:
            loader.dispose()
    if not isinstance(data, dict):
        raise SpecError("a spec must be a mapping of keys to values", file=file, line=1)
    return SpecDoc(data, node, file, base or Path("."))


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


def _message(err) -> str:
    """The jsonschema wording of ``err``, with the value it quotes cut short."""
    message = err.message
    try:
        full = repr(err.instance)
    except Exception:  # pragma: no cover - repr of plain data does not fail
        return message
    if len(full) > MAX_QUOTE:
        message = message.replace(full, clip(full))
    return message


def _unquoted_hint(key) -> str:
    """Why a key is a boolean or null where a name was meant (``on:``), or ``""``."""
    if isinstance(key, bool) or key is None:
        return (" (YAML reads an unquoted on, off, yes, no, true, false or ~ as a boolean "
                "or null: quote a name)")
    return ""


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
    message = _message(err)
    if err.validator == "additionalProperties" and isinstance(err.instance, dict):
        allowed = set(err.schema.get("properties", {}))
        extra = sorted(k for k in err.instance if k not in allowed)
        if extra:
            path = path + (extra[0],)
            message = (f"unknown key {_quote(extra[0])}"
                       + (f" (allowed: {', '.join(sorted(allowed))})" if allowed else "")
                       + _unquoted_hint(extra[0]))
    elif err.validator == "required":
        message = message.replace("is a required property", "is required")
    elif "propertyNames" in err.absolute_schema_path:  # a name of the mapping, not its value
        path = path + (err.instance,)
        message = f"the key {_quote(err.instance)} is not a name here: {message}" \
            + _unquoted_hint(err.instance)
    elif err.validator in ("oneOf", "anyOf") and err.context:
        deepest = max(err.context, key=lambda e: len(e.absolute_path))
        if len(deepest.absolute_path) > len(err.absolute_path):
            path = tuple(deepest.absolute_path)
            message = _message(deepest)
    raise doc.error(path, message)


def load_spec(path: str | Path, kind: str | None = None) -> SpecDoc:
    """Read a YAML spec file, check it against ``kind``'s schema when given."""
    from ..provenance import remember_spec

    path = Path(path)
    try:
        data = path.read_bytes()
        # (as read_text reads it: universal newlines)
        text = data.decode("utf-8").replace("\r\n", "\n").replace("\r", "\n")
    except FileNotFoundError:
        raise SpecError("no such spec file", file=str(path)) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise SpecError(f"cannot read spec ({exc})", file=str(path)) from None
    remember_spec(path, data)  # (a pipe, /dev/stdin, is read once: its hash is of these bytes)
    doc = parse_spec_text(text, file=str(path), base=path.parent)
    if kind is not None:
        validate(doc, load_schema(kind))
    return doc


# -- specs given as Python values (volwarp_cli.api) -------------------------------------
def load_spec_data(data: Any, kind: str | None = None, *, file: str = "<spec>",
                   base: str | Path | None = None) -> SpecDoc:
    """A :class:`SpecDoc` of a spec given as Python values, as :func:`load_spec` reads a file.

    ``data``: the document a YAML file would give (a mapping of keys to
    values). It passes the checks a file's text passes (:func:`_check_tree`:
    finite numbers, no value inside itself, at most :data:`MAX_VALUES` values
    and :data:`MAX_DEPTH` levels, names as keys), then ``kind``'s schema when
    given, and its errors name the same key paths (``steps[2].move[0].index``);
    they have no line (``file``, default ``<spec>``, names the document in
    them). Tuples are read as lists, numpy scalars and arrays as the numbers
    and lists they hold, paths as strings; the data is copied, never kept.
    ``base``: the folder relative file names in the spec are relative to
    (default: the current folder).
    """
    from collections.abc import Mapping

    if not isinstance(data, Mapping):
        raise SpecError("a spec must be a mapping of keys to values", file=file)
    plain = _plain(data, (), file, set(), [0])
    doc = SpecDoc(plain, {}, file, Path(base) if base is not None else Path("."))
    if kind is not None:
        validate(doc, load_schema(kind))
    return doc


def _plain(value: Any, path: Key, file: str, open_: set, count: list) -> Any:
    """``value`` as the plain data YAML gives (a copy), or a :class:`SpecError` at ``path``.

    ``open_``: the ids of the collections being copied (a value inside itself);
    ``count``: the values copied so far, in a list (shared values count each
    time, as a YAML alias does: refused past :data:`MAX_VALUES`, in time).
    """
    from collections.abc import Mapping

    import numpy as np

    def fail(message):
        raise SpecError(clip(message, MAX_MESSAGE), file=file, key=_error_key(path))

    count[0] += 1
    if count[0] > MAX_VALUES:
        fail(f"spec too large (over {MAX_VALUES} values)")

    if isinstance(value, np.ndarray):
        value = value.tolist()
    elif isinstance(value, np.generic):
        value = value.item()
    elif isinstance(value, Path):
        value = str(value)
    if value is None or isinstance(value, (bool, str)):
        return value
    if isinstance(value, int):
        if not -_MAX_FLOAT <= value <= _MAX_FLOAT:
            fail(f"number too large: {clip(value)} (the limit is {_MAX_FLOAT:.4g})")
        return value
    if isinstance(value, float):
        if not math.isfinite(value):
            fail(f"must be a finite number, got {value}")
        return value
    if not isinstance(value, (Mapping, list, tuple)):
        fail(f"cannot read a {type(value).__name__} (a spec holds mappings, lists, strings, "
             "numbers, booleans and null)")
    if len(path) >= MAX_DEPTH:
        fail(f"nested more than {MAX_DEPTH} levels deep")
    if id(value) in open_:
        fail("this value contains itself (a recursive value)")
    open_.add(id(value))
    try:
        if isinstance(value, Mapping):
            out = {}
            for key, item in value.items():
                if isinstance(key, np.generic):
                    key = key.item()
                if not (key is None or isinstance(key, (str, int, float, bool))):
                    fail(f"a key must be a name, not a {type(key).__name__}")
                count[0] += 1  # (the key)
                out[key] = _plain(item, path + (key,), file, open_, count)
            return out
        return [_plain(item, path + (i,), file, open_, count) for i, item in enumerate(value)]
    finally:
        open_.discard(id(value))

