"""The sweep by output blocks: any block is the whole grid's, bit for bit.

One evaluation (:func:`volwarp_cli.sweep.chunked.block_fields`): the whole grid
on volwarp's threads (:func:`~volwarp_cli.sweep.evaluate`) and any block of it in
one thread give the same samples. Odd grid sizes (37 x 41 x 29, x y z) with
block shapes that do not divide them, every method the CLI offers (voxelize,
direct), single sweeps with every segment kind and a scene of CVG operators; the
executor's blocks on a Dask threaded engine; random partitions (hypothesis);
block tasks in parallel threads (the C kernels release the GIL).
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from volwarp_cli.box import Box
from volwarp_cli.errors import VolwarpError
from volwarp_cli.geometry import Geometry
from volwarp_cli.io import write_volume
from volwarp_cli.io.images import write_image
from volwarp_cli.spec.loader import load_schema, parse_spec_text, validate
from volwarp_cli.sweep import evaluate
from volwarp_cli.sweep.chunked import field_names, prepare_sweep, sweep_block
from volwarp_cli.sweep.model import fit_grid, parse_sweep_spec
from volwarp_cli.volume import Volume

ROOT = Path(__file__).resolve().parents[1]
SHAPE_XYZ = [37, 41, 29]  # array (29, 41, 37)
CHUNKS = (10, 7, 13)  # (z, y, x): divides none of 29, 41, 37


def write_templates(d: Path) -> None:
    c = (np.arange(48) + 0.5) / 48 - 0.5
    x, y = np.meshgrid(c, c)
    write_image(d / "disc.png", (np.hypot(x, y) <= 0.5).astype(np.float32)[:, :, None])
    ramp = np.tile(np.linspace(1, 0, 40, dtype=np.float32)[:, None], (1, 40))
    ramp *= np.linspace(0.3, 1, 40, dtype=np.float32)[None, :]
    write_image(d / "ramp.png", (ramp * 65535).astype(np.uint16)[:, :, None])
    stack = np.linspace(0, 1, 5, dtype=np.float32)[:, None, None] * np.ones((5, 6, 7), np.float32)
    write_volume(Volume(stack), d / "stack.nrrd")


def make_spec(d: Path, body: dict, name: str):
    path = d / name
    path.write_text(yaml.safe_dump({"version": 1, **body}, sort_keys=False))
    doc = parse_spec_text(path.read_text(), str(path), d)
    validate(doc, load_schema("sweep"))
    return parse_sweep_spec(doc)


#: every segment kind, the default (rotation-minimising) up across joined segments,
#: scale keyframes, an image, a constant and a volume template with f(u); the sweep
#: crosses itself (sum) and blends its attributes (the kernel's weight sums)
VOXELIZE = {
    "fields": {"opacity": {"image": "disc.png"}, "red": {"image": "ramp.png"},
               "geometry": 0.7, "flame": {"frames": "stack.nrrd", "path": {"expr": "4 * u * u"}}},
    "trajectory": [
        {"bezier": {"points": [[-6, -5, -3], [8, -6, 2], [-8, 6, 3], [6, 5, -2]]}},
        {"polyline": {"points": [[6, 5, -2], [0, 7, 0], [-4, 2, 2]]}},
        {"arc": {"center": [0, 0, 0], "radius": 2, "axis": [0.2, 0.1, 1],
                 "start": 10, "end": 250}}],
    "scale": {"keyframes": [[0, [3, 2]], [1, [4, 5]]]},
    "combine": {"opacity": "sum", "default": "blend"}}

#: what the inverse mapping handles: a line with a constant direction, an arc crossing
#: its axis (two candidates), a Bezier with the binormal frame
DIRECT = {
    "method": "direct",
    "fields": {"opacity": {"image": "disc.png"}, "red": {"image": "ramp.png"}},
    "trajectory": [
        {"line": {"from": [-6, 5, 0], "to": [6, -4, 1], "direction": [1, -0.6, 0.3]}},
        {"arc": {"center": [0, 0, 0], "radius": 1.5, "axis": [0.2, 0.1, 1],
                 "start": 10, "end": 300}},
        {"bezier": {"points": [[-6, -5, -3], [8, -6, 2], [-8, 6, 3], [6, 5, -2]],
                    "up": "binormal"}}],
    "up": [0, 0, 1], "scale": [4, 5], "combine": {"opacity": "union", "default": "blend"}}


def _line(a, b, fields, up=(0, 0, 1)):
    return {"sweep": {"fields": fields, "up": list(up), "scale": [5, 4],
                      "trajectory": [{"line": {"from": a, "to": b}}]}}


#: a scene tree: (tube - tube) blended with a tube that has no 'red' (0 there)
SCENE = {"scene": {"op": {"opacity": "union", "default": "blend"}, "of": [
    {"op": "difference", "of": [
        _line([-7, 0, -1], [7, 1, 1], {"opacity": {"image": "disc.png"},
                                       "red": {"image": "ramp.png"}}),
        _line([0, -7, 0], [1, 7, 0], {"opacity": 0.6, "red": 0.25}, up=(1, 0, 1))]},
    _line([-5, -5, -4], [5, 5, 4], {"opacity": {"image": "disc.png"}}, up=(0, 1, 0))]}}

CASES = {
    "voxelize": (VOXELIZE, None),
    "direct": (DIRECT, None),
    "scene-voxelize": (SCENE, "voxelize"),
    "scene-direct": (SCENE, "direct"),
}


@pytest.fixture(scope="module")
def case_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("sweep_chunked")
    write_templates(d)
    return d


@pytest.fixture(scope="module")
def whole(case_dir):
    """Per case: (spec, grid, method, the in-memory fields stacked [F, z, y, x])."""
    out = {}
    for name, (body, method) in CASES.items():
        spec = make_spec(case_dir, {"grid": {"shape": SHAPE_XYZ}, **body}, f"{name}.yaml")
        lo, hi = spec.bounds()
        grid = fit_grid(spec.grid, lo, hi)
        fields = evaluate(spec, grid, method=method)
        assert list(fields) == field_names(spec)
        out[name] = (spec, grid, method, np.stack([fields[n] for n in field_names(spec)]))
    return out


def _by_blocks(spec, grid, method, boxes) -> np.ndarray:
    """The fields assembled from blocks each computed alone (one thread), ``[F, z, y, x]``."""
    plan = prepare_sweep(spec, grid, method=method)
    out = np.full((len(plan.names),) + grid.shape, np.nan, dtype=np.float32)
    for box in boxes:
        out[(slice(None),) + box.slices] = sweep_block(spec, grid, box, plan=plan)
    return out


@pytest.mark.parametrize("case", list(CASES))
def test_blocks_equal_the_whole_bit_for_bit(whole, case):
    spec, grid, method, ref = whole[case]
    assert grid.shape == (29, 41, 37)
    assert np.count_nonzero(ref[0]) > 1000 and np.count_nonzero(ref[0] == 0) > 1000
    got = _by_blocks(spec, grid, method, grid.box.blocks(CHUNKS))
    assert got.dtype == ref.dtype == np.float32
    assert np.array_equal(got, ref)


def test_the_executor_by_blocks_on_threads_writes_the_whole(whole, tmp_path):
    """The sweep operation by blocks on a threaded engine: the in-memory fields' bytes."""
    from volwarp_cli import execute
    from volwarp_cli.engine import open_engine
    from volwarp_cli.io import read_volume
    from volwarp_cli.sweep.run import SweepOperation

    spec, grid, method, ref = whole["scene-voxelize"]
    names = field_names(spec)
    op = SweepOperation(spec, grid, {n: tmp_path / f"{n}.nrrd" for n in names}, "float32",
                        {}, {}, method=method)
    ran = execute.run(op, execute.How(chunked=True, block=CHUNKS,
                                      open_engine=lambda: open_engine("threads", workers=2)))
    assert ran.by_blocks and ran.block == CHUNKS
    for i, n in enumerate(names):
        assert np.array_equal(read_volume(tmp_path / f"{n}.nrrd").data, ref[i])


def test_each_block_alone_and_without_a_plan(whole):
    spec, grid, method, ref = whole["voxelize"]
    plan = prepare_sweep(spec, grid, method=method)
    for box in grid.box.blocks(CHUNKS)[::7]:
        got = sweep_block(spec, grid, box, plan=plan)
        assert got.dtype == np.float32
        assert np.array_equal(got, ref[(slice(None),) + box.slices])
    box = Box((3, 10, 11), (17, 23, 30))
    assert np.array_equal(sweep_block(spec, grid, box, method=method),
                          ref[(slice(None),) + box.slices])
    with pytest.raises(VolwarpError, match="outside"):
        sweep_block(spec, grid, Box((20, 0, 0), (30, 5, 5)), plan=plan)


def test_a_grid_with_a_direction_is_refused_as_in_memory(whole):
    # the sweep samples axis-aligned grids only (its kernels place voxel (i, j, k) at
    # origin + spacing * (i, j, k)); blocks refuse what the whole refuses, the same way
    spec, grid, _, _ = whole["voxelize"]
    c, s = np.cos(0.3), np.sin(0.3)
    turned = Geometry(grid.shape, grid.spacing, grid.origin, ((c, -s, 0), (s, c, 0), (0, 0, 1)))
    for method in ("voxelize", "direct"):
        with pytest.raises(VolwarpError, match="identity direction") as whole_err:
            evaluate(spec, turned, method=method)
        with pytest.raises(VolwarpError, match="identity direction") as block_err:
            prepare_sweep(spec, turned, method=method)
        assert str(block_err.value) == str(whole_err.value)
        with pytest.raises(VolwarpError, match="identity direction"):
            sweep_block(spec, turned, Box((0, 0, 0), (2, 2, 2)), method=method)


def test_direct_refuses_a_polyline_before_any_block_runs(whole):
    spec, grid, _, _ = whole["voxelize"]  # it has a polyline segment
    with pytest.raises(VolwarpError, match="polyline"):
        prepare_sweep(spec, grid, method="direct")


# -- random chunkings --------------------------------------------------------------------
SMALL = {"grid": {"shape": [15, 12, 9], "margin": 0}, "fields": {"opacity": {"image": "disc.png"},
                                                    "red": {"image": "ramp.png"}},
         "trajectory": [{"bezier": {"points": [[-5, -4, -2], [7, -5, 2], [-7, 5, 2], [5, 4, -2]]}},
                        {"arc": {"center": [0, 0, 0], "radius": 1.5, "axis": [0, 0.3, 1],
                                 "start": 0, "end": 200}}],
         "up": [0, 0, 1], "scale": [7, 6], "combine": {"opacity": "sum", "default": "blend"}}


@pytest.fixture(scope="module")
def small(case_dir):
    spec = make_spec(case_dir, SMALL, "small.yaml")
    lo, hi = spec.bounds()
    grid = fit_grid(spec.grid, lo, hi)
    refs = {}
    for method in ("voxelize", "direct"):
        f = evaluate(spec, grid, method=method)
        refs[method] = np.stack([f[n] for n in field_names(spec)])
    assert np.count_nonzero(refs["voxelize"][0]) > 100
    return spec, grid, refs


def _partition(n):
    """Irregular chunks of an axis of n (up to 4): sorted distinct cut points."""
    return st.sets(st.integers(1, n - 1), max_size=3).map(
        lambda cuts: tuple(np.diff([0, *sorted(cuts), n]).tolist()))


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data(), method=st.sampled_from(["voxelize", "direct"]))
def test_any_chunking_equals_in_memory(small, data, method):
    spec, grid, refs = small
    chunks = tuple(data.draw(_partition(n), label=f"axis {a}") for a, n in enumerate(grid.shape))
    edges = [np.cumsum((0,) + c) for c in chunks]
    boxes = [Box((z0, y0, x0), (z1, y1, x1))
             for z0, z1 in zip(edges[0][:-1], edges[0][1:], strict=True)
             for y0, y1 in zip(edges[1][:-1], edges[1][1:], strict=True)
             for x0, x1 in zip(edges[2][:-1], edges[2][1:], strict=True)]
    got = _by_blocks(spec, grid, method, boxes)
    assert got.dtype == np.float32 and np.array_equal(got, refs[method])


# -- block tasks in parallel threads -----------------------------------------------------------
PARALLEL_SCRIPT = textwrap.dedent("""
    import sys, threading, time
    from concurrent.futures import ThreadPoolExecutor
    import numpy as np
    sys.path.insert(0, sys.argv[1])
    sys.path.insert(0, sys.argv[2])
    from test_sweep_chunked import CASES, make_spec, write_templates
    from pathlib import Path
    from volwarp_cli.sweep import chunked, evaluate
    from volwarp_cli.sweep.chunked import field_names, prepare_sweep
    from volwarp_cli.sweep.model import fit_grid

    d = Path(sys.argv[3])
    write_templates(d)
    spans = []

    for name, method in (("voxelize", None), ("direct", None)):
        body = dict(CASES[name][0])
        spec = make_spec(d, {"grid": {"shape": [60, 64, 50]}, **body}, name + ".yaml")
        grid = fit_grid(spec.grid, *spec.bounds())
        ref = evaluate(spec, grid)  # the whole grid, in the main thread and its pool
        ref = np.stack([ref[n] for n in field_names(spec)])
        plan = prepare_sweep(spec, grid)
        got = np.empty_like(ref)

        def task(box):  # a block task: when and in which thread it ran
            t0 = time.perf_counter()
            fields = chunked.block_fields(plan, box)
            spans.append((t0, time.perf_counter(), threading.get_ident()))
            for i, n in enumerate(field_names(spec)):
                got[(i,) + box.slices] = fields[n]

        spans.clear()
        with ThreadPoolExecutor(2) as pool:
            list(pool.map(task, grid.box.blocks((13, 17, 19))))
        assert np.array_equal(got, ref), name
        threads = {s[2] for s in spans}
        overlap = sum(1 for a in spans for b in spans
                      if a[2] != b[2] and a[0] < b[1] and b[0] < a[1])
        assert len(threads) == 2 and overlap > 0, (name, len(threads), overlap)
        print(name, "ok", len(spans), "tasks", overlap, "overlaps")
""")


def test_block_tasks_run_in_parallel_threads(tmp_path):
    """Block tasks in two threads of their own overlap and give the whole grid's bits (the
    kernels release the GIL; numba's ``prange`` kernels, before them, aborted under its
    workqueue layer when two threads ran them at once)."""
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    res = subprocess.run([sys.executable, "-c", PARALLEL_SCRIPT, str(ROOT),
                          str(Path(__file__).parent), str(tmp_path)],
                         env=env, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    assert "voxelize ok" in res.stdout and "direct ok" in res.stdout


def test_the_in_memory_path_does_not_import_dask(case_dir):
    code = textwrap.dedent(f"""
        import sys
        sys.path.insert(0, {str(ROOT)!r})
        sys.path.insert(0, {str(Path(__file__).parent)!r})
        from pathlib import Path
        from test_sweep_chunked import SMALL, make_spec
        from volwarp_cli.box import Box
        from volwarp_cli.sweep import evaluate
        from volwarp_cli.sweep.chunked import sweep_block
        from volwarp_cli.sweep.model import fit_grid
        spec = make_spec(Path({str(case_dir)!r}), SMALL, "nodask.yaml")
        grid = fit_grid(spec.grid, *spec.bounds())
        evaluate(spec, grid)
        sweep_block(spec, grid, Box((0, 0, 0), (3, 4, 5)))
        assert not any(m == "dask" or m.startswith("dask.") for m in sys.modules), "dask"
        print("ok")
    """)
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120)
    assert res.returncode == 0 and "ok" in res.stdout, res.stderr[-3000:]
