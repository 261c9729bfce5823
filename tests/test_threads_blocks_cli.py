"""By blocks at --threads 1, 2, 3, 5 and forced small odd blocks: the in-memory outputs.

Every command that runs by blocks (distance exact and banded sub-voxel, mesh, sweep
with --render, morph by exact passes and by a band, warp and warp --labels, one-shot;
a label map without 0 on the grown grid, whose empty space is its border's label)
runs once in memory at ``--threads 1`` (the reference),
then ``--chunked`` with ``--block 5`` at 1, 2, 3 and 5 threads and ``--block 7,6,9``
(neither divides the odd input sizes) at 2 threads. Every output must be the
reference's bytes; where the by-blocks path writes another order (the mesh's
canonical vertex and face order), the samples,
geometry and other key/values are compared exactly with
:func:`volwarp_cli.io.read_volume` (the mesh after canonical ordering), and every
by-blocks run must write the bytes of the others.

Each run also proves that the work was split as asked: spies on the engine's
block tasks (:func:`volwarp_cli.engine.block_task`), on the block writes of the
outputs (:meth:`volwarp_cli.io.blockwrite.BlockWriter.write`), on the mesh's
flying-edges blocks and on the ray caster's slabs check that the output was
written as the grid of the forced block size (every block once, nothing else),
that the Dask engine had ``--threads`` workers, and that its block tasks ran on
that many threads at most and, for 2 threads or more, on more than one at once.
A command that ignored ``--chunked``, ``--block`` or ``--threads``, or ran its
block tasks one at a time, fails here. A few runs on the named schedulers (the
mesh's blocks as Dask tasks, synchronous) write the same bytes too.
"""

from __future__ import annotations

import contextlib
import math
import threading
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from volwarp_cli.io import read_volume, write_volume
from volwarp_cli.volume import Volume

#: (--block, --threads) of the by-blocks runs: every count on one block shape, a
#: second shape (Z, Y, X all different, none dividing the sizes) at 2 threads
RUNS = [("5", 1), ("5", 2), ("5", 3), ("5", 5), ("7,6,9", 2)]
RUN_IDS = [f"block{b.replace(',', 'x')}-t{t}" for b, t in RUNS]

SHAPE = (23, 27, 21)  # (z, y, x) of the generated inputs: odd, divided by neither block
GEOMETRY = dict(spacing=np.array([1.0, 0.9, 1.2]), origin=np.array([-30.0, 12.0, 4.0]))

WARP = """version: 1
capture: {lattice: 6, oversample: 2}
steps:
  - move:
      - {index: [2, 3, 2], by: [3.0, -2.0, 4.0]}
      - {index: [3, 2, 3], by: [-2.0, 1.5, -3.0]}
"""

SWEEP = """version: 1
grid: {spacing: 0.6}
fields:
  opacity: {value: 0.8}
  red: 0.25
trajectory:
  - line: {from: [0, 0, 0], to: [8, 2, 5]}
  - arc: {center: [8, 5, 5], radius: 3, axis: [0.2, 0, 1], start: -90, end: 90}
up: [0, 0, 1]
scale: [3, 3]
"""


# -- inputs and running the CLI in process --------------------------------------------
def _blob(centre, radii):
    z, y, x = np.meshgrid(*[np.arange(n, dtype=np.float64) for n in SHAPE], indexing="ij")
    r = np.sqrt(((x - centre[0]) / radii[0]) ** 2 + ((y - centre[1]) / radii[1]) ** 2
                + ((z - centre[2]) / radii[2]) ** 2)
    return 1 / (1 + np.exp((r - 1) * 6)) * 200  # smooth, 100 on the ellipsoid


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    d = tmp_path_factory.mktemp("blocks_in")
    rng = np.random.default_rng(7)
    ball = _blob((10.3, 13.6, 11.2), (7.5, 7.5, 7.5)) + rng.uniform(0, 2, SHAPE)
    egg = _blob((9.1, 12.2, 12.4), (6.0, 8.5, 5.5)) + rng.uniform(0, 2, SHAPE)
    write_volume(Volume(ball.astype(np.float32), **GEOMETRY), d / "ball.nrrd")
    write_volume(Volume(egg.astype(np.float32), **GEOMETRY), d / "egg.nrrd")
    # binary shapes: the morph's exact passes (no band needed by blocks)
    write_volume(Volume((ball >= 100).astype(np.uint8), **GEOMETRY), d / "ball_mask.nrrd")
    write_volume(Volume((egg >= 100).astype(np.uint8), **GEOMETRY), d / "egg_mask.nrrd")
    labels = (ball >= 100).astype(np.uint8) + 2 * (egg >= 150).astype(np.uint8)  # 0, 1, 3
    write_volume(Volume(labels, **GEOMETRY), d / "labels.nrrd")
    # ids 2 to 4 and 1 around them (no 0): where nothing lands, 1 (the border's label)
    write_volume(Volume(labels + 1, **GEOMETRY), d / "labels_no0.nrrd")
    (d / "warp.yaml").write_text(WARP)
    (d / "sweep.yaml").write_text(SWEEP)
    return d


def invoke(*args):
    """Run the CLI in this process (so that the spies see the work); exit 0 or fail."""
    from volwarp_cli.cli.main import cli

    res = CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)
    assert res.exit_code == 0, f"volwarp {' '.join(map(str, args))}: {res.stderr}"
    return res


# -- the commands ----------------------------------------------------------------------
@dataclass(frozen=True)
class Case:
    """A command: its arguments for an output prefix, the files it writes, how to compare.

    ``volumes``: the volume outputs (written by blocks, checked block by block);
    ``note``: ``(key, suffix)``: the one key/value the by-blocks path may extend,
    by ``suffix`` (else every byte must be the in-memory file's);
    ``mesh``: a mesh output (canonical order by blocks); ``render``: a PNG
    rendered by slabs; ``grid(shape, block)``: the outputs' block grid for
    ``--block`` (z, y, x) (default: the block itself).
    """

    argv: callable
    volumes: callable
    mesh: callable = None
    render: callable = None
    note: tuple[str, str] | None = None
    grid: callable = None

    def block_grid(self, shape, block):
        return block if self.grid is None else self.grid(shape, block)

    def outputs(self, p: Path) -> list[Path]:
        out = list(self.volumes(p))
        if self.mesh:
            out.append(self.mesh(p))
        if self.render:
            out.append(self.render(p))
        return out


CASES = {
    "distance-exact": Case(
        lambda d, p: ("distance", d / "ball.nrrd", "--iso", "100", "--surface", "voxel",
                      "-o", p / "d.nrrd"),
        lambda p: [p / "d.nrrd"],
        # the z pass's blocks: whole z lines, Y x X columns (Z: the x/y passes' slabs)
        grid=lambda shape, block: (shape[0], *block[1:])),
    "distance-band-subvoxel": Case(
        lambda d, p: ("distance", d / "ball.nrrd", "--iso", "100", "--max-distance", "3.5",
                      "-o", p / "d.nrrd"),
        lambda p: [p / "d.nrrd"]),
    "distance-labels": Case(
        lambda d, p: ("distance", d / "labels.nrrd", "-o", p / "d.nrrd"),
        lambda p: [p / "d.nrrd"],
        grid=lambda shape, block: (shape[0], *block[1:])),
    "distance-labels-band": Case(
        lambda d, p: ("distance", d / "labels.nrrd", "--label", "3", "--max-distance", "3",
                      "-o", p / "d.nrrd"),
        lambda p: [p / "d.nrrd"]),
    "mesh": Case(
        lambda d, p: ("mesh", d / "ball.nrrd", "--iso", "100", "-o", p / "m.ply"),
        lambda p: [], mesh=lambda p: p / "m.ply"),
    "sweep-render": Case(
        lambda d, p: ("sweep", d / "sweep.yaml", "-o", p / "s_{field}.nrrd",
                      "--render", p / "s.png", "--render-size", "64x48"),
        lambda p: [p / "s_opacity.nrrd", p / "s_red.nrrd"], render=lambda p: p / "s.png"),
    "morph-band": Case(
        lambda d, p: ("morph", d / "ball.nrrd", d / "egg.nrrd", "--frames", "3", "--iso",
                      "100", "--max-distance", "4", "-o", p / "f_{i}.nrrd"),
        lambda p: [p / f"f_{i}.nrrd" for i in range(3)]),
    "morph-exact": Case(
        lambda d, p: ("morph", d / "ball_mask.nrrd", d / "egg_mask.nrrd", "--times",
                      "0,0.4,1", "--iso", "0.5", "-o", p / "f_{i}.nrrd"),
        lambda p: [p / f"f_{i}.nrrd" for i in range(3)]),
    "warp": Case(
        lambda d, p: ("warp", d / "ball.nrrd", "--spec", d / "warp.yaml", "-o", p / "w.nrrd"),
        lambda p: [p / "w.nrrd"]),
    "warp-labels": Case(
        lambda d, p: ("warp", d / "labels.nrrd", "--labels", "--spec", d / "warp.yaml",
                      "-o", p / "w.nrrd"),
        lambda p: [p / "w.nrrd"],
        # slabs of Z whole output planes
        grid=lambda shape, block: (block[0], *shape[1:])),
    "warp-labels-no0-grow": Case(
        lambda d, p: ("warp", d / "labels_no0.nrrd", "--spec", d / "warp.yaml", "--grid",
                      "grow", "-o", p / "w.nrrd"),
        lambda p: [p / "w.nrrd"],
        grid=lambda shape, block: (block[0], *shape[1:])),
}


@pytest.fixture(scope="module")
def references(inputs, tmp_path_factory):
    """Lazily, once per command: its in-memory outputs at --threads 1."""
    made = {}

    def get(name):
        if name not in made:
            p = tmp_path_factory.mktemp(f"ref-{name}")
            invoke(*CASES[name].argv(inputs, p), "--threads", "1")
            made[name] = CASES[name].outputs(p)
        return made[name]

    return get


@pytest.fixture(scope="module")
def first_blocks(inputs, tmp_path_factory):
    """Lazily, once per command: its outputs by blocks of 5 on one thread (no spies)."""
    made = {}

    def get(name):
        if name not in made:
            p = tmp_path_factory.mktemp(f"blk-{name}")
            invoke(*CASES[name].argv(inputs, p), "--threads", "1", "--chunked", "--block", "5")
            made[name] = CASES[name].outputs(p)
        return made[name]

    return get


# -- spies -----------------------------------------------------------------------------
@dataclass
class Spy:
    """What a by-blocks run did: block tasks, engines, block writes, mesh blocks, slabs.

    ``threads``: the run's --threads; with 2 or more, the first block task of a
    batch of several waits (a second at most) for a second one to start, so that
    the run shows whether its tasks do run side by side, whatever the machine's
    load. ``batch``: the tasks of the engine's current run (the mesh's blocks on
    this process's threads: several).
    """

    threads: int = 1
    batch: int = 2
    lock: threading.Lock = field(default_factory=threading.Lock)
    busy: int = 0
    most_at_once: int = 0
    overlap: threading.Event = field(default_factory=threading.Event)
    waited: bool = False
    inner: threading.local = field(default_factory=threading.local)
    tasks: list = field(default_factory=list)  # block task ids
    engines: list = field(default_factory=list)  # (scheduler kind, workers) per Engine.run
    writes: list = field(default_factory=list)  # (output path, its block grid, box)
    placed: list = field(default_factory=list)  # (output path, box) placed inside a block
    mesh_cells: list = field(default_factory=list)  # the flying-edges blocks' cell boxes
    slabs: list = field(default_factory=list)  # (slab depth, [(z0, z1) read])

    def enter(self):
        """A block task starts on this thread (a mesh block inside a task: the same one)."""
        depth = getattr(self.inner, "depth", 0)
        self.inner.depth = depth + 1
        if depth:
            return
        with self.lock:
            self.busy += 1
            self.most_at_once = max(self.most_at_once, self.busy)
            if self.busy >= 2:
                self.overlap.set()
            wait = (self.threads >= 2 and self.batch >= 2 and not self.overlap.is_set()
                    and not self.waited)
            self.waited = self.waited or wait
        if wait:
            self.overlap.wait(timeout=1.0)

    def leave(self):
        self.inner.depth -= 1
        if self.inner.depth:
            return
        with self.lock:
            self.busy -= 1


@contextlib.contextmanager
def spying(threads: int):
    """The spies on for the block inside (a :class:`Spy` of what it ran), off after."""
    from volwarp_cli import engine
    from volwarp_cli.io import blockwrite
    from volwarp_cli.render import raycast
    from volwarp_cli.surface import chunked as surface_chunked

    s = Spy(threads=int(threads))
    real_task = engine.block_task

    def block_task(fn, ident, *args, **kwargs):
        s.enter()
        try:
            with s.lock:
                s.tasks.append(ident)
            return real_task(fn, ident, *args, **kwargs)
        finally:
            s.leave()

    real_run = engine.Engine.run

    def run(self, tasks, **kwargs):
        tasks = list(tasks)
        s.engines.append((self.choice.kind, self.workers))
        s.batch = len(tasks)
        return real_run(self, tasks, **kwargs)

    real_write = blockwrite.BlockWriter.write

    def write(self, box, array):
        with s.lock:
            s.writes.append((self.where, tuple(self.chunks), box))
        return real_write(self, box, array)

    # a task that places its planes as it computes them (the warp into an NRRD) writes its
    # block too: every voxel of it placed once, counted as the block's write
    from volwarp_cli import execute

    real_place = blockwrite._MappedWriter._place
    real_block = execute._block_task

    def place(self, file, box, array):
        with s.lock:
            s.placed.append((self.where, box))
        return real_place(self, file, box, array)

    def block(op, box, writers, placed=False):
        result = real_block(op, box, writers, placed)
        if placed:
            with s.lock:
                for w in writers.values():
                    inside = [b for where, b in s.placed
                              if where == w.where and b.intersect(box) == b]
                    assert sum(b.size for b in inside) == box.size, (w.where, box)
                    s.writes.append((w.where, tuple(w.chunks), box))
        return result

    real_mesh_block = surface_chunked.mesh_block

    def mesh_block(raw, region, cells, plan):
        s.enter()
        try:
            with s.lock:
                s.mesh_cells.append(cells)
            return real_mesh_block(raw, region, cells, plan)
        finally:
            s.leave()

    real_slabs = raycast.render_volume_slabs

    def render_volume_slabs(read_slab, shape, *, slab=None, **kwargs):
        reads = []

        def read(z0, z1, names):
            reads.append((z0, z1))
            return read_slab(z0, z1, names)

        s.slabs.append((slab, reads))
        return real_slabs(read, shape, slab=slab, **kwargs)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(engine, "block_task", block_task)
        mp.setattr(engine.Engine, "run", run)
        mp.setattr(blockwrite.BlockWriter, "write", write)
        mp.setattr(blockwrite._MappedWriter, "_place", place)
        mp.setattr(execute, "_block_task", block)
        mp.setattr(surface_chunked, "mesh_block", mesh_block)
        mp.setattr(raycast, "render_volume_slabs", render_volume_slabs)
        yield s


def block_zyx(block: str) -> tuple[int, int, int]:
    sizes = [int(v) for v in block.split(",")]
    return tuple(sizes * 3) if len(sizes) == 1 else tuple(sizes)


def assert_tiled(boxes, shape, grid):
    """``boxes`` are the blocks of grid ``grid`` over ``shape``: each once, nothing else."""
    boxes = list(boxes)
    want = math.prod(math.ceil(n / g) for n, g in zip(shape, grid, strict=True))
    assert len(boxes) == want, f"{len(boxes)} blocks written, the grid {grid} has {want}"
    assert len(set(boxes)) == len(boxes), "a block was written twice"
    for b in boxes:
        assert all(lo % g == 0 for lo, g in zip(b.lo, grid, strict=True)), b
        assert all(h - lo == min(g, n - lo) for lo, h, g, n in zip(b.lo, b.hi, grid, shape,
                                                                      strict=True)), b
    assert sum(b.size for b in boxes) == math.prod(shape)


def assert_split(s: Spy, case: Case, out: Path, block: str, threads: int,
                 scheduler: str | None = None):
    """The run was split into the forced blocks, on an engine of ``threads`` workers."""
    zyx = block_zyx(block)
    volumes = case.volumes(out)
    blocks = 0
    for path in volumes:
        written = [(grid, box) for where, grid, box in s.writes if where == str(path)]
        assert written, f"{path.name}: not written by blocks"
        shape = read_volume(path).data.shape
        grid = case.block_grid(shape, zyx)
        assert {g for g, _ in written} == {grid}
        assert_tiled([b for _, b in written], shape, grid)
        assert len(written) >= 4
        blocks = max(blocks, len(written))
    if case.mesh:  # flying edges on blocks of cells
        nz, ny, nx = SHAPE
        assert len(s.mesh_cells) >= 8
        assert_tiled(s.mesh_cells, (nz - 1, ny - 1, nx - 1), zyx)
        blocks = max(blocks, len(s.mesh_cells))
    # the block tasks ran on a Dask engine of --threads workers (the mesh without
    # --scheduler: on this process's threads, --threads of them, no engine)
    if volumes or scheduler:
        assert s.engines and len(s.tasks) >= blocks
    assert set(s.engines) <= {(scheduler or "threads", threads)}, s.engines
    if case.render:  # the ray caster marched slabs of Z planes, none the whole depth
        assert len(s.slabs) == 1 and s.slabs[0][0] == zyx[0]
        nz = read_volume(volumes[0]).data.shape[0]
        reads = s.slabs[0][1]
        assert len(reads) > 2 and all(z1 - z0 < nz for z0, z1 in reads), (nz, reads)
        assert min(z0 for z0, _ in reads) == 0 and max(z1 for _, z1 in reads) == nz
    # never more block tasks at once than --threads; several at once when it allows
    assert 1 <= s.most_at_once <= threads
    if threads == 1 or scheduler == "synchronous":
        assert s.most_at_once == 1
    else:
        assert s.most_at_once >= 2, "the block tasks never ran side by side"


# -- comparing outputs -----------------------------------------------------------------
def assert_same_volume(ref: Path, got: Path, note: tuple[str, str]):
    """Samples, type, shape, geometry and key/values exactly; ``note``'s key may only have
    its suffix added."""
    a, b = read_volume(ref), read_volume(got)
    assert a.data.dtype == b.data.dtype and a.data.shape == b.data.shape
    assert a.data.tobytes() == b.data.tobytes(), f"{got.name}: other samples than in memory"
    assert np.array_equal(a.index_to_world_matrix, b.index_to_world_matrix)
    assert np.array_equal(a.spacing, b.spacing) and np.array_equal(a.origin, b.origin)
    assert np.array_equal(a.direction, b.direction) and a.space == b.space
    ma, mb = dict(a.meta), dict(b.meta)
    key, suffix = note
    na, nb = ma.pop(key), mb.pop(key)
    assert nb in (na, na + suffix), (key, na, nb)
    assert ma == mb


def header(path: Path) -> bytes:
    data = path.read_bytes()
    return data[:data.index(b"end_header")]


# -- the tests -------------------------------------------------------------------------
@pytest.mark.parametrize(("block", "threads"), RUNS, ids=RUN_IDS)
@pytest.mark.parametrize("name", list(CASES))
def test_by_blocks_writes_the_in_memory_outputs(inputs, references, first_blocks, tmp_path,
                                                name, block, threads):
    case = CASES[name]
    ref, first = references(name), first_blocks(name)
    with spying(threads) as spy:
        invoke(*case.argv(inputs, tmp_path), "--threads", threads, "--chunked", "--block",
               block)
    assert_split(spy, case, tmp_path, block, threads)
    got = case.outputs(tmp_path)
    # every by-blocks run writes the same bytes (whatever the threads and blocks)
    for a, b in zip(first, got, strict=True):
        assert a.read_bytes() == b.read_bytes(), f"{b.name}: other bytes than --block 5 " \
                                                 "--threads 1"
    for a, b in zip(ref, got, strict=True):
        if a.read_bytes() == b.read_bytes():
            continue
        if b.suffix == ".nrrd" and case.note is not None:
            assert_same_volume(a, b, case.note)
        else:  # (a mesh too: the in-memory PLY is the one-block case, the same bytes)
            pytest.fail(f"{name}: {b.name} by blocks is not the in-memory file")


#: other schedulers than the default: the mesh's blocks as Dask tasks (``engine.map``,
#: not this process's threads), the warp and the exact distance on one thread
SCHEDULED = [("mesh", "threads", 3, "7,6,9"), ("warp", "synchronous", 3, "5"),
             ("distance-exact", "synchronous", 2, "7,6,9")]


@pytest.mark.parametrize(("name", "scheduler", "threads", "block"), SCHEDULED,
                         ids=[f"{n}-{s}" for n, s, _, _ in SCHEDULED])
def test_named_schedulers_write_the_same_bytes(inputs, first_blocks, tmp_path, name, scheduler,
                                               threads, block):
    case = CASES[name]
    first = first_blocks(name)
    with spying(1 if scheduler == "synchronous" else threads) as spy:
        invoke(*case.argv(inputs, tmp_path), "--threads", threads, "--chunked", "--block",
               block, "--scheduler", scheduler)
    assert_split(spy, case, tmp_path, block, threads, scheduler)
    for a, b in zip(first, case.outputs(tmp_path), strict=True):
        assert a.read_bytes() == b.read_bytes(), f"{b.name}: other bytes on {scheduler}"


def test_mesh_by_blocks_keeps_the_normals(references, first_blocks):
    """`volwarp mesh` writes outward vertex normals (PLY nx, ny, nz), one a vertex; --chunked
    writes the same file, byte for byte."""
    from volwarp_cli.surface.mesh_io import read_mesh

    (mem,), (blk,) = references("mesh"), first_blocks("mesh")
    mesh = read_mesh(mem)
    assert mesh.n_faces > 1000 and mesh.normals is not None
    assert len(mesh.normals) == mesh.n_vertices
    assert header(blk) == header(mem) and blk.read_bytes() == mem.read_bytes()


def test_a_map_without_0_on_the_grown_grid_gains_no_0(references, first_blocks):
    """The no-0 case is what it says: grown, and only the map's ids (the margin: 1), in
    memory and by blocks."""
    for (path,) in (references("warp-labels-no0-grow"), first_blocks("warp-labels-no0-grow")):
        got = read_volume(path).data
        assert got.shape != SHAPE and set(np.unique(got).tolist()) == {1, 2, 3, 4}
        assert (got[0] == 1).all() or (got[-1] == 1).all()
