"""volwarp's dataclass methods compiled once and kept (volwarp_cli/dataclass_code.py).

Each check runs in a fresh interpreter: the table is loaded, and ``dataclasses``
patched, once per process; the table is a file of the test's own.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import numpy as np

from volwarp_cli.io import write_volume
from volwarp_cli.volume import Volume

# Classes of every kind dataclasses writes methods for: frozen (__setattr__,
# __delattr__, __hash__), ordered, keyword-only, slots, defaults and factories,
# a field kept out of the comparison, an annotation that must stay a type.
CLASSES = '''
import dataclasses
from dataclasses import dataclass, field

@dataclass(frozen=True)
class Point:
    """A point."""
    x: float
    y: float = 0.0
    tags: tuple = ()

@dataclass(order=True)
class Ranked:
    rank: int
    name: str = field(default="n", compare=False)
    items: list = field(default_factory=list)

@dataclass(kw_only=True, slots=True)
class Options:
    threads: int = 1
    block: "tuple | None" = None

@dataclass(eq=False)
class Plain:
    a: int
'''

PROBE = '''
import json, sys, types
from volwarp_cli import dataclass_code as d
d.install(sys.argv[1])

def define(module_name):
    m = types.ModuleType(module_name)
    sys.modules[module_name] = m
    exec(CLASSES, m.__dict__)
    return m

other = define("elsewhere._probe_classes")        # another package's: not kept
kept_other = len(d._made) + len(d._used)
ours = define("volwarp_cli._probe_classes")      # through the table
facts = {"compiled": len(d._made), "kept_other": kept_other,
         "saved": d.save(sys.argv[1], force=sys.argv[2] == "force")}
def behaviour(m):
    p = m.Point(1.5, tags=(2,))
    try:
        p.x = 3
        frozen = "no"
    except Exception as exc:
        frozen = type(exc).__name__
    r = sorted([m.Ranked(3), m.Ranked(1, "b", [1])])
    o = m.Options(threads=2)
    try:
        m.Options(2)
        positional = "accepted"
    except TypeError as exc:
        positional = str(exc)
    return [repr(p), hash(p) == hash(m.Point(1.5, 0.0, (2,))), p == m.Point(1.5, 0, (2,)), frozen,
            repr(r), m.Ranked(1, "x") == m.Ranked(1, "y"), repr(o), hasattr(o, "__dict__"),
            positional, m.Plain(1) == m.Plain(1), list(m.Point.__match_args__),
            repr(m.Point.__init__.__annotations__), repr(m.Options.__init__.__annotations__),
            m.Point.__init__.__defaults__ == m.Point.__init__.__defaults__]
def code(m):
    return [[getattr(getattr(m.Point, f).__code__, a) == getattr(getattr(other.Point, f).__code__, a)
             for a in ("co_code", "co_consts", "co_names", "co_varnames", "co_filename")]
            for f in ("__init__", "__repr__", "__eq__", "__hash__", "__setattr__", "__delattr__")]
facts["ours"] = behaviour(ours)
facts["other"] = behaviour(other)
facts["same_code"] = code(ours)
print(json.dumps(facts))
'''


def _probe(table, force=True, env=None) -> dict:
    script = f"CLASSES = {CLASSES!r}\n" + PROBE
    res = subprocess.run([sys.executable, "-c", script, str(table), "force" if force else "-"],
                         capture_output=True, text=True, timeout=120,
                         env=dict(os.environ, **(env or {})))
    assert res.returncode == 0, res.stderr
    return json.loads(res.stdout)


def test_kept_methods_are_the_ones_exec_compiles(tmp_path):
    table = tmp_path / "table.bin"
    first = _probe(table)
    assert first["compiled"] > 10 and first["saved"] and table.exists()
    assert first["kept_other"] == 0  # (another package's classes: not through the table)
    second = _probe(table)
    assert second["compiled"] == 0  # every method came from the table
    assert second["saved"] is False  # (nothing new to keep)
    # the classes behave as the built-in exec's do, annotations still types, not strings
    assert second["ours"] == second["other"] == first["ours"]
    assert "<class 'float'>" in second["ours"][11]
    assert second["same_code"] == [[True] * 5] * 6


def test_a_damaged_or_foreign_table_costs_only_the_compilations(tmp_path):
    import marshal
    from importlib.util import MAGIC_NUMBER

    table = tmp_path / "table.bin"
    good = _probe(table)["ours"]
    entries = marshal.loads(table.read_bytes()[len(MAGIC_NUMBER):])
    damaged = {
        "garbage": b"\x00\x01not a table",
        "another Python's": b"\x01\x02\r\n" + table.read_bytes()[len(MAGIC_NUMBER):],
        "truncated": table.read_bytes()[:100],
        "not code": MAGIC_NUMBER + marshal.dumps({text: marshal.dumps(12) for text in entries}),
        "not a dict": MAGIC_NUMBER + marshal.dumps([1, 2]),
    }
    for name, data in damaged.items():
        table.write_bytes(data)
        facts = _probe(table)
        assert facts["compiled"] > 10, name
        assert facts["ours"] == good, name
        assert facts["saved"], name  # and written again, whole
        assert _probe(table)["compiled"] == 0, name


def test_not_written_where_bytecode_is_not(tmp_path):
    table = tmp_path / "table.bin"
    facts = _probe(table, force=False, env={"PYTHONDONTWRITEBYTECODE": "1"})
    assert facts["saved"] is False and not table.exists()
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o555)
    try:
        if os.access(locked, os.W_OK):  # (root writes anywhere: a file in the way instead)
            (locked / "x").write_text("")
            table = locked / "x" / "table.bin"
        else:
            table = locked / "table.bin"
        facts = _probe(table, force=False, env={"PYTHONDONTWRITEBYTECODE": ""})
        assert facts["saved"] is False
        assert facts["ours"] == facts["other"]
    finally:
        locked.chmod(0o755)
    assert sorted(p.name for p in locked.iterdir()) in ([], ["x"])  # no temporary left


def test_a_full_table_keeps_what_its_process_used(tmp_path, monkeypatch):
    import marshal
    from importlib.util import MAGIC_NUMBER

    from volwarp_cli import dataclass_code

    table = tmp_path / "table.bin"
    _probe(table)
    used = marshal.loads(table.read_bytes()[len(MAGIC_NUMBER):])
    stale = {f"def old_{i}(): pass": marshal.dumps(compile("1", "<string>", "exec"))
             for i in range(dataclass_code.MAX_ENTRIES)}
    table.write_bytes(MAGIC_NUMBER + marshal.dumps({**stale, **used}))
    # a process that compiles one text more: the table is over its size, so it keeps its own
    script = (f"CLASSES = {CLASSES!r}\n" + PROBE).replace(
        "ours = define(", "exec('from dataclasses import dataclass\\n@dataclass\\nclass New:\\n"
        "    q: int', define('volwarp_cli._probe_new').__dict__)\nours = define(")
    res = subprocess.run([sys.executable, "-c", script, str(table), "force"],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    kept = marshal.loads(table.read_bytes()[len(MAGIC_NUMBER):])
    assert set(used) < set(kept) and not any(t.startswith("def old_") for t in kept)


def test_a_command_keeps_its_classes_methods_for_the_next(tmp_path):
    """The command line installs the table and writes it at its end; the next run compiles none."""
    write_volume(Volume(np.arange(4096, dtype=np.float32).reshape(16, 16, 16)),
                 tmp_path / "v.nrrd")
    table = tmp_path / "table.bin"
    script = textwrap.dedent(f'''
        import os, sys
        from volwarp_cli import dataclass_code as d
        d.table_path = lambda: {str(table)!r}
        compiled = []  # (the texts compiled, counted when the command saves them)
        real_save = d.save
        d.save = lambda *a, **k: compiled.extend(d._made) or real_save(*a, **k)
        real_exit = os._exit
        def report(code):
            sys.stderr.write(f"\\ncompiled {{len(compiled)}}\\n")
            real_exit(code)
        os._exit = report
        sys.argv = ["volwarp", "convert", {str(tmp_path / "v.nrrd")!r}, "-o",
                    {str(tmp_path / "c.nii")!r}]
        from volwarp_cli.entry import main
        main()
    ''')
    counts = []
    for _ in range(2):
        (tmp_path / "c.nii").unlink(missing_ok=True)
        res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                             timeout=300, env=dict(os.environ, PYTHONDONTWRITEBYTECODE=""))
        assert res.returncode == 0, res.stderr
        assert (tmp_path / "c.nii").exists()
        counts.append(int(res.stderr.rsplit("compiled ", 1)[1]))
    assert counts[0] > 20 and counts[1] == 0


def test_the_table_goes_where_python_puts_bytecode(tmp_path):
    """Beside the package's ``__pycache__``; under ``PYTHONPYCACHEPREFIX`` where that is set
    (it was written into the source tree beside a prefix's bytecode)."""
    import volwarp_cli

    code = ("from volwarp_cli import dataclass_code as d, warmup\n"
            "warmup.main(['--list'])\n"  # (lists the commands: patches nothing)
            "import dataclasses\n"
            "print(d.table_path()); print('exec' in vars(dataclasses))")
    package = os.path.dirname(volwarp_cli.__file__)
    for prefix, folder in ((None, os.path.join(package, "__pycache__")),
                           (str(tmp_path / "prefix"), str(tmp_path / "prefix") + package)):
        env = {k: v for k, v in os.environ.items() if k != "PYTHONPYCACHEPREFIX"}
        if prefix:
            env["PYTHONPYCACHEPREFIX"] = prefix
        res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                             timeout=120, env=env)
        assert res.returncode == 0, res.stderr
        path, patched = res.stdout.splitlines()[-2:]
        assert os.path.dirname(path) == folder and patched == "False"
