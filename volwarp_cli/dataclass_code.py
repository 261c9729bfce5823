"""The methods ``@dataclass`` writes for volwarp's classes, compiled once, like a module's ``.pyc``.

``dataclasses`` (Python 3.11, 3.12) writes each class's ``__init__``, ``__repr__``,
``__eq__``, ``__hash__`` (and, frozen, ``__setattr__`` and ``__delattr__``) as source
text when the class is made, and compiles each with ``exec``: about 0.5 ms a
frozen class on the project's machine. A 16^3 ``warp`` makes 28 of them while
its modules load, 14-18 ms of its 0.14 s: more than click's import, the largest
piece of its fixed cost (issue 32).

A text and what it compiles to depend on nothing but the text (and the Python
that compiles it), so the code can be kept: :func:`install` (the command
line's entry point calls it, before any volwarp module loads) makes the
``exec`` of ``dataclasses`` compile a text of a ``volwarp_cli`` class once, from
a table of texts and their code objects kept beside the package's bytecode
(:data:`FILE`, marked with the interpreter's bytecode magic number as a
``.pyc`` is). The code run is what ``exec`` of the text would have compiled: the
same compiler, the same flags (none inherited), the same ``"<string>"`` file
name; a text not in the table is compiled as before. Other packages' classes,
and any other ``exec``, go to the built-in ``exec`` untouched.

The table is written as Python writes bytecode: by the warm-up at install
(``python -m volwarp_cli.warmup``, which makes every command's classes), and
at the end of a command that compiled a text the table lacked, unless
``PYTHONDONTWRITEBYTECODE`` is set or the folder cannot be written (a
read-only install keeps the table its install wrote; a missing or damaged
table only costs the compilations). A library user's process is left as it is.
"""

from __future__ import annotations

import builtins
import marshal
import os
import sys

#: the table's file name beside the package's bytecode (per interpreter, as a .pyc)
FILE = f"volwarp-dataclass-code.{sys.implementation.cache_tag}.bin"
#: entries kept at most: beyond that a write keeps only the texts its process used
#: (the package's classes need about 470; edited classes leave their old texts behind)
MAX_ENTRIES = 4000
_PACKAGE = "volwarp_cli"

_kept: dict[str, bytes] = {}     # text -> its marshalled code, as the table was read
_made: dict[str, object] = {}    # text -> code object this process compiled
_used: set[str] = set()          # texts this process executed (kept by a write)
_installed = False


def _magic() -> bytes:
    from importlib.util import MAGIC_NUMBER  # (imported by site before any command)

    return MAGIC_NUMBER


def table_path() -> str | None:
    """The table's path, or None where this Python keeps no bytecode (no cache tag).

    Beside the package's bytecode: its ``__pycache__``, or the mirror folder under
    ``PYTHONPYCACHEPREFIX`` where that is set.
    """
    if sys.implementation.cache_tag is None:
        return None
    from importlib.util import cache_from_source

    here = os.path.join(os.path.dirname(os.path.abspath(__file__)), "__init__.py")
    return os.path.join(os.path.dirname(cache_from_source(here)), FILE)


def load(path: str | None) -> dict[str, bytes]:
    """The table at ``path``: ``{text: marshalled code}``; empty where missing, damaged or another Python's.

    (Each code object is unmarshalled when its text is executed: reading all of
    them, about 370, would take 2.5 ms of a command that runs a third.)
    """
    if path is None:
        return {}
    try:
        with open(path, "rb") as f:
            data = f.read()
    except OSError:
        return {}
    magic = _magic()
    if not data.startswith(magic):
        return {}
    try:
        table = marshal.loads(data[len(magic):])
    except (EOFError, ValueError, TypeError):
        return {}
    if not isinstance(table, dict):
        return {}
    return {k: v for k, v in table.items() if isinstance(k, str) and isinstance(v, bytes)}


def _code(source: str):
    """The code of ``source``: kept, or compiled as ``exec(source)`` compiles it."""
    code = _made.get(source)
    if code is not None:
        return code
    kept = _kept.get(source)
    if kept is not None:
        try:
            code = marshal.loads(kept)
        except (EOFError, ValueError, TypeError):
            code = None
        if isinstance(code, _CODE):
            return code
        del _kept[source]  # (damaged: compiled below, and written again)
    # no future flags inherited (as above), the file name exec gives a text
    code = compile(source, "<string>", "exec", dont_inherit=True)
    _made[source] = code
    return code


_CODE = type(_code.__code__)


def _ours(globals_) -> bool:
    name = globals_.get("__name__") if isinstance(globals_, dict) else None
    return isinstance(name, str) and (name == _PACKAGE or name.startswith(_PACKAGE + "."))


def _exec(source, globals=None, locals=None, /, **kwargs):  # noqa: A002 (exec's own names)
    """``exec`` for the ``dataclasses`` module: a volwarp class's text compiled once (module notes)."""
    if not isinstance(source, str):
        return builtins.exec(source, globals, locals, **kwargs)
    if kwargs or not _ours(globals):
        # compiled here as it would be in dataclasses: exec(text) called from this
        # module would inherit its `annotations` future (annotations made strings)
        return builtins.exec(compile(source, "<string>", "exec", dont_inherit=True),
                             globals, locals, **kwargs)
    code = _code(source)
    _used.add(source)
    return builtins.exec(code, globals, locals)


def install(path: str | None = None) -> None:
    """Compile volwarp's dataclass methods from the kept table (module notes); once per process."""
    global _installed
    if _installed:
        return
    import dataclasses

    _kept.update(load(table_path() if path is None else path))
    dataclasses.exec = _exec  # (the module's own global: found before the built-in)
    _installed = True


def save(path: str | None = None, *, force: bool = False) -> bool:
    """Write the table where this process compiled texts it lacked; whether it was written.

    ``force``: write even where ``PYTHONDONTWRITEBYTECODE`` is set (the warm-up,
    as ``compileall`` writes bytecode whatever that says). Never raises: a table
    not written only costs a later command the compilations.
    """
    if not _installed or not _made or (sys.dont_write_bytecode and not force):
        return False
    path = table_path() if path is None else path
    if path is None:
        return False
    table = load(path)  # (another process may have added its texts meanwhile)
    ours = {text: _kept.get(text) or marshal.dumps(_made[text]) for text in _used}
    table.update(ours)
    if len(table) > MAX_ENTRIES:
        table = ours
    tmp = f"{path}.{os.getpid()}.tmp"
    try:
        os.makedirs(os.path.dirname(path), exist_ok=True)
        with open(tmp, "wb") as f:
            f.write(_magic() + marshal.dumps(table))
        os.replace(tmp, path)  # (another process reads either table, whole)
        _kept.update(ours)
        _made.clear()
    except (OSError, ValueError):
        try:
            os.unlink(tmp)
        except OSError:
            pass
        return False
    return True
