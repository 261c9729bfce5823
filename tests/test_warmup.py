"""The warm-up compiles the kernels the commands load, wherever the package is installed.

``python -m volwarp_cli.warmup`` (run by ``make install``) compiles every numba
kernel into the cache the commands use: the package's ``__pycache__`` folders
when they are writable, else a per-user folder that the install's kernels are
copied into (:func:`volwarp_cli.entry.configure_numba_cache`). The main test
copies the package, warms it, makes it read-only and runs commands from it as
another user, reading numba's own cache log (``NUMBA_DEBUG_CACHE=1``): they
load the install's kernels and compile nothing, the first run and the second.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import stat
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

import volwarp_cli
from volwarp_cli import entry, warmup

PKG = Path(volwarp_cli.__file__).resolve().parent
ROOT = PKG.parent
SETPRIV = shutil.which("setpriv")
IS_ROOT = hasattr(os, "geteuid") and os.geteuid() == 0


def _env(**extra) -> dict:
    env = {k: v for k, v in os.environ.items()
           if not k.startswith(("NUMBA_", "XDG_", "PYTHON", "COV_"))}
    env.update(extra)
    return env


def _chmod_tree(top: Path, writable: bool) -> None:
    for folder, _dirs, files in os.walk(top):
        for name in files:
            path = os.path.join(folder, name)
            mode = os.stat(path).st_mode
            os.chmod(path, mode | stat.S_IWUSR if writable else mode & ~0o222)
        os.chmod(folder, 0o755 if writable else 0o555)


@pytest.fixture
def shared_tmp():
    """A folder another user can read (pytest's tmp_path is private to its owner)."""
    top = Path(tempfile.mkdtemp(prefix="volwarp-test-warmup-"))
    top.chmod(0o755)
    try:
        yield top
    finally:
        _chmod_tree(top, writable=True)
        shutil.rmtree(top, ignore_errors=True)


def _cache_log(output: str) -> tuple[list[str], list[str]]:
    """numba's cache log lines: (loaded, saved)."""
    lines = [line for line in output.splitlines() if line.startswith("[cache]")]
    return ([line for line in lines if " loaded from " in line],
            [line for line in lines if " saved to " in line])


@pytest.mark.slow
@pytest.mark.skipif(IS_ROOT and SETPRIV is None, reason="root without setpriv: cannot drop "
                    "to a user the read-only folder refuses")
def test_read_only_install_loads_the_install_kernels(shared_tmp):
    site = shared_tmp / "site"
    shutil.copytree(PKG, site / "volwarp_cli")  # with the install's own caches, if any
    for old in (site / "volwarp_cli" / "__pycache__").glob(entry.WARMUP_MARK):
        old.unlink()

    # the install: the warm-up, into the copy's __pycache__ folders (loaded from the copied
    # caches where the source is the same, compiled where not)
    done = subprocess.run([sys.executable, "-m", "volwarp_cli.warmup", "-q"], cwd=shared_tmp,
                          env=_env(PYTHONPATH=str(site)), capture_output=True, text=True,
                          timeout=900)
    assert done.returncode == 0, done.stderr
    assert (site / "volwarp_cli" / "__pycache__" / entry.WARMUP_MARK).is_file()
    installed = sorted(p.name for p in site.rglob("*.nbi"))
    assert len(installed) >= 10, installed

    data = shared_tmp / "data"
    data.mkdir()
    inputs = warmup.write_inputs(str(data))
    out = shared_tmp / "out"
    home = shared_tmp / "home"
    for folder in (out, home):
        folder.mkdir()
        folder.chmod(0o777)
    _chmod_tree(site, writable=False)  # the install is read-only from here on

    user = [SETPRIV, "--reuid=65534", "--regid=65534", "--clear-groups"] if IS_ROOT else []
    volwarp = [*user, sys.executable, "-m", "volwarp_cli"]
    env = _env(PYTHONPATH=str(site), HOME=str(home), NUMBA_DEBUG_CACHE="1")
    if user and subprocess.run([*user, sys.executable, "-c", "import numpy, numba"], env=env,
                               cwd=shared_tmp, capture_output=True).returncode != 0:
        pytest.skip("the unprivileged user cannot run this interpreter (installed in a "
                    "private folder)")
    # (command line, whether it loads numba kernels: the exact distance, the warp, apply and
    # the sweep's voxeliser are C; the sub-voxel distance, the mesh's statistics and
    # renderer and the sweep's ray caster (--render) are numba's)
    commands = [
        (["distance", inputs["mask"], "--iso", "100", "-o", str(out / "d.nrrd")], False),
        (["distance", inputs["blob"], "--iso", "50", "-o", str(out / "sdf.nrrd")], True),
        (["warp", inputs["blob"], "--spec", inputs["move"], "-o", str(out / "w.nrrd"),
          "--jacobian-to", str(out / "j.nrrd")], False),
        (["mesh", inputs["blob"], "--iso", "50", "-o", str(out / "m.ply"), "--stats",
          "--render", str(out / "m.png"), "--render-size", "64x48"], True),
        (["sweep", inputs["bezier"], "-o", str(out / "s_{field}.nrrd"), "--spacing", "1",
          "--render", str(out / "s.png"), "--render-size", "48x32"], True),
        # a float64 displacement field, as SimpleITK writes them (apply's kernels are C)
        (["apply", inputs["blob"], "-o", str(out / "a64.nrrd"), "-t", inputs["field64"]], False),
    ]
    for run in ("first", "second"):
        for args, kernels in commands:
            done = subprocess.run([*volwarp, *args], cwd=shared_tmp, env=env,
                                  capture_output=True, text=True, timeout=300)
            assert done.returncode == 0, (run, args[0], done.stderr)
            loaded, saved = _cache_log(done.stdout + done.stderr)
            assert not saved, (run, args[0], saved)  # nothing compiled
            assert bool(loaded) == kernels, (run, args, loaded)  # from the cache, or none
    # the cache the commands used: the per-user one, holding the install's kernels
    cache = home / ".cache" / "volwarp" / "numba"
    assert sorted(p.name for p in cache.rglob("*.nbi")) == installed
    assert not list(site.rglob(".*.tmp"))


def test_numba_finds_the_copied_kernels_where_it_looks():
    import numba.core.caching as caching

    source = PKG / "distance" / "exact.py"
    assert entry._numba_subpath(str(source.parent)) == \
        caching._CacheLocator.get_suitable_cache_subpath(str(source))


def test_seed_copies_once_per_warmup(tmp_path):
    pkg = tmp_path / "pkg"
    (pkg / "distance" / "__pycache__").mkdir(parents=True)
    (pkg / "__pycache__").mkdir()
    (pkg / "distance" / "__pycache__" / "minnorm.axis_pass-1.py311.nbi").write_bytes(b"index")
    (pkg / "distance" / "__pycache__" / "minnorm.axis_pass-1.py311.1.nbc").write_bytes(b"code")
    (pkg / "distance" / "__pycache__" / "minnorm.cpython-311.pyc").write_bytes(b"bytecode")
    cache = tmp_path / "cache"
    cache.mkdir()
    assert entry.seed_cache(str(cache), str(pkg)) == 0  # no warm-up at install: nothing
    (pkg / "__pycache__" / entry.WARMUP_MARK).write_text("1\n")
    assert entry.seed_cache(str(cache), str(pkg)) == 2
    sub = cache / ("distance_" + hashlib.sha1(str(pkg / "distance").encode()).hexdigest())
    assert sorted(p.name for p in sub.iterdir()) == ["minnorm.axis_pass-1.py311.1.nbc",
                                                     "minnorm.axis_pass-1.py311.nbi"]
    assert entry.seed_cache(str(cache), str(pkg)) == 0  # done for this warm-up
    (pkg / "__pycache__" / entry.WARMUP_MARK).write_text("2\n")  # a new install
    assert entry.seed_cache(str(cache), str(pkg)) == 2


def test_cache_dir_choice(tmp_path, monkeypatch):
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert entry.user_cache_dir() == str(tmp_path / "xdg" / "volwarp" / "numba")
    if os.access(PKG, os.W_OK):
        assert entry.numba_cache_dir() is None  # beside the sources, where make install wrote
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "mine"))
    assert entry.numba_cache_dir() is None  # the user's own folder stands
    assert entry.configure_numba_cache() is None
    assert os.environ["NUMBA_CACHE_DIR"] == str(tmp_path / "mine")


def test_warmup_covers_every_command(capsys):
    assert warmup.main(["--list"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert {line.split()[1] for line in lines} >= {"capture", "warp", "distance", "mesh",
                                                    "sweep", "morph"}
    assert any("--chunked" in line for line in lines) == warmup._has_dask()
    assert warmup.main(["--bogus"]) == 2
