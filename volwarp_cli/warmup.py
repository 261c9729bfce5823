"""Compile and cache every numba kernel ahead: ``python -m volwarp_cli.warmup``.

volwarp's numba kernels (the min-norm and line-metric distance passes, the sub-voxel
distance, the renderers, the mesh statistics and decimation, the warp's export
loops, the papers' table evaluator) are compiled on their first call and cached on disk
(``cache=True``): 3-7 s per kernel, paid inside a user's first real command or
cron job on a fresh install. The warm-up pays it once, at install (``make
install``, ``make demo`` and ``make test`` run it), or in a container image's
build: it runs every command's core on tiny volumes (16^3, written to a
temporary folder) with the options that reach each kernel, on one thread and on
two (a volume cut into blocks passes views, another signature), in memory and
by blocks (``--chunked``, when Dask is installed). That compiles exactly the
signatures the commands use, and keeps doing so as the kernels change, with no
list of signatures to keep up to date. It also fills the table of volwarp's
dataclass methods, compiled once (:mod:`volwarp_cli.dataclass_code`: 14-18 ms of
every 16^3 warp's start otherwise), importing every module so that each class is in it.

The cache is the one the commands use: :func:`volwarp_cli.entry.configure_numba_cache`
chooses it for both (the package's ``__pycache__`` folders when they are
writable, else a per-user folder the install's kernels are copied into; the
user's ``NUMBA_CACHE_DIR`` always wins). A second run finds everything cached
and takes a few seconds. Exit status 0 when every command ran, 1 otherwise (the
failing command line is printed).

Options: ``-q``/``--quiet`` (errors only), ``-v``/``--verbose`` (a line and its
time for each command), ``--list`` (print the command lines and exit).
"""

from __future__ import annotations

import os
import sys
import time

#: the move every warp of the warm-up makes (voxel units: a 5^3 lattice on 16^3)
_WARP_SPEC = """\
version: 1
units: voxel
capture: {lattice: 5}
steps:
  - move:
      - {index: [2, 2, 2], by: [1.0, 0.5, -0.5]}
"""
_WARP_TABLE_SPEC = """\
version: 1
units: voxel
values: intensity
capture: {lattice: [6, 7, 6], placement: tripled, oversample: 1.5, sampling: nearest}
evaluator: table
pushforward: nearest
steps:
  - move:
      - {index: [2, 2, 2], by: [1.0, 0.5, 0.0]}
  - drag:
      - {from: [7.5, 7.5, 7.5], to: [8.5, 7.5, 7.5]}
"""
_TRANSFORM_SPEC = "version: 1\nrotate: [0, 0, 10]\ntranslate: [1.0, 0.0, 0.0]\n"
_SWEEP_SPEC = """\
version: 1
grid: {{spacing: 1.0, margin: 1.0}}
fields:
  opacity:  {{image: {t}/opacity.png, channel: 0}}
  red:      {{image: {t}/colour.png, channel: 0}}
  geometry: {{image: {t}/geometry.png, channel: 0}}
trajectory:
  - {trajectory}
up: [0, 0, 1]
scale: {{keyframes: [[0, [4, 4]], [1, [6, 6]]], interp: cubic}}
"""
_BEZIER = "bezier: {points: [[0, 0, 0], [4, 6, 0], [8, -3, 2], [12, 0, 3]]}"
_ARC = "arc: {center: [0, 0, 0], radius: 5, axis: [0, 0, 1], start: 0, end: 270}"
_LINE = "line: {from: [0, 0, 0], to: [12, 0, 0]}"
_MORPH_SPEC = """\
version: 1
source: {{volume: {src}, iso: 50}}
target: {{volume: {dst}, iso: 50}}
grid: {grid}
{extra}frames: 3
metric: {metric}
"""


def write_inputs(folder: str) -> dict:
    """Write the warm-up's tiny inputs into ``folder``; their paths by name."""
    import numpy as np

    from .io import write_volume
    from .io.images import write_image
    from .volume import Volume

    z, y, x = np.mgrid[:16, :16, :16].astype(np.float64)
    r2 = (x - 7.3) ** 2 + (y - 7.9) ** 2 + (z - 8.2) ** 2
    blob = 100.0 * np.exp(-r2 / 24.0)
    egg = 100.0 * np.exp(-(((x - 8.5) / 1.3) ** 2 + (y - 7.5) ** 2 + (z - 7.0) ** 2) / 20.0)
    labels = np.zeros((16, 16, 16), np.uint8)
    labels[3:8, 3:12, 4:12] = 1
    labels[8:13, 4:12, 3:13] = 2
    labels[5:11, 9:14, 6:10] = 3
    aniso = dict(spacing=np.array([0.9, 1.0, 1.25]))
    files = {
        "blob": Volume(blob.astype(np.float32), **aniso),
        "blob16": Volume(np.round(blob * 10 - 200).astype(np.int16)),
        "egg": Volume(egg.astype(np.float32)),
        "mask": Volume((r2 < 30).astype(np.uint8) * 200),
        # one slice (a 2-D image as a volume): its line passes see Fortran-ordered views
        "slice": Volume(np.ascontiguousarray((r2 < 30)[8:9]).astype(np.uint8) * 200),
        "labels": Volume(labels, **aniso),
    }
    paths = {}
    for name, vol in files.items():
        paths[name] = os.path.join(folder, f"{name}.nrrd")
        write_volume(vol, paths[name])
    templates = os.path.join(folder, "templates")
    os.makedirs(templates)
    v, u = np.mgrid[:24, :16].astype(np.float32)
    disc = (((u - 7.5) / 7.0) ** 2 + ((v - 11.5) / 10.0) ** 2 < 1).astype(np.float32)
    write_image(os.path.join(templates, "opacity.png"), disc[..., None])
    write_image(os.path.join(templates, "geometry.png"), disc[..., None])
    write_image(os.path.join(templates, "colour.png"),
                np.stack([disc, u / 15.0, v / 23.0], axis=-1))
    texts = {
        "move": _WARP_SPEC,
        "table": _WARP_TABLE_SPEC,
        "turn": _TRANSFORM_SPEC,
        "bezier": _SWEEP_SPEC.format(t=templates, trajectory=_BEZIER),
        "arc": _SWEEP_SPEC.format(t=templates, trajectory=_ARC),
        "line": _SWEEP_SPEC.format(t=templates, trajectory=_LINE),
        "morph": _MORPH_SPEC.format(src=paths["blob"], dst=paths["egg"], metric="euclidean",
                                    grid="union", extra=""),
        "morph_minnorm": _MORPH_SPEC.format(src=paths["mask"], dst=paths["egg"],
                                            metric="minnorm", grid="union", extra=""),
        "morph_iso": _MORPH_SPEC.format(src=paths["mask"], dst=paths["egg"], metric="euclidean",
                                        grid="source", extra="max_distance: 6\n"),
    }
    for name, text in texts.items():
        paths[name] = os.path.join(folder, f"{name}.yaml")
        with open(paths[name], "w", encoding="utf-8") as f:
            f.write(text)
    paths["affine"] = os.path.join(folder, "affine.tfm")  # as ITK writes one
    with open(paths["affine"], "w", encoding="utf-8") as f:
        f.write("#Insight Transform File V1.0\n#Transform 0\n"
                "Transform: AffineTransform_double_3_3\n"
                "Parameters: 1 0.05 0 0 1 0 0 0 1 0.5 -0.25 0\nFixedParameters: 8 8 8\n")
    # a float64 displacement field (SimpleITK and ITK write them so): the field kernels'
    # other signature
    from .io.nrrd import write_nrrd
    from .volume import LPS

    wave = [0.5 * np.sin(z / 4), 0.3 * np.cos(x / 5), 0.2 * np.sin(y / 3)]
    paths["field64"] = os.path.join(folder, "field64.nrrd")
    write_nrrd(Volume(wave[0], space=LPS, **aniso), paths["field64"], components=wave,
               component_names=["x", "y", "z"])
    paths["points"] = os.path.join(folder, "points.csv")
    with open(paths["points"], "w", encoding="utf-8") as f:
        f.write("x,y,z\n7.0,7.5,8.0\n3.0,4.0,5.0\n")
    return paths


def _has_dask() -> bool:
    from importlib.util import find_spec

    return find_spec("dask") is not None


def command_lines(p: dict, out: str, chunked: bool) -> list[list[str]]:
    """The warm-up's command lines: every kernel, with the types the commands pass it.

    ``p``: the inputs' paths (:func:`write_inputs`); ``out``: the folder outputs go to;
    ``chunked``: also by blocks on Dask.
    """
    from .cli.main import COMMANDS

    def o(name):
        return os.path.join(out, name)

    runs: list[list[str]] = [
        ["capture", p["blob"], "-o", o("blob.vwc"), "--lattice", "5"],
        ["mesh", p["blob"], "--iso", "50", "-o", o("blob.ply")],
    ]
    for threads in ("1", "2"):
        t = ["--threads", threads]
        runs += [
            # warp: from a capture file and from a volume; the exports' kernels; the
            # papers' table evaluator; a label map
            ["warp", o("blob.vwc"), "--spec", p["move"], "-o", o("w.nrrd"), *t],
            ["warp", p["blob"], "--spec", p["move"], "-o", o("w.nrrd"),
             "--displacement-to", o("disp.nrrd"), "--forward-field-to", o("fwd.nrrd"),
             "--jacobian-to", o("jac.nrrd"), "--transform-to", o("w.tfm"),
             "--points-in", p["points"], "--points-to", o("moved.csv"),
             "--mesh-in", o("blob.ply"), "--mesh-to", o("moved.ply"), *t],
            ["warp", p["blob"], "--spec", p["move"], "--jacobian-to", o("jac2.nrrd"),
             "--displacement-to", o("disp2.nrrd"), *t],
            ["warp", p["blob16"], "--spec", p["table"], "-o", o("wt.nrrd"), *t],
            # (a label map's warp is C: nothing to compile)
            # distance: exact between voxel centres, sub-voxel, labels, the line metrics,
            # the update of a moved field
            ["distance", p["mask"], "--iso", "100", "-o", o("d.nrrd"), *t],
            ["distance", p["blob"], "--iso", "50", "-o", o("sdf.nrrd"), *t],
            ["distance", p["blob16"], "--iso", "100", "--surface", "subvoxel", "--unsigned",
             "--max-distance", "5", "-o", o("d16.nrrd"), *t],
            ["distance", p["blob"], "--iso", "50", "--surface", "voxel", "-o", o("dv.nrrd"),
             *t],
            ["distance", p["labels"], "--label", "2", "-o", o("dl.nrrd"), *t],
            ["distance", p["labels"], "-o", o("dla.nrrd"), *t],
            *[["distance", p["mask"], "--iso", "100", "--metric", m, "-o", o(f"d{m}.nrrd"), *t]
              for m in ("minnorm", "chessboard", "taxicab")],
            ["distance", p["mask"], "--iso", "100", "--metric", "minnorm", "-o", o("dmn.nrrd"),
             *t],
            *[["distance", p["slice"], "--iso", "100", "--metric", m, "-o", o(f"ds{m}.nrrd"),
               *t] for m in ("euclidean", "minnorm", "chessboard", "taxicab")],
            ["distance", "--update", o("dmn.nrrd"), "--transform", p["turn"],
             "-o", o("dup.nrrd"), *t],
            # mesh: statistics, topology, decimation, normals, the surface renderer
            ["mesh", p["blob"], "--iso", "50", "-o", o(f"m{threads}.ply"), "--stats", "--cap",
             "--largest-component", "--smooth", "5", "--decimate", "0.5",
             "--render", o("m.png"), "--render-size", "64x48", "--turntable", "2", *t],
            ["mesh", p["blob"], "--iso", "50", "-o", o("m.stl"), "--json", *t],
            ["mesh", p["labels"], "--labels", "-o", o("ml_{label}.ply"), "--stats", *t],
            # sweep: its render's ray caster (the voxeliser and the direct evaluation are C)
            *[["sweep", p[k], "-o", o(k + "_{field}.nrrd"), "--spacing", "1",
               "--render", o(f"{k}.png"), "--render-size", "48x32", *t]
              for k in ("bezier", "arc", "line")],
            # morph: both fields, the frames' surfaces and renders
            ["morph", "--spec", p["morph"], "-o", o("f_{i:02d}.nrrd"),
             "--mesh-to", o("f_{i:02d}.ply"), "--render-to", o("f_{i:02d}.png"),
             "--sheet", o("sheet.png"), "--render-size", "48x48", *t],
            ["morph", "--spec", p["morph_minnorm"], "-o", o("g_{i:02d}.nrrd"), *t],
        ]
        if "apply" in COMMANDS:  # (its kernels are C: the mesh it moves takes the normals')
            runs += [
                ["apply", p["blob"], "-o", o("at.nrrd"), "-t", o("disp.nrrd"),
                 "-t", p["affine"], "--points-in", p["points"], "--points-to", o("ap.csv"),
                 "--mesh-in", o("blob.ply"), "--mesh-to", o("am.ply"), *t],
            ]
    if chunked:
        c = ["--chunked", "--block", "8", "--threads", "2"]
        runs += [
            ["warp", p["blob"], "--spec", p["move"], "-o", o("cw.nrrd"),
             "--jacobian-to", o("cjac.nrrd"), "--displacement-to", o("cdisp.nrrd"), *c],
            ["distance", p["mask"], "--iso", "100", "-o", o("cd.nrrd"), *c],
            ["distance", p["blob"], "--iso", "50", "--max-distance", "4", "-o", o("cds.nrrd"),
             *c],
            ["distance", p["mask"], "--iso", "100", "--metric", "minnorm", "-o",
             o("cdm.nrrd"), *c],
            ["distance", p["mask"], "--iso", "100", "--metric", "chessboard", "-o",
             o("cdc.nrrd"), *c],
            ["distance", p["mask"], "--iso", "100", "--metric", "taxicab", "-o",
             o("cdt.nrrd"), *c],
            ["mesh", p["blob"], "--iso", "50", "-o", o("cm.ply"), "--stats",
             "--render", o("cm.png"), "--render-size", "64x48", *c],
            ["sweep", p["bezier"], "-o", o("cs_{field}.nrrd"), "--spacing", "1",
             "--render", o("cs.png"), "--render-size", "48x32", *c],
            ["morph", "--spec", p["morph_iso"], "-o", o("cf_{i:02d}.nrrd"), *c],
        ]
    return runs


def run(*, verbosity: int = 1, list_only: bool = False) -> int:
    """Run the warm-up's commands (module notes); the exit status.

    ``verbosity``: 0 silent (errors only), 1 a line before and after, 2 a line a command.
    """
    import contextlib
    import tempfile

    from .entry import configure_numba_cache

    folder = configure_numba_cache()

    def say(message, level=1):
        if verbosity >= level:
            print(message, file=sys.stderr, flush=True)

    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="volwarp-warmup-") as tmp:
        out = os.path.join(tmp, "out")
        os.makedirs(out)
        chunked = _has_dask()
        if list_only:
            names = ("blob", "blob16", "egg", "mask", "slice", "labels", "move", "table", "turn",
                     "bezier", "arc", "line", "morph", "morph_minnorm", "morph_iso", "points",
                     "affine", "field64")
            paths = {k: os.path.join(tmp, k) for k in names}
            for line in command_lines(paths, out, chunked):
                print("volwarp " + " ".join(line))
            return 0
        from . import dataclass_code

        dataclass_code.install()  # (every class made below: its methods kept)
        from .cli.main import cli

        paths = write_inputs(tmp)
        lines = command_lines(paths, out, chunked)
        where = folder or os.environ.get("NUMBA_CACHE_DIR") or "the package's __pycache__ folders"
        say(f"volwarp warm-up: compiling the numba kernels ({len(lines)} commands on "
            f"16^3 volumes) into {where}")
        for i, line in enumerate(lines, 1):
            t0 = time.perf_counter()
            with open(os.devnull, "w") as devnull, contextlib.redirect_stdout(devnull):
                code = cli.main(line + ["-q"], standalone_mode=False)  # (--stats: stdout)
            if code != 0:
                print(f"volwarp warm-up: failed (exit {code}): volwarp {' '.join(line)}",
                      file=sys.stderr)
                return 1
            say(f"  [{i}/{len(lines)}] {time.perf_counter() - t0:5.2f} s  "
                f"volwarp {' '.join(line[:1] + [os.path.basename(a) for a in line[1:2]])}", 2)
    _import_every_module()  # (the classes of paths no command above took: a label warp's)
    _mark()
    dataclass_code.save(force=True)  # (as compileall writes bytecode, whatever the environment says)
    say(f"volwarp warm-up: done in {time.perf_counter() - start:.1f} s")
    return 0


def _import_every_module() -> None:
    """Import every module of the package, so that each of its dataclasses is made once here.

    Their methods then go into :mod:`volwarp_cli.dataclass_code`'s table with
    those of the commands run: a class only a path the warm-up does not take
    makes (a label map's warp) would otherwise be compiled in every run where
    bytecode is not written (``PYTHONDONTWRITEBYTECODE``). A module whose
    optional dependency is not installed is skipped.
    """
    import importlib
    import pkgutil

    from . import __path__ as package_path

    for module in pkgutil.walk_packages(package_path, f"{__package__}."):
        try:
            importlib.import_module(module.name)
        except ImportError:
            continue


def _mark() -> None:
    """Record this warm-up in the package's ``__pycache__`` (where it could write there).

    A read-only install's per-user caches copy the kernels compiled here once per
    mark (:func:`volwarp_cli.entry.seed_cache`).
    """
    from .entry import WARMUP_MARK, package_dir

    if os.environ.get("NUMBA_CACHE_DIR"):
        return  # the kernels went to the user's folder, not beside the sources
    folder = os.path.join(package_dir(), "__pycache__")
    try:
        os.makedirs(folder, exist_ok=True)
        tmp = os.path.join(folder, f".{WARMUP_MARK}.{os.getpid()}")
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(f"{time.time_ns()} {os.getpid()}\n")
        os.replace(tmp, os.path.join(folder, WARMUP_MARK))
    except OSError:
        pass


def main(argv: list[str] | None = None) -> int:
    """``python -m volwarp_cli.warmup [-q|-v] [--list]``."""
    argv = sys.argv[1:] if argv is None else argv
    unknown = [a for a in argv if a not in ("-q", "--quiet", "-v", "--verbose", "--list")]
    if unknown:
        print(f"usage: python -m volwarp_cli.warmup [-q|--quiet] [-v|--verbose] [--list]\n"
              f"volwarp warm-up: error: unknown argument {unknown[0]!r}", file=sys.stderr)
        return 2
    for name in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):  # as the command line sets them
        os.environ.setdefault(name, "1")
    quiet = "-q" in argv or "--quiet" in argv
    verbose = "-v" in argv or "--verbose" in argv
    return run(verbosity=0 if quiet else 2 if verbose else 1, list_only="--list" in argv)


if __name__ == "__main__":
    raise SystemExit(main())
