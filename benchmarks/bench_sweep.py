"""Sweep and ray-cast timings, side by side with a reference in the same run.

* ``sweep``: the paper's §4.2 figure, five fields (O, R, G, B, geometry) of the
  Fig. 3 '@' Bezier sweep on a 300 x 150 x 150 grid (the paper: under two
  minutes on a 400 MHz PC). There is no peer library for image-swept
  volumes; the reference is volwarp's own direct evaluation (§5.3, the
  roots of v . a'(u) = 0 per voxel) on the same grid, which must give the
  same fields (the row reports how many voxels differ by more than 0.25).
* ``render``: a 256^3 spatial object (opacity + RGB) ray-cast at 512 x 512 by
  volwarp vs VTK's ``vtkFixedPointVolumeRayCastMapper`` (through pyvista,
  off-screen, Mesa), same view size.

Run: ``python benchmarks/bench_sweep.py [--quick]``.
"""

from __future__ import annotations

import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")


def _median(fn, repeats):
    times = []
    out = None
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times), out


def _row(name, a, b, extra=""):
    print(f"{name:44s} volwarp {a:7.3f} s  peer {b:7.3f} s  ratio {a / b:5.2f}x  {extra}")


def bench_sweep(quick: bool):
    import importlib.util

    from volwarp_cli.spec.loader import load_spec
    from volwarp_cli.sweep import evaluate
    from volwarp_cli.sweep.model import fit_grid, parse_sweep_spec

    spec_mod = importlib.util.spec_from_file_location(
        "make_templates", ROOT / "examples" / "sweep-at" / "make_templates.py")
    mt = importlib.util.module_from_spec(spec_mod)
    spec_mod.loader.exec_module(mt)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        mt.make_all(tmp / "templates", frames=1)
        text = (ROOT / "specs" / "sweep-at-bezier.yaml").read_text()
        (tmp / "s.yaml").write_text(text)
        spec = parse_sweep_spec(load_spec(tmp / "s.yaml", "sweep"))
        lo, hi = spec.bounds()
        shape = [150, 75, 75] if quick else [300, 150, 150]
        grid = fit_grid({"shape": shape}, lo, hi)
        evaluate(spec, grid)  # warm the numba cache
        nvox = int(np.prod(shape))
        tv, fv = _median(lambda: evaluate(spec, grid), 3)
        td, fd = _median(lambda: evaluate(spec, grid, method="direct"), 1)
        o1, o2 = fv["opacity"], fd["opacity"]
        agree = np.count_nonzero(np.abs(o1 - o2) > 0.25) / max(np.count_nonzero(o1), 1)
        _row(f"sweep 5 fields {shape[0]}x{shape[1]}x{shape[2]} (vs direct)", tv, td,
             f"{nvox * 5 / tv / 1e6:.0f} M field-voxels/s; {agree:.2%} voxels differ > 0.25")
    return tv


def bench_render(quick: bool):
    import pyvista as pv

    from volwarp_cli.render.raycast import render_volume

    n = 128 if quick else 256
    z, y, x = np.mgrid[:n, :n, :n].astype(np.float32)
    c = (n - 1) / 2
    r = np.sqrt((x - c) ** 2 + (y - c) ** 2 + (z - c) ** 2)
    op = np.clip(0.35 * n - r, 0, 1).astype(np.float32)
    op *= (0.5 + 0.5 * np.sin(x / 9)) ** 2
    col = [np.clip(x / n, 0, 1), np.clip(y / n, 0, 1), np.full_like(x, 0.6)]
    render_volume(op[:16, :16, :16], size=(8, 8))  # compile/load kernels
    tv, _ = _median(lambda: render_volume(op, colour=col, size=(512, 512)), 3)

    grid = pv.ImageData(dimensions=(n, n, n))
    grid.point_data["o"] = (op * 255).astype(np.uint8).transpose(2, 1, 0).ravel(order="F")

    def vtk_render():
        pl = pv.Plotter(off_screen=True, window_size=(512, 512))
        pl.add_volume(grid, scalars="o", mapper="fixed_point", opacity="linear", cmap="viridis")
        pl.camera_position = "iso"
        img = pl.screenshot(return_img=True)
        pl.close()
        return img

    vtk_render()
    tp, _ = _median(vtk_render, 3)
    _row(f"render {n}^3 at 512x512 (vs VTK fixed-point)", tv, tp)
    return tv


def main(quick: bool = False) -> None:
    bench_sweep(quick)
    bench_render(quick)


if __name__ == "__main__":
    main(quick="--quick" in sys.argv)
