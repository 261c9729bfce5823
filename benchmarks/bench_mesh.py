"""Isosurface and render timings: volwarp against scikit-image and VTK, in the same run.

Rows:
- isosurface of a 256^3 smooth sphere and of a 256^3 gyroid (~5M triangles):
  ``volwarp_cli.surface.isosurface`` (VTK flying edges, world coordinates,
  outward winding, normals) against ``skimage.measure.marching_cubes``;
- the whole ``volwarp mesh`` command on the gyroid writing binary PLY (a
  fresh process: imports, reading the NRRD, isosurface, normals, writing)
  against skimage's bare computation, against scikit-image's whole job as a
  process (read the NRRD with SimpleITK, marching cubes with its normals, write
  the same binary PLY layout), alternated, and the same by blocks
  (``--chunked``: the same bytes, checked) against it in memory;
- rendering a ~1M-triangle mesh at 1024x768: volwarp's rasteriser, and the
  whole ``volwarp mesh --render`` command, against pyvista/VTK off-screen
  through Mesa EGL (plotter set-up, first render and screenshot).

Run: ``python benchmarks/bench_mesh.py [--quick]``.
"""

from __future__ import annotations

import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
sys.path.insert(0, str(Path(__file__).parent))
from common import median_time, paired_times, row  # noqa: E402


def sphere_field(n: int) -> np.ndarray:
    c = (n - 1) / 2
    z, y, x = np.ogrid[:n, :n, :n]
    return (n * 0.4 - np.sqrt((x - c) ** 2 + (y - c) ** 2 + (z - c) ** 2)).astype(np.float32)


def gyroid_field(n: int, period: float = 32.0) -> np.ndarray:
    s = 2 * np.pi / period
    z, y, x = np.ogrid[:n, :n, :n]
    x, y, z = (a.astype(np.float32) * np.float32(s) for a in (x, y, z))
    return (np.sin(x) * np.cos(y) + np.sin(y) * np.cos(z) + np.sin(z) * np.cos(x)).astype(
        np.float32)


def _volwarp_cmd() -> list[str]:
    exe = Path(sys.executable).with_name("volwarp")
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "volwarp_cli"]


def _run_cmd(args: list[str]) -> None:
    env = dict(os.environ)
    env.setdefault("NUMBA_CACHE_DIR", str(ROOT / ".numba-cache"))
    res = subprocess.run(_volwarp_cmd() + ["mesh"] + args, capture_output=True, text=True, env=env)
    if res.returncode != 0:
        raise RuntimeError(f"volwarp {' '.join(args)} failed: {res.stderr.strip()}")


#: scikit-image's whole job as a process: read, marching cubes (with normals), binary PLY
SKIMAGE_JOB = """
import sys, numpy as np, SimpleITK as sitk
from skimage.measure import marching_cubes
a = sitk.GetArrayFromImage(sitk.ReadImage(sys.argv[1]))
v, f, n, _ = marching_cubes(a, 0.0)
v, n = v[:, ::-1].astype(np.float32), n[:, ::-1].astype(np.float32)
head = ("ply\\nformat binary_little_endian 1.0\\nelement vertex %d\\nproperty float x\\n"
        "property float y\\nproperty float z\\nproperty float nx\\nproperty float ny\\n"
        "property float nz\\nelement face %d\\nproperty list uchar int vertex_indices\\n"
        "end_header\\n" % (len(v), len(f)))
faces = np.empty(len(f), dtype=[("n", "u1"), ("i", "<i4", 3)])
faces["n"], faces["i"] = 3, f
with open(sys.argv[2], "wb") as fh:
    fh.write(head.encode())
    fh.write(np.hstack([v, n]).astype("<f4").tobytes())
    fh.write(faces.tobytes())
"""


def main(quick: bool = False) -> None:
    from skimage.measure import marching_cubes

    from volwarp_cli.io import write_volume
    from volwarp_cli.render.surface import render_mesh
    from volwarp_cli.surface.isosurface import isosurface
    from volwarp_cli.volume import Volume

    n = 128 if quick else 256
    repeats = 3 if quick else 5
    print(f"# mesh benchmarks ({'quick' if quick else 'full'}: {n}^3, median of {repeats})")
    # warm up: VTK import and numba kernels are loaded once per process
    isosurface(Volume(sphere_field(16)), 0.0)
    render_mesh(isosurface(Volume(sphere_field(16)), 0.0), size=(32, 24))

    fields = {"sphere": sphere_field(n), "gyroid": gyroid_field(n)}
    skimage_times = {}
    for name, f in fields.items():
        vol = Volume(f)
        mesh = isosurface(vol, 0.0)
        ours = median_time(lambda vol=vol: isosurface(vol, 0.0), repeat=repeats, warmup=0)
        verts, faces, _, _ = marching_cubes(f, 0.0)
        peer = median_time(lambda f=f: marching_cubes(f, 0.0), repeat=repeats, warmup=0)
        skimage_times[name] = peer
        row(f"isosurface {name} {n}^3 ({mesh.n_faces / 1e6:.2f}M tri)", ours, peer,
             "skimage")
        assert abs(len(faces) - mesh.n_faces) < 0.01 * len(faces)

    with tempfile.TemporaryDirectory(prefix="volwarp-bench-") as tmp:
        tmp = Path(tmp)
        gpath = tmp / "gyroid.nrrd"
        write_volume(Volume(fields["gyroid"]), gpath)
        out = tmp / "gyroid.ply"
        cmd = [str(gpath), "-o", str(out), "--iso", "0", "-q"]
        _run_cmd(cmd)  # warm the file cache
        whole = median_time(lambda: _run_cmd(cmd), repeat=max(2, repeats - 2), warmup=0)
        size_mb = out.stat().st_size / 1e6
        row(f"volwarp mesh gyroid -> PLY ({size_mb:.0f} MB)", whole,
             skimage_times["gyroid"], "skimage (bare)")
        peer_argv = [sys.executable, "-c", SKIMAGE_JOB, str(gpath), str(tmp / "sk.ply")]
        job, peer_job, ratio = paired_times(lambda: _run_cmd(cmd),
                                            lambda: subprocess.run(peer_argv, check=True),
                                            repeats)
        row("volwarp mesh gyroid -> PLY", job, peer_job, "skimage's whole job (process)",
            ratio)
        # by blocks: the same file, byte for byte (slabs on the engine, welded)
        blocked = tmp / "gyroid-blocks.ply"
        cmd = [str(gpath), "-o", str(blocked), "--iso", "0", "-q", "--chunked"]
        _run_cmd(cmd)
        if blocked.read_bytes() != out.read_bytes():
            raise RuntimeError("volwarp mesh --chunked wrote other bytes than in memory")
        by_blocks = median_time(lambda: _run_cmd(cmd), repeat=max(2, repeats - 2), warmup=0)
        row("volwarp mesh gyroid -> PLY by blocks", by_blocks, whole, "in memory")

        # ~1M triangles: a 150^3 gyroid (64^3 in quick mode)
        m = 80 if quick else 150
        rpath = tmp / "gyroid_small.nrrd"
        rvol = Volume(gyroid_field(m))
        write_volume(rvol, rpath)
        mesh = isosurface(rvol, 0.0)
        tri = f"{mesh.n_faces / 1e6:.2f}M tri"
        size = (1024, 768)
        ours = median_time(lambda: render_mesh(mesh, size=size), repeat=repeats, warmup=0)
        peer_cold, peer_warm = _pyvista_render(mesh, size)
        row(f"render {tri} 1024x768 (core)", ours, peer_warm, "pyvista EGL")
        png = tmp / "r.png"
        cmd = [str(rpath), "--iso", "0", "--render", str(png), "--render-size", "1024x768", "-q"]
        _run_cmd(cmd)
        whole = median_time(lambda: _run_cmd(cmd), repeat=max(2, repeats - 2), warmup=0)
        row(f"volwarp mesh --render {tri} (whole)", whole, peer_cold,
             "pyvista 1st render")


def _pyvista_render(mesh, size) -> tuple[float, float]:
    """(set-up + first render + screenshot, a later render + screenshot) with pyvista EGL."""
    import pyvista as pv

    faces = np.hstack([np.full((mesh.n_faces, 1), 3, dtype=np.int64), mesh.faces]).ravel()
    poly = pv.PolyData(mesh.vertices, faces)
    poly.point_data["Normals"] = mesh.normals
    t = time.perf_counter()
    plotter = pv.Plotter(off_screen=True, window_size=list(size))
    plotter.add_mesh(poly, color="tan", smooth_shading=True)
    plotter.view_isometric()
    plotter.screenshot(return_img=True)
    cold = time.perf_counter() - t
    times = []
    for k in range(2):
        t = time.perf_counter()
        plotter.camera.azimuth = 10.0 * (k + 1)
        plotter.render()
        plotter.screenshot(return_img=True)
        times.append(time.perf_counter() - t)
    plotter.close()
    return cold, statistics.median(times)


if __name__ == "__main__":
    main(quick="--quick" in sys.argv[1:])
