"""volwarp's log imports :mod:`logging` only when a record may be emitted (progress._VolwarpLog).

A command at the default verbosity mostly says nothing: the logging module (and
``concurrent.futures``, which imports it) stay unloaded, 5 ms of every start.
The records asked for (-v), the warnings said at the default level and -q's
silence must not change for it. Each run is a fresh process: the test process
has logging loaded already (pytest's), where the log is the real logger's.
"""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import pytest

from volwarp_cli.warmup import write_inputs


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    folder = tmp_path_factory.mktemp("lazy_logging")
    return folder, write_inputs(folder)


def _volwarp(folder, *args):
    """``volwarp ARGS`` in a fresh interpreter: (exit code, stderr, modules loaded at the end)."""
    code = textwrap.dedent(f"""
        import json, sys
        from volwarp_cli.cli.main import main
        code = main({list(args)!r})
        sys.stdout.write("\\n" + json.dumps([m for m in ("logging", "concurrent.futures")
                                            if m in sys.modules]))
        sys.exit(code)
        """)
    res = subprocess.run([sys.executable, "-c", code], cwd=folder, capture_output=True,
                         text=True, timeout=120)
    return res.returncode, res.stderr, json.loads(res.stdout.splitlines()[-1] or "null")


def test_a_warp_that_says_nothing_loads_no_logging(inputs):
    folder, p = inputs
    for threads in ("1", "2"):  # (two threads: the volume read beside the spec, the blocks)
        code, err, loaded = _volwarp(folder, "warp", p["blob"], "--spec", p["move"], "-o",
                                     f"w{threads}.nrrd", "--threads", threads)
        assert code == 0 and err == "", err
        assert loaded == [], loaded
        assert (folder / f"w{threads}.nrrd").stat().st_size > 4096


def test_records_asked_for_and_warnings_still_reach_stderr(inputs):
    folder, p = inputs
    code, err, loaded = _volwarp(folder, "warp", p["blob"], "--spec", p["move"], "-o",
                                 "v.nrrd", "-v")
    assert code == 0 and "volwarp: write v.nrrd: " in err and "logging" in loaded
    warn = ("warp", p["blob16"], "--spec", p["move"], "-o", "l.nrrd", "--labels")
    code, err, _ = _volwarp(folder, *warn)  # (labels asked for on a smooth volume)
    assert code == 0
    assert err.startswith("volwarp: warning: ") and "does not look like a label map" in err
    assert err.count("\n") == 1
    code, err, loaded = _volwarp(folder, *warn, "-q")
    assert code == 0 and err == "" and loaded == []


def test_a_readers_warning_is_the_command_lines_whoever_loaded_logging(inputs):
    """A reader that imports logging itself (tifffile's) says its warning through volwarp's
    log: the ``volwarp:`` prefix, and nothing with -q (it once went to logging's last-resort
    handler when it came before any other record)."""
    tifffile = pytest.importorskip("tifffile")
    import numpy as np

    folder, _ = inputs
    tifffile.imwrite(folder / "noz.ome.tif", np.zeros((4, 8, 8), np.uint8), ome=True,
                     metadata={"axes": "ZYX", "PhysicalSizeX": 0.5, "PhysicalSizeY": 0.5})
    code, err, _ = _volwarp(folder, "info", "noz.ome.tif")
    assert code == 0 and err.splitlines() == [
        "volwarp: warning: noz.ome.tif: the OME metadata give no PhysicalSizeZ: z spacing is 1"
    ], err
    code, err, _ = _volwarp(folder, "info", "noz.ome.tif", "-q")
    assert code == 0 and err == ""


def test_the_stand_in_reads_and_sets_the_real_loggers_attributes():
    """progress.log is the ``volwarp`` logger to a library caller: what it sets on it
    (propagate, level, disabled) is the logger's."""
    import logging

    from volwarp_cli.progress import log

    real = logging.getLogger("volwarp")
    before = real.propagate, real.level
    try:
        log.propagate = not before[0]
        log.level = logging.ERROR
        assert real.propagate is (not before[0]) and real.level == logging.ERROR
        assert log.propagate is real.propagate and log.getEffectiveLevel() == logging.ERROR
    finally:
        real.propagate, real.level = before


def test_a_caller_s_handler_does_not_take_the_command_line_s_stderr(inputs, tmp_path):
    """A Python caller (or a test) with its own handler on the "volwarp" logger before the
    first command left every command of that process without its stderr lines: the
    command line's handler was added only to a logger with no handler at all (a test
    of this session found a warning missing from stderr, order-dependent)."""
    folder, _ = inputs
    code = textwrap.dedent(f"""
        import io, logging, sys
        from click.testing import CliRunner
        from volwarp_cli.cli.main import cli
        kept = []
        class Keep(logging.Handler):
            def emit(self, record):
                kept.append(record.getMessage())
        logging.getLogger("volwarp").addHandler(Keep())
        res = CliRunner().invoke(cli, ["mesh", {str(folder / 'blob.nrrd')!r}, "--iso", "1e6",
                                       "--allow-empty", "-o", {str(tmp_path / 'e.ply')!r}])
        print(res.exit_code, "empty" in res.stderr, any("empty" in m for m in kept))
        """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120)
    assert out.stdout.split() == ["0", "True", "True"], (out.stdout, out.stderr)


def test_every_warning_line_says_warning_once(capsys):
    """Two thirds of volwarp's warnings wrote "warning:" themselves, the rest did not
    ("volwarp: steps[1]: the handles cannot all be reached"): the command line's log says
    it of every warning, once, and of nothing else."""
    import logging

    from volwarp_cli.progress import configure, log

    configure(1)
    try:
        log.warning("steps[%d]: the handles cannot all be reached", 1)
        log.warning("warning: %s: said by the caller", "x.nrrd")
        log.info("read x.nrrd: %.3f s", 0.5)
        logging.getLogger("volwarp.io").warning("a reader's own")
    finally:
        configure(0)
    assert capsys.readouterr().err.splitlines() == [
        "volwarp: warning: steps[1]: the handles cannot all be reached",
        "volwarp: warning: x.nrrd: said by the caller",
        "volwarp: read x.nrrd: 0.500 s",
        "volwarp: warning: a reader's own"]
