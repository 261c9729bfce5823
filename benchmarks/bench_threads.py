"""Each subcommand at one thread and at every core, and the general deformation against
VTK and SimpleITK at every core (same run).

    python benchmarks/bench_threads.py [--quick]

Rows: ``name  1 thread X s  N threads Y s  speedup``: whole commands (a new process
each run, start-up, reading and writing included), paired runs (1, N, 1, N, ...).
The first line says how many cores this process may use: figures from a bigger
machine read right. The outputs of both counts are compared byte for byte.

Then, for the two warp rows, the part no thread count changes (the same command
on a 16^3 volume: start-up, imports, the spec, the output's file) and the
speedup that bounds (Amdahl: every other part scaled perfectly); and the general
warp against the peers three ways: the whole command against their bare
in-process resample, the whole command against their whole job as a process
(``peer_bspline_script.py``: read the NRRD, resample, write), and volwarp's core
in process against their bare resample.
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

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))
os.environ.setdefault("NUMBA_CACHE_DIR", str(ROOT / ".numba-cache"))

import common  # noqa: E402
from bench_warp import volume, volwarp_bin, vtk_bspline_resample  # noqa: E402


def paired(argv_a, argv_b, pairs, run=None):
    """Medians of two commands run in turn, and the median of the pairwise ratios a / b.

    With a the one-thread run and b the all-threads run, a / b is the speedup.
    ``run``: two callables to time instead of the commands.
    """
    if run is None:
        run = tuple(lambda argv=argv: subprocess.run(argv, check=True, stdout=subprocess.DEVNULL)
                    for argv in (argv_a, argv_b))
    a, b = [], []
    for _ in range(pairs):
        for go, times in zip(run, (a, b), strict=True):
            start = time.perf_counter()
            go()
            times.append(time.perf_counter() - start)
    return (statistics.median(a), statistics.median(b),
            statistics.median(x / y for x, y in zip(a, b, strict=True)))


def scaling_row(name, argv, outputs, cores, pairs):
    """Time ``argv`` (a list with ``{t}`` in output names) at 1 and ``cores`` threads."""
    one = [a.replace("{t}", "1") for a in argv] + ["--threads", "1"]
    all_ = [a.replace("{t}", "n") for a in argv] + ["--threads", str(cores)]
    subprocess.run(one, check=True, stdout=subprocess.DEVNULL)  # warm caches
    t1, tn, r = paired(one, all_, pairs)
    same = all(Path(o.replace("{t}", "1")).read_bytes() == Path(o.replace("{t}", "n")).read_bytes()
               for o in outputs)
    print(f"  {name:<44} 1 thread {t1:7.3f} s   {cores} threads {tn:7.3f} s   "
          f"speedup {r:5.2f}x   {'identical' if same else 'OUTPUTS DIFFER'}", flush=True)
    return t1, tn


def amdahl_row(name, fixed, t1, tn, cores):
    """The speedup a command can reach at ``cores`` threads, given what no thread changes.

    ``fixed``: the same command on a 16^3 volume (start-up, imports, the spec, the
    output's file): were everything else to scale perfectly, the speedup would be
    t1 / (fixed + (t1 - fixed) / cores).
    """
    bound = t1 / (fixed + max(t1 - fixed, 0.0) / cores)
    rest1, restn = t1 - fixed, tn - fixed
    scaled = f"{rest1 / restn:5.2f}x" if restn > 0 else "  n/a"
    print(f"  {name:<44} fixed part (16^3) {fixed:6.3f} s of {t1:6.3f} s: at most "
          f"{bound:4.2f}x at {cores} threads; the rest scaled {scaled}", flush=True)


def predicted_rows(name, scene, t1=None, fixed=None, counts=(2, 4, 16, 64)):
    """What the one-shot warp's cut predicts at more cores than this machine has.

    For each thread count: the parts :func:`volwarp_cli.warp.blocks.least_time_cut`
    makes of the whole output (what a command with that many threads runs),
    the domain voxels they scatter over the whole's (their halos), and the
    speedup of the scatter work that cut allows (the whole's work over its
    longest thread's, dealt largest first): a bound, reached only where memory
    bandwidth grows with the cores. With ``t1`` (the command at one thread)
    and ``fixed`` (its part no thread count changes): the whole command's.
    """
    from volwarp_cli.warp.blocks import _makespan, block_work, domain_box, least_time_cut

    whole = scene._work([scene.dq], domain_box(scene, scene.target_box))
    for n in counts:
        parts = least_time_cut(scene, scene.target_box, n)
        work = [scene._work([scene.dq], domain_box(scene, p)) for p in parts]
        bound = whole / _makespan(work, n)
        line = (f"  {name:<44} {n:>2} threads: {len(parts):>3} parts scatter "
                f"{block_work(scene, parts):4.2f}x the voxels; scatter speedup at most "
                f"{bound:5.2f}x")
        if t1 is not None and fixed is not None:
            line += f", the command's {t1 / (fixed + max(t1 - fixed, 0.0) / bound):5.2f}x"
        print(line, flush=True)


def general_coefficients(c, amplitude, seed=1):
    """Offsets (voxels) of every control point of a c^3 lattice, as a registration gives."""
    rng = np.random.default_rng(seed)
    return rng.normal(scale=amplitude, size=(c, c, c, 3))


def general_spec(path, dq):
    lines = ["version: 1", f"capture: {{lattice: {dq.shape[0]}, oversample: 1}}",
             "pushforward: box", "steps:", "  - move:"]
    c = dq.shape[0]
    for k in range(c):
        for j in range(c):
            for i in range(c):
                by = [round(float(v), 4) for v in dq[k, j, i]]
                lines.append(f"      - {{index: [{i}, {j}, {k}], by: {by}}}")
    path.write_text("\n".join(lines) + "\n")


def vtk_general(data, dq):
    """VTK's reslice through the same lattice (about the inverse: its coefficients pull back)."""
    return vtk_bspline_resample(data, -dq)


def sitk_general(data, dq):
    import SimpleITK as sitk

    img = sitk.GetImageFromArray(data)
    c = dq.shape[0]
    tx = sitk.BSplineTransformInitializer(img, [c - 3] * 3, 3)
    params = np.concatenate([-dq[..., d].ravel() for d in range(3)])  # (z, y, x) flat, per axis
    tx.SetParameters(params.tolist())

    def go():
        return sitk.Resample(img, img, tx, sitk.sitkLinear, 0.0)

    return go


def threads_speedup(run_at, cores, pairs):
    """Medians at one thread and at ``cores`` (``run_at(n)`` runs the work on n), paired."""
    run_at(1)
    run_at(cores)
    return paired(None, None, pairs, run=(lambda: run_at(1), lambda: run_at(cores)))


def copy_in_threads(n_bytes=256 << 20):
    """A memory-bound reference: a plain copy of ``n_bytes`` cut in as many parts as threads.

    What this machine's memory gives a second thread when there is nothing
    but loads and stores (numpy's copy releases the GIL).
    """
    from volwarp_cli import parallel

    src = np.ones(n_bytes // 4, np.float32)
    dst = np.empty_like(src)

    def run_at(n):
        edges = parallel.cuts(0, src.size, n)
        parallel.run_blocks(lambda i: np.copyto(dst[edges[i]:edges[i + 1]],
                                                src[edges[i]:edges[i + 1]]),
                            range(len(edges) - 1), n)

    return run_at


def peer_scaling_rows(vol, spec, one, data, dq, cores, pairs):
    """Each resample, in process, at one thread and at ``cores``: whose work scales here.

    volwarp's warp (``api.warp`` of the volume held; through ``spec``, every point
    moved, and ``one``, one point), vtkImageReslice and SimpleITK's Resample
    through the same lattice as ``spec``, and a plain memory copy:
    the slower a resample's arithmetic per voxel, the less it waits on memory,
    and the better it scales on a machine whose memory a second core barely
    widens.
    """
    import SimpleITK as sitk

    from volwarp_cli import api, parallel

    def ours(n, spec=spec):
        with parallel.use_threads(n):
            api.warp(vol, str(spec))

    go_vtk = vtk_general(data, dq)

    def vtk_at(n):
        go_vtk.filter.SetNumberOfThreads(n)
        go_vtk()

    go_sitk = sitk_general(data, dq)

    def sitk_at(n):
        sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(n)
        go_sitk()

    for name, run_at, k in (("volwarp warp, every point moved, in process", ours, pairs),
                            ("volwarp warp, one point moved, in process",
                             lambda n: ours(n, one), pairs),
                            ("vtkImageReslice + vtkBSplineTransform", vtk_at, pairs),
                            ("SimpleITK Resample + BSplineTransform", sitk_at, max(1, pairs // 2)),
                            ("a plain copy of 256 MiB (memory only)", copy_in_threads(), pairs)):
        t1, tn, r = threads_speedup(run_at, cores, k)
        print(f"  {name:<44} 1 thread {t1:7.3f} s   {cores} threads {tn:7.3f} s   "
              f"speedup {r:5.2f}x", flush=True)
    sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(cores)


def main(quick: bool = False):
    from volwarp_cli import parallel
    from volwarp_cli.io import write_volume
    from volwarp_cli.volume import Volume

    cores = parallel.available_cores()
    print(f"  cores this process may use: {cores} (affinity and cgroup quota; "
          f"os.cpu_count() {os.cpu_count()})", flush=True)
    if cores < 2:
        print("  one core: no scaling to measure", flush=True)
        return
    pairs = 2 if quick else 5
    n = 128 if quick else 256
    v = volwarp_bin()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        data = volume(n)
        src = tmp / "in.nrrd"
        write_volume(Volume(data), src)
        one = tmp / "one.yaml"
        one.write_text("version: 1\ncapture: {lattice: 9, oversample: 1}\npushforward: box\n"
                       "steps:\n  - move:\n      - {index: [4, 4, 4], by: [3.0, 2.0, 1.0]}\n")
        one2 = tmp / "one2.yaml"
        one2.write_text(one.read_text().replace("oversample: 1", "oversample: 2"))
        dq = general_coefficients(9, 2.0)
        general = tmp / "general.yaml"
        general_spec(general, dq)
        sweep = tmp / "sweep.yaml"
        sweep.write_text(
            "version: 1\ngrid: {spacing: 0.1}\nfields:\n  opacity: {value: 0.8}\n"
            "trajectory:\n  - line: {from: [0, 0, 0], to: [12, 2, 1]}\n"
            "  - arc: {center: [12, 6, 1], radius: 4, axis: [0, 0, 1], start: -90, end: 90}\n"
            "up: [0, 0, 1]\nscale: [4, 4]\n")
        o = str(tmp / "o_{t}")
        rows = [
            (f"warp {n}^3, one point moved", v + ["warp", str(src), "--spec", str(one),
                                                  "-o", o + ".nrrd"], [o + ".nrrd"]),
            (f"warp {n}^3, every point of 9^3 moved",
             v + ["warp", str(src), "--spec", str(general), "-o", o + "g.nrrd"], [o + "g.nrrd"]),
            (f"warp {n}^3 oversample 2, one point moved",
             v + ["warp", str(src), "--spec", str(one2), "-o", o + "2.nrrd"], [o + "2.nrrd"]),
            (f"distance {n}^3", v + ["distance", str(src), "--iso", "50", "-o", o + "d.nrrd"],
             [o + "d.nrrd"]),
            (f"mesh {n}^3", v + ["mesh", str(src), "--iso", "50", "-o", o + ".ply"],
             [o + ".ply"]),
            ("sweep 0.1 mm grid", v + ["sweep", str(sweep), "-o", o + "_{field}.nrrd"],
             [o + "_opacity.nrrd"]),
        ]
        timed = {}
        for name, argv, outputs in rows:
            try:
                timed[name] = scaling_row(name, argv, outputs, cores, pairs)
            except subprocess.CalledProcessError as exc:
                print(f"  {name:<44} failed: {exc}", flush=True)
        # what no thread count changes: the same warp commands on a 16^3 volume
        small = tmp / "small.nrrd"
        write_volume(Volume(volume(16)), small)
        fixed_of = {}
        for name, spec in ((f"warp {n}^3, one point moved", one),
                           (f"warp {n}^3, every point of 9^3 moved", general)):
            if name not in timed:
                continue
            fixed = common.command_time(v + ["warp", str(small), "--spec", str(spec), "-o",
                                             str(tmp / "small_out.nrrd"), "--threads", "1"],
                                        repeat=pairs)
            amdahl_row(name, fixed, *timed[name], cores)
            fixed_of[name] = fixed
        # what the cut predicts at 2, 4, 16 and 64 cores (not measured here)
        from volwarp_cli.bspline.capture import capture_volume
        from volwarp_cli.bspline.scene import Scene

        vol = Volume(data)
        base = capture_volume(vol, lattice=(9, 9, 9), oversample=1)
        one_dq = np.zeros_like(dq)
        one_dq[4, 4, 4] = (3.0, 2.0, 1.0)
        for name, move in ((f"warp {n}^3, one point moved", one_dq),
                           (f"warp {n}^3, every point of 9^3 moved", dq)):
            cap = capture_volume(vol, lattice=(9, 9, 9), oversample=1, defer=True)
            pad = int(np.ceil(np.abs(move).max())) + 1
            scene = Scene(cap.voxmap, cap.grid, base.dq + move, pad, domain_range=base.stats[:2])
            t1 = timed[name][0] if name in timed else None
            predicted_rows(name, scene, t1, fixed_of.get(name))
        # the general deformation against the peers, everything on every core
        cmd = v + ["warp", str(src), "--spec", str(general), "-o", str(tmp / "g.nrrd")]
        subprocess.run(cmd, check=True)
        go_vtk = vtk_general(data, dq)
        go_vtk()
        ours, peer, r = common.paired_times(lambda: subprocess.run(cmd, check=True), go_vtk, pairs)
        common.row(f"general warp {n}^3 vs vtkImageReslice+BSpline", ours, peer, "vtk", r)
        go_sitk = sitk_general(data, dq)
        ours, peer, r = common.paired_times(lambda: subprocess.run(cmd, check=True), go_sitk,
                                            1 if quick else 3)
        common.row(f"general warp {n}^3 vs SimpleITK Resample", ours, peer, "sitk", r)
        # like for like: the peers' whole job as a process too (reading and writing)
        np.save(tmp / "dq.npy", dq)
        for kind, out in (("vtk", "peer.mha"), ("sitk", "peer.nrrd")):
            script = [sys.executable, str(Path(__file__).with_name("peer_bspline_script.py")),
                      kind, str(src), str(tmp / "dq.npy"), str(tmp / out)]
            ours, peer, r = common.paired_times(lambda: subprocess.run(cmd, check=True),
                                                lambda s=script: subprocess.run(s, check=True),
                                                pairs if kind == "vtk" else (1 if quick else 3))
            common.row(f"general warp {n}^3 command vs {kind} script", ours, peer,
                       f"{kind} script", r)
        # the same work in process, no start-up, reading or writing: what the peers' figures
        # are; the command's own path (`volwarp_cli.api.warp` of the volume held), its
        # output cut for the threads as the command's (the whole target as one block on
        # one thread, as before, was slower than the whole command on two)
        from volwarp_cli import api

        def core():
            api.warp(vol, str(general))

        core()
        with parallel.use_threads(cores):
            ours, peer, r = common.paired_times(core, go_vtk, pairs)
            common.row(f"general warp core {n}^3 vs vtkImageReslice+BSpline", ours, peer, "vtk", r)
            ours, peer, r = common.paired_times(core, go_sitk, 1 if quick else 3)
            common.row(f"general warp core {n}^3 vs SimpleITK Resample", ours, peer, "sitk", r)
        # how each scales, in process, from one thread to all, in this same run
        peer_scaling_rows(vol, general, one, data, dq, cores, pairs)
        import SimpleITK as sitk
        import vtk

        reslice = vtk.vtkImageReslice()
        print(f"  (peers' threads: SimpleITK {sitk.ProcessObject.GetGlobalDefaultNumberOfThreads()}, "
              f"vtkImageReslice {reslice.GetNumberOfThreads()} "
              f"(SMP {'on' if reslice.GetEnableSMP() else 'off'}))", flush=True)


if __name__ == "__main__":
    main(quick="--quick" in sys.argv)
