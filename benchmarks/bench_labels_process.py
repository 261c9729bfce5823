"""A label warp against the intensity warp of the same map, whole processes (issue 32).

    python benchmarks/bench_labels_process.py [--quick] [--pairs N]

Two maps, each warped by the same spec (a 9^3 lattice, its centre dragged by
about 6% of the map) with ``--values labels`` and with ``--values
intensity``, each a new process (``python -m volwarp_cli warp ... -q``),
alternated ``--pairs`` times after one untimed run of each (kernels loaded,
files cached); printed: both medians and the median of the pair-by-pair
ratios (the target: at most 1.5x, whatever the label count).

- the frog: pyvista's ``frog_tissues.vti`` (26 labels on 500x470x136, the
  test extras install it) taken every second voxel in x and y: 250x235x136
  uint8 (a synthetic map of 26 touching labels of that size without pyvista);
- 100 labels: a ball of 100 touching Voronoi cells with scattered uint16 ids,
  0 around, 224x224x160.

``--quick``: maps of half the size, 3 pairs.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import common  # noqa: E402
from common import row  # noqa: E402


def voronoi(shape, cells: int, seed: int, dtype=np.uint16) -> np.ndarray:
    """A ball of ``cells`` touching Voronoi cells (ids scattered over 1..9 * cells), 0 around."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(seed)
    coarse = tuple(max(1, n // 4) for n in shape)
    centres = (np.indices(coarse).reshape(3, -1).T + 0.5) / np.array(coarse) - 0.5
    seeds = rng.uniform(-0.4, 0.4, (cells, 3))
    _, nearest = cKDTree(seeds).query(centres)
    ids = rng.permutation(np.arange(1, 9 * cells + 1))[:cells]
    small = ids[nearest].reshape(coarse)
    small[(centres ** 2).sum(axis=1).reshape(coarse) > 0.45 ** 2] = 0
    full = small.repeat(4, 0).repeat(4, 1).repeat(4, 2)
    out = np.zeros(shape, dtype)
    out[:full.shape[0], :full.shape[1], :full.shape[2]] = full[:shape[0], :shape[1], :shape[2]]
    return out


def frog(quick: bool):
    """The frog's tissues every second voxel in x and y (z y x) and its spacing (x y z)."""
    try:
        import pyvista
        from pyvista import examples  # noqa: F401
    except ImportError:
        pyvista = None
    path = Path(pyvista.__file__).parent / "examples" / "frog_tissues.vti" if pyvista else None
    if path is not None and path.exists():
        image = pyvista.read(str(path))
        nx, ny, nz = image.dimensions
        data = np.asarray(image.point_data[image.array_names[0]]).reshape(nz, ny, nx)
        lab = np.ascontiguousarray(data[:, ::2, ::2]).astype(np.uint8)
        what = "the frog's tissues (pyvista), 26 labels"
    else:
        lab = voronoi((136, 235, 250), 25, seed=1, dtype=np.uint8)
        what = "a frog-sized map of 26 labels (pyvista missing)"
    if quick:
        lab = np.ascontiguousarray(lab[::2, ::2, ::2])
    return lab, what


def spec_for(shape_zyx, path: Path) -> Path:
    """The spec both warps of a map take: a 9^3 lattice, the centre dragged (voxel units)."""
    nz, ny, nx = shape_zyx
    c = [nx / 2, ny / 2, nz / 2]
    to = [c[0] + 0.05 * nx, c[1] - 0.04 * ny, c[2] + 0.06 * nz]
    path.write_text("version: 1\nunits: voxel\ncapture: {lattice: 9}\nsteps:\n  - drag:\n"
                    f"      - {{from: [{c[0]:.1f}, {c[1]:.1f}, {c[2]:.1f}], "
                    f"to: [{to[0]:.1f}, {to[1]:.1f}, {to[2]:.1f}]}}\n")
    return path


def main(quick: bool = False, pairs: int | None = None) -> None:
    from volwarp_cli.io import write_volume
    from volwarp_cli.volume import Volume

    pairs = pairs or (3 if quick else 7)
    frog_map, frog_what = frog(quick)
    shape = (80, 112, 112) if quick else (160, 224, 224)
    maps = [("frog", frog_map, frog_what),
            ("voronoi100", voronoi(shape, 100, seed=7), "100 labels, uint16")]
    with tempfile.TemporaryDirectory(prefix="volwarp-bench-labels-") as tmp:
        tmp = Path(tmp)
        print(f"  whole `warp` processes, --values labels against --values intensity "
              f"({pairs} alternated pairs each)", flush=True)
        for name, lab, what in maps:
            src = tmp / f"{name}.nrrd"
            write_volume(Volume(lab), src)
            spec = spec_for(lab.shape, tmp / f"{name}.yaml")
            runs = {}
            for values in ("labels", "intensity"):
                argv = common.volwarp_argv("warp", str(src), "--spec", str(spec), "--values",
                                           values, "-o", str(tmp / f"{name}_{values}.nrrd"), "-q")
                runs[values] = common.process(argv)
                runs[values]()  # untimed: kernels loaded, files cached
            ours, ref, ratio = common.paired_times(runs["labels"], runs["intensity"], pairs)
            nz, ny, nx = lab.shape
            row(f"warp --labels {nx}x{ny}x{nz} ({name})", ours, ref, "intensity", ratio=ratio)
            print(f"    ({what})", flush=True)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="half-size maps, 3 pairs")
    parser.add_argument("--pairs", type=int, default=None, help="pairs per row (default 7)")
    args = parser.parse_args()
    main(quick=args.quick, pairs=args.pairs)
