"""The sweep as an operation of the executor, and the render of its fields.

:class:`SweepOperation` states the sweep's outputs (one volume per field, or
one multi-component file) and computes any block of them from the block's
box alone (:func:`.chunked.block_fields`): :func:`volwarp_cli.execute.run`
runs it as one block on the calling threads when the fields fit the memory
budget, else as many blocks on an engine, with the same bytes.
:func:`render` ray-casts the fields however they ran: the in-memory render
is the one-slab case of the slab march, by blocks the slabs are read back
from the outputs (bit for bit the in-memory picture). Nothing here parses
options or names files.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..box import Box
from ..execute import Operation, Target
from ..geometry import Geometry
from ..progress import timed
from ..samples import cast_samples


@dataclass(frozen=True)
class VolumeRender:
    """How the sweep's fields are ray-cast.

    A view (a name or (azimuth, elevation)), a (width, height) in pixels, a
    camera (default: fitted to the grid) and the anatomical letters at the
    edges; ``what``: the render's name in the timings (its file).
    """

    view: object = "iso"
    size: tuple[int, int] = (512, 512)
    camera: object = None
    orientation_labels: bool = False
    what: str = "render"


def field_paths(pattern: str, names: list[str], multi: bool = False) -> dict:
    """The output file of each field from ``pattern`` (``{field}``: the field's name).

    With ``multi`` one multi-component NRRD holds every field (key ``None``):
    ``pattern`` then has no ``{field}`` and ends in ``.nrrd`` or ``.nhdr``.
    Without it, a pattern without ``{field}`` names the one field of a spec
    that has one. A :class:`~volwarp_cli.errors.BadUsage` otherwise.
    """
    from ..errors import BadUsage

    if multi:
        if "{field}" in pattern:
            raise BadUsage("with --multi all fields go into one file: drop {field}")
        low = pattern.lower()
        if not (low.endswith(".nrrd") or low.endswith(".nhdr")):
            raise BadUsage("--multi writes a multi-component NRRD: use .nrrd or .nhdr")
        return {None: pattern}
    if "{field}" not in pattern:
        if len(names) > 1:
            raise BadUsage(f"the spec has {len(names)} fields ({', '.join(names)}): put "
                           "{field} in the output name (e.g. 'out_{field}.nrrd') or use "
                           "--multi")
        return {names[0]: pattern}
    return {n: pattern.replace("{field}", n) for n in names}


def scale_to_dtype(data, dtype):
    """Float fields in [0, 1] scaled to an integer type's full range (floats unchanged)."""
    if dtype is None or np.dtype(dtype).kind == "f":
        return data
    out = data.astype(np.float64)
    out *= np.iinfo(np.dtype(dtype)).max  # (in place: one float64 copy, not two)
    return out


class SweepOperation(Operation):
    """The sweep's fields on its grid, block by block (:mod:`volwarp_cli.execute`).

    Parameters
    ----------
    spec : SweepSpec
        The parsed spec (its method and tau are the defaults).
    grid : Geometry
        The output grid.
    paths : dict
        Field name -> output path, or ``{None: path}`` for one file holding
        every field as its components (``--multi``).
    dtype
        The outputs' type (floats as they are, integers scaled from [0, 1]).
    meta : dict
        Key/values of every output (each field's adds ``volwarp_sweep_field``).
    write : dict
        :class:`~volwarp_cli.execute.Target`'s write options (``compress``,
        ``byte_order``, ``version``, ``pyramid``).
    method, tau : optional
        As :func:`.chunked.prepare_sweep`'s.

    The subdivision every block shares (:func:`.chunked.prepare_sweep`) is
    made by :meth:`prepare`, once the run is decided: an absurd grid is
    refused before it (its ``tau`` would subdivide without end).
    """

    def __init__(self, spec, grid: Geometry, paths: dict, dtype, meta: dict, write: dict, *,
                 method: str | None = None, tau: float | None = None):
        self.spec, self.method, self.tau = spec, method, tau
        self.plan = None
        self.grid = grid
        self.names = list(spec.field_names())
        self.dtype = np.dtype(dtype)
        nx, ny, nz = self.grid.shape_xyz
        self.what = f"sweep output {nx}x{ny}x{nz} x {len(self.names)} fields"
        if None in paths:  # (the key/values of the first field's, without its name)
            self.targets = {None: Target(paths[None], self.grid.header(self.dtype,
                                                                       meta=dict(meta)),
                                         self.dtype, components=tuple(self.names), **write)}
        else:
            self.targets = {n: Target(paths[n], self.grid.header(
                self.dtype, meta=dict(meta, volwarp_sweep_field=n)), self.dtype, **write)
                for n in self.names}

    def prepare(self) -> None:
        """The plan every block shares (the subdivisions), made once."""
        from ..samples import expect_reached
        from .chunked import prepare_sweep

        if self.plan is None:
            self.plan = prepare_sweep(self.spec, self.grid, method=self.method, tau=self.tau)
            expect_reached(self.what, empty_sweep_message(self.spec, self.grid))

    def memory(self, box: Box) -> int:
        """Every field as float32 and its cast, the coverage and the blend's weights.

        An integer cast passes through float64 (its scaling, rounding and check, 24 bytes
        a voxel, one field at a time, measured); ``--multi`` stacks the casts in one more
        array, the file's layout.
        """
        # (+5: a blend's divisor and the uncovered mask, :func:`.cvg.finish_fields`)
        per_voxel = len(self.names) * (4 + self.dtype.itemsize) + 1 + 4 + 5
        if self.dtype.kind != "f":
            per_voxel += 24 + self.dtype.itemsize
        if None in self.targets:
            per_voxel += len(self.names) * self.dtype.itemsize
        return int(box.size) * per_voxel

    def compute(self, box: Box, *, threads: int) -> dict:
        """``{field: float32 [z, y, x]}`` of ``box``."""
        from .chunked import block_fields

        self.prepare()
        return block_fields(self.plan, box, threads=threads)

    def output(self, results: dict, key) -> np.ndarray:
        """A field cast to the outputs' type (``--multi``: every field, on the last axis)."""
        if key is None:  # (filled a field at a time: no list of every cast beside it)
            first = results[self.names[0]]
            out = np.empty(first.shape + (len(self.names),), self.dtype)
            for k, n in enumerate(self.names):
                out[..., k] = self._cast(results[n], n)
            return out
        return self._cast(results[key], key)

    def _cast(self, data, name) -> np.ndarray:
        from ..samples import note_reached

        note_reached(self.what, lambda: bool(np.any(data)))  # (all 0: said at the end)
        return cast_samples(scale_to_dtype(data, self.dtype), self.dtype, what=str(name))

    def load(self) -> None:
        """The evaluation on a 4^3 corner, so the budget counts what the blocks load.

        (The kernels are compiled C, :mod:`._sweepkernels`: a few tens of kB, loaded with
        the module; what the corner loads besides is what the evaluation imports.)
        """
        corner = Box((0, 0, 0), tuple(min(s, 4) for s in self.grid.shape))
        self.compute(corner, threads=1)


def empty_sweep_message(spec, grid: Geometry) -> str:
    """What to say when every field of the sweep on ``grid`` came out 0 (the likely cause).

    A grid beside the sweep's bounds (a spec's ``grid`` with its own origin) is
    named with both boxes; otherwise the templates reached no voxel centre
    where they are not 0.
    """
    lo, hi = (np.asarray(v, np.float64) for v in spec.bounds())
    g_lo = np.asarray(grid.origin_array, np.float64)
    g_hi = g_lo + np.asarray(grid.spacing_array, np.float64) * (
        np.asarray(grid.shape_xyz, np.float64) - 1)
    box = "x".join(str(v) for v in grid.shape_xyz)

    def span(a, b):
        return " ".join(f"{x:.4g}..{y:.4g}" for x, y in zip(a, b, strict=True))

    if np.any(hi < g_lo) or np.any(lo > g_hi):
        return (f"every field of the sweep is 0: the output grid ({box} voxels, centres at "
                f"x y z {span(g_lo, g_hi)} mm) does not meet the sweep (its templates span "
                f"{span(lo, hi)} mm); check the spec's grid origin")
    return (f"every field of the sweep is 0 on its {box} grid: the templates reached no "
            "voxel centre where they are not 0 (thinner than a voxel? a finer --spacing)")


def render(ran, op: SweepOperation, how: VolumeRender, slab_budget: int | None = None):
    """``(image, camera)``: the ray-cast of the swept fields (``opacity`` at least).

    In memory (``ran.results``): the fields as computed, as one slab
    (:func:`~volwarp_cli.render.raycast.render_volume`). By blocks: slabs of z
    planes (:func:`~volwarp_cli.render.raycast.render_volume_slabs`, the same
    kernel) read back from the written outputs where their type holds the
    float32 fields exactly (float32, float64), else computed again for the
    slab (:func:`.chunked.block_fields`, the same samples), so the picture is
    the in-memory one bit for bit; ``slab_budget``: the bytes a slab may take
    (default: the block's depth).
    """
    from ..render.raycast import render_volume, render_volume_slabs, slab_depth
    from .chunked import block_fields

    grid, names = op.grid, op.names
    nz, ny, nx = grid.shape
    colour = all(c in names for c in ("red", "green", "blue"))
    look = dict(spacing=grid.spacing_array, origin=grid.origin_array, view=how.view,
                size=how.size, camera=how.camera, orientation_labels=how.orientation_labels,
                return_camera=True)
    if ran.results is not None:
        fields = ran.results
        with timed(f"render {how.what}"):
            return render_volume(fields["opacity"], geometry=fields.get("geometry"),
                                 colour=[fields[c] for c in ("red", "green", "blue")]
                                 if colour else None, **look)
    exact = op.dtype in (np.dtype(np.float32), np.dtype(np.float64))
    slab = (ran.block[0] if ran.block else 0) or 1
    if slab_budget is not None:
        slab = slab_depth(grid.shape, slab_budget)

    def read_slab(z0, z1, wanted):
        box = Box((z0, 0, 0), (z1, ny, nx))
        if not exact:
            fields = block_fields(op.plan, box)
            return [fields[n] for n in wanted]
        if None in op.targets:  # --multi: the fields are the components of one output
            both = ran.read(None, box)
            return [np.asarray(both[..., names.index(n)], dtype=np.float32) for n in wanted]
        return [np.asarray(ran.read(n, box), dtype=np.float32) for n in wanted]

    with timed(f"render {how.what} by slabs of {slab} z cells"):
        return render_volume_slabs(read_slab, (nz, ny, nx), colour=colour,
                                   geometry="geometry" in names, slab=slab, **look)
