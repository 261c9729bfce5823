"""A stop is a stop: SIGTERM / SIGINT at any moment of a run exits 143 / 130 with one line,
the old output intact and no temporary file left (or the run had finished: exit 0, the
new output complete).

Each command is run once to completion (its length and its reference output), then
again and again with the signal sent at delays swept over that length.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from volwarp_cli.signals import STOPS

DATA = Path(__file__).parent / "data"
VOLWARP = Path(sys.executable).parent / "volwarp"
OLD = b"the old output, complete\n"

pytestmark = [pytest.mark.slow,
              pytest.mark.skipif(not VOLWARP.exists(), reason="the volwarp command is not installed")]


def _commands(tmp: Path):
    scan = tmp / "scan.nrrd"
    scan.write_bytes((DATA / "mri_colin27_brain_1mm.nrrd").read_bytes())
    spec = tmp / "w.yaml"
    spec.write_text("version: 1\ncapture: {lattice: 7, oversample: 1}\nsteps:\n"
                    "  - move:\n      - {index: [3, 3, 3], by: [6.0, 0.0, 0.0]}\n")
    # (convert: the scan's 7 MB to .nii.gz took 0.2-0.3 s once nibabel came without
    # pydicom, over before a Ctrl-C from 0.25 s could land; a larger, noisy int16 scan
    # written as float64 takes about a second)
    from volwarp_cli.io import read_volume, write_volume

    vol = read_volume(scan)
    tiled = np.tile(vol.data, (2, 2, 1)).astype(np.int16) * 8
    tiled += np.random.default_rng(0).integers(0, 8, tiled.shape, dtype=np.int16)
    big = tmp / "big.nrrd"
    write_volume(vol.with_data(tiled), big)
    return {
        "convert": (["convert", big, "-o", tmp / "out.nii.gz", "--dtype", "float64"],
                    tmp / "out.nii.gz"),
        "info": (["info", tmp / "ras.nii.gz"], None),
        "distance": (["distance", scan, "--iso", "40", "-o", tmp / "d.nrrd"], tmp / "d.nrrd"),
        "warp": (["warp", scan, "--spec", spec, "-o", tmp / "w.nrrd"], tmp / "w.nrrd"),
        # (decimated: the plain isosurface takes about 0.25 s, over before a stop lands)
        "mesh": (["mesh", scan, "--iso", "40", "--decimate", "0.5", "-o", tmp / "m.ply"],
                 tmp / "m.ply"),
    }


def _default_stops():
    """The stops a job gets from a terminal: a suite run under ``nohup`` (SIGHUP ignored,
    which a child inherits and volwarp then honours) would find nothing to stop."""
    for signum in STOPS:
        signal.signal(signum, signal.SIG_DFL)


def _run(args, env, delay=None, signum=None):
    start = time.perf_counter()
    proc = subprocess.Popen([str(VOLWARP)] + [str(a) for a in args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, env=env, preexec_fn=_default_stops)
    if delay is not None:
        time.sleep(delay)
        proc.send_signal(signum)
    out, err = proc.communicate(timeout=120)
    return proc.returncode, err.decode(), time.perf_counter() - start


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT], ids=["TERM", "INT"])
@pytest.mark.parametrize("name", ["convert", "info", "distance", "warp", "mesh"])
def test_a_stop_at_any_moment_keeps_the_old_output(tmp_path, name, signum):
    _stop_at_any_moment(tmp_path, name, signum)


@pytest.mark.parametrize(("name", "signum"), [("distance", signal.SIGHUP),
                                              ("convert", signal.SIGQUIT),
                                              ("warp", signal.SIGUSR1)],
                         ids=["HUP", "QUIT", "USR1"])
def test_a_closed_terminal_is_a_stop_too(tmp_path, name, signum):
    """SIGHUP (a job left in the foreground of an ssh session that closes) and SIGQUIT
    (Ctrl-\\) killed the process as they came: a distance by blocks left its hidden
    256 MB temporary output behind, exit 129. Now stops like SIGTERM's; so does a batch
    system's warning before its time limit (Slurm's ``--signal=USR1@60``)."""
    _stop_at_any_moment(tmp_path, name, signum)


def test_nohup_keeps_a_job_going(tmp_path):
    """A job started with SIGHUP ignored (``nohup``) goes on through a SIGHUP: the handler
    is installed only where the signal is not ignored."""
    args, out = _commands(tmp_path)["convert"]
    proc = subprocess.Popen([str(VOLWARP)] + [str(a) for a in args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE,
                            preexec_fn=lambda: signal.signal(signal.SIGHUP, signal.SIG_IGN))
    try:  # (the signal while the output is written: a fixed 0.5 s missed a 0.49 s job)
        deadline = time.monotonic() + 60
        while (proc.poll() is None and time.monotonic() < deadline
               and not any(".part" in n for n in os.listdir(tmp_path))):
            time.sleep(0.002)
        assert proc.poll() is None, "the job ended before the SIGHUP: nothing tested"
        proc.send_signal(signal.SIGHUP)
    finally:  # (its pipes closed whatever happened: left open, they failed a later test)
        _, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, err
    assert out.exists()


def _stop_at_any_moment(tmp_path, name, signum):
    args, out = _commands(tmp_path)[name]
    if name == "info":  # read a NIfTI (nibabel's optional imports used to swallow the stop;
        # the larger scan's: the bundled one's info ended before a Ctrl-C from 0.25 s)
        code, err, _ = _run(["convert", tmp_path / "big.nrrd", "-o", tmp_path / "ras.nii.gz",
                             "--dtype", "float64"], os.environ)
        assert code == 0, err
    env = dict(os.environ)
    code, err, length = _run(args, env)
    assert code == 0, err
    reference = out.read_bytes() if out else None
    before = set(os.listdir(tmp_path))
    if signum == signal.SIGINT:
        # from 0.25 s: before that the interpreter may still be starting (site, the
        # editable install's finder), where a Ctrl-C is Python's own KeyboardInterrupt,
        # before any volwarp code runs (SIGTERM there kills the process cleanly: -15)
        delays = np.linspace(0.25, max(length * 0.9, 0.3), 3 if name in ("info", "mesh")
                             else 5)
    else:
        delays = np.concatenate([[0.03, 0.08, 0.15], np.linspace(0.2, length * 1.05, 5)])
    seen = {"stopped": 0, "finished": 0}
    for delay in delays:
        if out is not None:
            out.write_bytes(OLD)
        code, err, _ = _run(args, env, float(delay), signum)
        assert "Traceback" not in err, (delay, err)
        assert set(os.listdir(tmp_path)) == before, (delay, "a temporary file was left")
        if code == 0:
            seen["finished"] += 1
            if out is not None:
                assert out.read_bytes() == reference, (delay, "exit 0 with a wrong output")
            continue
        assert code in (128 + signum, -signum), (delay, code, err)
        seen["stopped"] += 1
        if code == 128 + signum:  # our handler ran (-signum: killed before Python started it)
            lines = err.strip().splitlines()
            assert lines[-1] == f"volwarp: error: interrupted by {signum.name}", (delay, err)
        if out is not None:
            # the old output, or (a stop landing after the output's rename, in the last
            # moments of the run) the complete new one: never anything else
            assert out.read_bytes() in (OLD, reference), (delay, "output damaged")
    assert seen["stopped"] >= (2 if signum == signal.SIGTERM else 1), seen  # not vacuous


def test_stale_temporaries_of_dead_processes_are_removed_and_others_kept(tmp_path):
    """SIGKILL leaves a temporary behind; the next write of the same output removes it
    (a dead pid of this host), never a live process's or another host's."""
    out = tmp_path / "o.nrrd"
    stale = []
    for _ in range(5):  # the temporary lives for the write only (tens of ms): catch it
        proc = subprocess.Popen([str(VOLWARP), "distance", DATA / "mri_colin27_brain_1mm.nrrd",
                                 "--iso", "40", "-o", out])
        while proc.poll() is None and not any(".part" in n for n in os.listdir(tmp_path)):
            time.sleep(0.001)
        proc.kill()
        proc.wait()
        stale = [n for n in os.listdir(tmp_path) if ".part" in n]
        if stale:
            break
        out.unlink(missing_ok=True)
    assert stale, "the killed run had no temporary to leave"
    assert f".vw-{proc.pid}@" in stale[0]  # says whose it is
    host = stale[0].split("@", 1)[1].split(".", 1)[0]
    alive = tmp_path / f".o.nrrd.vw-{os.getpid()}@{host}.abcdefgh.part.nrrd"
    other_host = tmp_path / f".o.nrrd.vw-{proc.pid}@elsewhere.abcdefgh.part.nrrd"
    unrelated = tmp_path / ".o.nrrd.notours.part.nrrd"
    for p in (alive, other_host, unrelated):
        p.write_bytes(b"x")
    code, err, _ = _run(["convert", DATA / "ball_30_uint8.nrrd", "-o", out], os.environ)
    assert code == 0, err
    left = set(os.listdir(tmp_path))
    assert not set(stale) & left
    assert {alive.name, other_host.name, unrelated.name} <= left


def test_a_detached_pair_is_both_old_or_both_new_after_a_stop(tmp_path):
    """`.mhd` + `.raw`: the header was renamed before its data file, so a stop between the
    two renames left a new header over old samples (a wrong image, read without error)."""
    big = tmp_path / "big.nrrd"
    other = tmp_path / "other.nrrd"
    rng = np.random.default_rng(4)
    from volwarp_cli.io import write_volume
    from volwarp_cli.volume import Volume
    # (big enough that a convert lasts long enough for stops to land: 96^3 took 0.12 s, and
    # in one CI run all twelve stops came after the end)
    write_volume(Volume(rng.random((160, 160, 160), dtype=np.float32)), big)
    write_volume(Volume(rng.random((160, 160, 160), dtype=np.float32) * 0.5,
                        origin=(5, 0, 0)), other)
    out = tmp_path / "o" / "out.mhd"
    out.parent.mkdir()
    refs = {}
    for src in (other, big):
        code, err, length = _run(["convert", src, "-o", out], os.environ)
        assert code == 0, err
        refs[src] = (out.read_bytes(), out.with_suffix(".raw").read_bytes())
    stopped = 0
    for delay in np.linspace(0.05, max(length * 1.1, 0.3), 12):
        code, err, _ = _run(["convert", other, "-o", out], os.environ)
        assert code == 0, err
        code, err, _ = _run(["convert", big, "-o", out], os.environ, float(delay),
                            signal.SIGTERM)
        pair = (out.read_bytes(), out.with_suffix(".raw").read_bytes())
        assert pair in (refs[other], refs[big]), (delay, code, "a mixed pair")
        assert sorted(os.listdir(out.parent)) == ["out.mhd", "out.raw"], (delay, "temporary")
        stopped += code in (143, -15)
    assert stopped >= 1


def test_a_stop_landing_on_the_way_out_changes_nothing():
    """The exit of a command-line run, once its code is decided: a stop raising there (a
    deferred stop's re-check timer, a second Ctrl-C) is absorbed; the process ends with
    the decided code, one line, no traceback (an escaping stop used to skip the fast
    exit: a traceback, and the interpreter's tear-down with numba's threads alive could
    crash with SIGSEGV)."""
    script = (
        "import signal, time\n"
        "from volwarp_cli import signals\n"
        "from volwarp_cli.cli import main as m\n"
        "signals.install()\n"
        "signals._stop.append(signal.SIGTERM)\n"
        "real = m.settle_signals\n"
        "calls = []\n"
        "def landing():\n"
        "    calls.append(1)\n"
        "    if len(calls) < 3:\n"
        "        raise signals.Interrupted(signal.SIGTERM)\n"
        "    real()\n"
        "m.settle_signals = landing\n"
        "m._end_process(143)\n"
        "print('not reached')\n")
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 143, proc
    assert "Traceback" not in proc.stderr and "not reached" not in proc.stdout


def test_a_deferred_stops_timer_is_cancelled_once_the_work_is_over():
    script = (
        "import signal, time\n"
        "from volwarp_cli import signals\n"
        "signals.install()\n"
        "signals._stop.append(signal.SIGINT)\n"
        "signal.signal(signal.SIGALRM, lambda s, f: signals._raise_when_safe(f))\n"
        "signal.setitimer(signal.ITIMER_REAL, 0.05)\n"
        "signals.cancel_deferred()\n"
        "time.sleep(0.2)\n"
        "print('no late raise')\n")
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 0 and "no late raise" in proc.stdout, proc


def test_a_stop_taken_by_another_thread_waits_for_the_blocked_section():
    """The signal mask is the calling thread's: another thread takes the signal and
    Python runs the handler in the main thread at its next bytecode, inside a blocked()
    section (it raised in the middle of mkstemp: the file made, never registered, left
    behind). The stop is raised when the section ends, and its temporaries go."""
    script = (
        "import os, signal, tempfile, threading, time\n"
        "from volwarp_cli import signals\n"
        "signals.install()\n"
        "d = tempfile.mkdtemp()\n"
        "go = threading.Event()\n"
        "def other():\n"
        "    go.wait()\n"
        "    os.kill(os.getpid(), signal.SIGINT)\n"
        "t = threading.Thread(target=other)\n"
        "t.start()\n"
        "state = []\n"
        "try:\n"
        "    with signals.blocked():\n"
        "        go.set()\n"
        "        t.join()\n"
        "        for _ in range(10000):\n"
        "            pass\n"
        "        time.sleep(0.05)\n"
        "        fd, tmp = tempfile.mkstemp(dir=d)\n"
        "        os.close(fd)\n"
        "        signals.temporaries.add(tmp)\n"
        "        state.append('section done')\n"
        "except signals.Interrupted:\n"
        "    state.append('raised after')\n"
        "print(state, os.listdir(d))\n")
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 0, proc
    assert proc.stdout.strip() == "['section done', 'raised after'] []", proc.stdout


@pytest.mark.parametrize("where", ["entry", "main"])
def test_a_deferred_stop_landing_before_the_command_line_starts_is_one_line(where):
    """A stop that arrives during the start-up imports is deferred (its timer looks again
    every 20 ms) and can land after them, before the command line's own handling of
    stops: between the entry's imports and the call (entry), or in cli.main's first
    steps (main). One line and 128 + the signal, never a traceback."""
    if where == "entry":
        land = ("from volwarp_cli.cli import main as m\n"
                "def run(argv=None):\n"
                "    raise signals.Interrupted(signal.SIGTERM)\n"
                "m.main = run\n"
                "from volwarp_cli import entry\n"
                "entry.main()\n")
    else:
        land = ("from volwarp_cli.cli import main as m\n"
                "def landing():\n"
                "    raise signals.Interrupted(signal.SIGTERM)\n"
                "m.install_signal_handlers = landing\n"
                "m.main(['info', '--help'])\n"
                "import os; os._exit(0)\n")
    script = "import signal, sys\nfrom volwarp_cli import signals\n" + land
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=60)
    assert "Traceback" not in proc.stderr, proc.stderr
    assert proc.stderr.strip().count("\n") == 0 and "interrupted by SIGTERM" in proc.stderr
    assert proc.returncode == (143 if where == "entry" else 0), proc
