"""Benchmark `volwarp warp` against VTK and SimpleITK B-spline resampling (same run).

    python benchmarks/bench_warp.py [--quick]

Rows: ``name  volwarp X s  peer Y s  ratio R``. Also prints the figures issue 3
asks for: the in-process warp core in memory passes, capture and warp-step
times at oversample 2 on 128^3, the incremental/full ratio on a 13^3 lattice,
peak memory of the 128^3 case, and the papers' own size (30^3, 9^3 lattice).
"""

from __future__ import annotations

import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))
os.environ.setdefault("NUMBA_CACHE_DIR", str(ROOT / ".numba-cache"))

import common  # noqa: E402
from common import row  # noqa: E402


def peak_rss_mib() -> float:
    """This process's peak resident memory (VmHWM; unlike ru_maxrss, not inherited over exec)."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def median_time(fn, repeats):
    """Median of ``repeats`` runs, no warm-up run (callers warm up what needs it)."""
    return common.median_time(fn, repeats, warmup=0)


def step_kind(scene) -> str:
    """How the scene did its last step: a local update, or a full pass where that was cheaper."""
    whole = scene.last_touched == scene.target_box
    return "full recomputation, cheaper than an update" if whole else "local update"


def volume(n):
    rng = np.random.default_rng(0)
    z, y, x = np.mgrid[:n, :n, :n].astype(np.float32) / n - 0.5
    data = 100 * np.exp(-(x * x + y * y + z * z) / 0.05) + rng.random((n, n, n), dtype=np.float32)
    return data.astype(np.float32)


def volwarp_bin():
    exe = Path(sys.executable).with_name("volwarp")
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "volwarp_cli"]


def vtk_resample(data, disp_index, shift):
    """vtkImageReslice through a 9^3 vtkBSplineTransform with one coefficient moved."""
    coeff = np.zeros((9, 9, 9, 3))
    i, j, k = disp_index
    coeff[k, j, i] = -np.asarray(shift)  # reslice pulls back: inverse displacement
    return vtk_bspline_resample(data, coeff)


def vtk_bspline_resample(data, coeff):
    """vtkImageReslice of ``data`` (n^3) through the uniform cubic B-spline whose
    coefficients (voxels, ``[k, j, i, 3]``, a c^3 grid spanning the volume) are ``coeff``."""
    import vtk
    from vtk.util import numpy_support as ns

    n = data.shape[0]
    img = vtk.vtkImageData()
    img.SetDimensions(n, n, n)
    img.GetPointData().SetScalars(ns.numpy_to_vtk(data.ravel(), deep=False))
    c = coeff.shape[0]
    h = n / (c - 3.0)
    cimg = vtk.vtkImageData()
    cimg.SetDimensions(c, c, c)
    cimg.SetSpacing(h, h, h)
    cimg.SetOrigin(-0.5 - h, -0.5 - h, -0.5 - h)
    arr = ns.numpy_to_vtk(np.asarray(coeff, np.float32).reshape(-1, 3), deep=True)
    cimg.GetPointData().SetScalars(arr)
    tr = vtk.vtkBSplineTransform()
    tr.SetCoefficientData(cimg)
    tr.SetBorderModeToZero()
    rs = vtk.vtkImageReslice()
    rs.SetInputData(img)
    rs.SetResliceTransform(tr)
    rs.SetInterpolationModeToLinear()
    rs.SetOutputExtent(0, n - 1, 0, n - 1, 0, n - 1)

    def go():
        rs.Modified()
        rs.Update()
        return rs.GetOutput()

    go.filter = rs  # (its thread count, for bench_threads)
    return go


def sitk_resample(data, disp_index, shift):
    import SimpleITK as sitk

    img = sitk.GetImageFromArray(data)
    tx = sitk.BSplineTransformInitializer(img, [6, 6, 6], 3)
    params = np.zeros(len(tx.GetParameters()))
    c = 9
    i, j, k = disp_index
    flat = (k * c + j) * c + i
    for d in range(3):
        params[d * c ** 3 + flat] = -shift[d]
    tx.SetParameters(params.tolist())

    def go():
        return sitk.Resample(img, img, tx, sitk.sitkLinear, 0.0)

    return go


def core_figures(quick):
    from volwarp_cli.bspline.capture import capture_volume
    from volwarp_cli.bspline.scene import Scene
    from volwarp_cli.volume import Volume

    n = 256
    data = volume(n)
    a = np.empty_like(data)
    b = data.copy()
    unit = median_time(lambda: (np.multiply(b, data, out=a), np.add(a, b, out=a)), 5)
    cap = capture_volume(Volume(data), lattice=(9, 9, 9), oversample=1)
    dq = cap.dq.copy()
    dq[4, 4, 4] += [3.0, 2.0, 1.0]
    scene = Scene(cap.domain, cap.grid, dq, 4)
    scene.compute()
    t = median_time(scene.compute, 2 if quick else 3)
    deferred = capture_volume(Volume(data), lattice=(9, 9, 9), oversample=1, defer=True)
    streamed = Scene(deferred.voxmap, deferred.grid, dq, 4, domain_range=deferred.stats[:2])
    common.one_shot(streamed)
    t_once = median_time(lambda: common.one_shot(streamed), 2 if quick else 3)
    print(f"one memory pass (a = b*c + d, 256^3 float32): {unit * 1e3:.1f} ms")
    print(f"warp core 256^3 (deformation + box pushforward, 9^3, oversample 1): {t:.3f} s "
          f"= {t / unit:.0f} passes keeping the accumulators (for local updates), "
          f"{t_once:.3f} s = {t_once / unit:.0f} passes streamed (the one-shot command's)")
    return unit


def oversample2_figures():
    from volwarp_cli.bspline.capture import capture_volume
    from volwarp_cli.bspline.scene import Scene
    from volwarp_cli.volume import Volume

    warm = capture_volume(Volume(np.ones((8, 8, 8), np.float32)), lattice=5)
    Scene(warm.domain, warm.grid, warm.dq, 1).compute()  # load numba's cached kernels
    data = volume(128)
    t0 = time.perf_counter()
    cap = capture_volume(Volume(data))  # 9^3, oversample 2 -> 258^3 domain
    tcap = time.perf_counter() - t0
    scene = Scene(cap.domain, cap.grid, cap.dq, 4)
    scene.compute()  # the captured state (no point moved)
    dq = cap.dq.copy()
    dq[4, 4, 4] += [2.0, 1.0, -1.0]
    t0 = time.perf_counter()
    scene.set_lattice(dq)
    tstep = time.perf_counter() - t0
    peak = peak_rss_mib()
    moved = Scene(cap.domain, cap.grid, dq, 4)
    t0 = time.perf_counter()
    moved.compute()
    tfull = time.perf_counter() - t0
    print(f"128^3 oversample 2 (domain {cap.grid.domain_shape}): capture {tcap:.3f} s, "
          f"full warp {tfull:.3f} s, one-point warp step {tstep:.3f} s ({step_kind(scene)}), "
          f"peak RSS {peak:.0f} MiB (input 8 MiB, domain {cap.domain.nbytes >> 20} MiB, "
          f"accumulators {scene.acc.nbytes >> 20} MiB, output {scene.out.nbytes >> 20} MiB)",
          flush=True)


def incremental_figures():
    """One moved control point on a 13^3 lattice (128^3 at oversample 2): update vs full.

    Two starting lattices: the capture's own (every region still but the
    moved point's 64, so the full pass takes the still shortcut for 94% of the
    domain) and a deformed one (every control point first moved by a random
    0.3 voxel, as after earlier steps: every voxel costs the same). The full
    warp is a warm recomputation of the same lattice by the same scene.
    """
    from volwarp_cli.bspline.capture import capture_volume
    from volwarp_cli.bspline.scene import Scene
    from volwarp_cli.volume import Volume

    data = volume(128)
    cap = capture_volume(Volume(data), lattice=(13, 13, 13), oversample=2)
    frac = 4 ** 3 / 10 ** 3
    rng = np.random.default_rng(0)
    deformed = cap.dq + rng.normal(scale=0.3, size=cap.dq.shape)
    for name, start in (("from the capture", cap.dq), ("deformed lattice", deformed)):
        scene = Scene(cap.domain, cap.grid, start, 4)
        scene.compute()
        scene.compute()  # warm
        dq = start.copy()
        steps, fulls, kinds = [], [], set()
        # pairs: an update, then a full recomputation of the same lattice (which
        # leaves the same accumulators): this machine's speed drifts, pairs share it
        for i in range(15):
            dq = dq.copy()
            dq[6, 6, 6] += [0.5, 0.3, -0.2] if i % 2 == 0 else [-0.4, -0.2, 0.3]
            t0 = time.perf_counter()
            scene.set_lattice(dq)
            t1 = time.perf_counter()
            kinds.add(step_kind(scene))
            scene.compute()
            t2 = time.perf_counter()
            steps.append(t1 - t0)
            fulls.append(t2 - t1)
        ratios = sorted(a / b for a, b in zip(steps, fulls, strict=True))
        print(f"13^3 lattice, 128^3 oversample 2, {name}: full {statistics.median(fulls):.3f} s, "
              f"{' / '.join(sorted(kinds))} {statistics.median(steps):.3f} s; ratio "
              f"{statistics.median(ratios):.3f} (pairs {ratios[0]:.3f}-{ratios[-1]:.3f}) vs "
              f"affected/all regions {frac:.3f} (target <= {2 * frac:.3f})", flush=True)


def papers_size():
    from volwarp_cli.bspline.capture import capture_volume
    from volwarp_cli.bspline.scene import Scene
    from volwarp_cli.volume import Volume

    z, y, x = np.mgrid[:30, :30, :30]
    data = (255 * ((x - 14.5) ** 2 + (y - 14.5) ** 2 + (z - 14.5) ** 2 <= 100)).astype(np.uint8)
    cap = capture_volume(Volume(data), lattice=(9, 9, 9), oversample=2)
    scene = Scene(cap.domain, cap.grid, cap.dq, 4)
    scene.compute()
    dq = cap.dq.copy()
    times = []
    for s in range(5):
        dq = dq.copy()
        dq[4 + s % 2, 4, 4] += [0.5, -0.5, 0.25]
        t0 = time.perf_counter()
        scene.set_lattice(dq)
        times.append(time.perf_counter() - t0)
    tfull = median_time(scene.compute, 3)
    print(f"papers' size (30^3 model, 60^3 domain, 9^3 lattice): warp step "
          f"{statistics.median(times) * 1e3:.1f} ms ({step_kind(scene)}), "
          f"{tfull * 1e3:.1f} ms full "
          "(papers: 1 s HP 9000/730, 6 s RISC6000)")


def main(quick: bool = False):
    from volwarp_cli.io import write_volume
    from volwarp_cli.volume import Volume

    n = 256
    data = volume(n)
    shift = (3.0, 2.0, 1.0)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        src = tmp / "in.nrrd"
        write_volume(Volume(data), src)
        spec = tmp / "w.yaml"
        spec.write_text("version: 1\ncapture: {lattice: 9, oversample: 1}\npushforward: box\n"
                        f"steps:\n  - move:\n      - {{index: [4, 4, 4], by: {list(shift)}}}\n")
        cmd = volwarp_bin() + ["warp", str(src), "--spec", str(spec), "-o", str(tmp / "o.nrrd")]
        subprocess.run(cmd, check=True)  # warm the page cache
        vtk_go = vtk_resample(data, (4, 4, 4), shift)
        vtk_go()  # VTK's first resample sets up its threads
        ours, vtk_t, r = common.paired_times(lambda: subprocess.run(cmd, check=True), vtk_go,
                                             3 if quick else 7)
        row("warp command 256^3 vs vtkImageReslice+BSpline", ours, vtk_t, "vtk", r)
        sitk_go = sitk_resample(data, (4, 4, 4), shift)
        ours, sitk_t, r = common.paired_times(lambda: subprocess.run(cmd, check=True), sitk_go,
                                              1 if quick else 5)
        row("warp command 256^3 vs SimpleITK Resample", ours, sitk_t, "sitk", r)
    core_figures(quick)
    # in a fresh process, so that its peak memory is its own
    subprocess.run([sys.executable, str(Path(__file__).resolve()), "--os2-child"], check=True)
    incremental_figures()
    papers_size()


if __name__ == "__main__":
    if "--os2-child" in sys.argv:
        oversample2_figures()
    else:
        main(quick="--quick" in sys.argv)
