"""`volwarp apply` against SimpleITK doing the same, whole processes (issue 30).

    python benchmarks/bench_apply.py [--quick] [--pairs N] [--big]

An int16 scan (.nii.gz) through a displacement field (a 5-D .nii.gz of float32
LPS vectors, as ANTs' ``1Warp.nii.gz``: smooth noise of a few mm, which
compresses as real fields do) and then an affine (ITK .tfm), onto its own grid,
linear: ``volwarp apply IN -o OUT -t FIELD -t AFFINE`` against a SimpleITK
script reading both, building the composite (affine after field, the same
mapping), ``Resample`` and writing the .nii.gz; each a new process, alternated
``--pairs`` times after one untimed run of each. Printed: both medians, the
median of the pair-by-pair ratios (the issue's target: at most 0.5x), and each
one's peak memory (``/usr/bin/time -f %M``, one more run each).

Rows: 160^3 and 256^3 (``--quick``: 96^3 and 128^3, 3 pairs). A third row
reads a large uncompressed field (``--big``: 512^3, 1.5 GiB; else 256^3, 201 MB)
against ``cat FILE > /dev/null`` of the same file, both from the page cache:
the field is read at near the file's speed and stays float32. A fourth (not
with ``--quick``) runs the 256^3 chain under ``--memory-limit 400M`` with the
``.nii.gz`` field (beyond a quarter of the budget: inflated to a scratch file,
read by windows) against the same field as ``.nii``.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import common  # noqa: E402
from common import row  # noqa: E402

PEER = """
import sys, SimpleITK as sitk
img = sitk.ReadImage(sys.argv[1])
field = sitk.ReadImage(sys.argv[2], sitk.sitkVectorFloat64)
chain = sitk.CompositeTransform(3)
chain.AddTransform(sitk.ReadTransform(sys.argv[3]))       # applied second
chain.AddTransform(sitk.DisplacementFieldTransform(field))  # applied first
sitk.WriteImage(sitk.Resample(img, img, chain, sitk.sitkLinear, 0.0), sys.argv[4])
"""


def scan_and_field(n: int, folder: Path, compressed: bool = True) -> tuple[Path, Path, Path]:
    """An n^3 int16 scan, its displacement field and an affine, written by SimpleITK."""
    import SimpleITK as sitk
    from scipy.ndimage import gaussian_filter, zoom

    rng = np.random.default_rng(0)
    ext = ".nii.gz" if compressed else ".nii"
    z, y, x = np.ogrid[:n, :n, :n]
    scan = (1000 * np.sin(6 * x / n) * np.cos(5 * y / n) * np.sin(4 * z / n + 1)
            + 1000).astype(np.int16)
    img = sitk.GetImageFromArray(scan)
    img.SetOrigin((-n / 2, -n / 2, -n / 2))
    img_path = folder / f"scan{n}{ext}"
    sitk.WriteImage(img, str(img_path))
    coarse = n // 4
    vectors = np.stack([zoom(gaussian_filter(rng.normal(size=(coarse,) * 3), 2) * 8,
                             n / coarse, order=1)[:n, :n, :n] for _ in range(3)], axis=-1)
    field = sitk.GetImageFromArray(vectors.astype(np.float32), isVector=True)
    field.CopyInformation(img)
    field_path = folder / f"field{n}{ext}"
    sitk.WriteImage(field, str(field_path))
    affine = sitk.AffineTransform(3)
    affine.SetMatrix((1.02, 0.05, 0, -0.04, 0.98, 0.03, 0.01, 0, 1.01))
    affine.SetTranslation((1.5, -2.0, 0.7))
    affine_path = folder / "affine.tfm"
    sitk.WriteTransform(affine, str(affine_path))
    return img_path, field_path, affine_path


def peak_mib(argv: list[str]) -> float | None:
    """The peak resident memory of one run of ``argv`` (GNU time), MiB; None without it."""
    if not Path("/usr/bin/time").exists():
        return None
    res = subprocess.run(["/usr/bin/time", "-f", "%M", *argv], check=True,
                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    return int(res.stderr.strip().splitlines()[-1]) / 1024


def chain_rows(sizes, pairs: int, folder: Path) -> None:
    peer_script = folder / "peer.py"
    peer_script.write_text(PEER)
    print(f"  whole processes: apply -t FIELD -t AFFINE (linear) against a SimpleITK script "
          f"({pairs} alternated pairs each)", flush=True)
    for n in sizes:
        scan, field, affine = scan_and_field(n, folder)
        ours = common.volwarp_argv("apply", str(scan), "-o", str(folder / "ours.nii.gz"),
                                   "-t", str(field), "-t", str(affine), "-q")
        peer = [sys.executable, str(peer_script), str(scan), str(field), str(affine),
                str(folder / "peer.nii.gz")]
        a, b = common.process(ours), common.process(peer)
        a()
        b()
        t_ours, t_peer, ratio = common.paired_times(a, b, pairs)
        row(f"apply {n}^3 .nii.gz, field + affine", t_ours, t_peer, "SimpleITK", ratio=ratio)
        mem = peak_mib(ours), peak_mib(peer)
        if None not in mem:
            print(f"    (peak memory: volwarp {mem[0]:.0f} MiB, SimpleITK {mem[1]:.0f} MiB)",
                  flush=True)
        for f in (scan, field):
            f.unlink()


def field_read_row(n: int, folder: Path, repeat: int) -> None:
    """Reading an uncompressed field in process against ``cat`` of its file."""
    from volwarp_cli.transforms.fields import read_field

    vectors = np.zeros((n, n, n, 3), np.float32)
    vectors[..., 0] = np.linspace(-2, 2, n, dtype=np.float32)
    import SimpleITK as sitk

    path = folder / f"field{n}.nii"
    sitk.WriteImage(sitk.GetImageFromArray(vectors, isVector=True), str(path))
    del vectors
    cat = shutil.which("cat")

    def read():
        field = read_field(str(path), "nifti")
        assert field.itemsize == 4  # float32 kept (never inflated to float64)

    def disk():
        subprocess.run([cat, str(path)], check=True, stdout=subprocess.DEVNULL)

    disk()
    read()  # untimed: the interleaving kernel loaded, the file in the page cache
    ours, ref, ratio = common.paired_times(read, disk, repeat)
    size = path.stat().st_size / 2 ** 20
    row(f"read a {n}^3 float32 field (.nii, {size:.0f} MiB)", ours, ref, "cat", ratio=ratio)
    path.unlink()


def over_budget_row(folder: Path, pairs: int, n: int = 256, limit: str = "400M") -> None:
    """A .nii.gz field beyond a quarter of the budget (a scratch copy) against the same .nii.

    Both by blocks under ``--memory-limit``; before the scratch copy the
    compressed field was read whole and the command refused.
    """
    import SimpleITK as sitk

    scan, field_gz, affine = scan_and_field(n, folder)
    field = folder / f"field{n}.nii"
    sitk.WriteImage(sitk.ReadImage(str(field_gz)), str(field))
    runs = [common.volwarp_argv("apply", str(scan), "-o", str(folder / f"{name}.nrrd"), "-t",
                                str(f), "-t", str(affine), "--memory-limit", limit, "-q")
            for name, f in (("gz", field_gz), ("raw", field))]
    a, b = common.process(runs[0]), common.process(runs[1])
    a()
    b()
    t_gz, t_raw, ratio = common.paired_times(a, b, pairs)
    row(f"apply {n}^3, .nii.gz field copied to scratch, --memory-limit {limit}", t_gz, t_raw,
        "the same field as .nii", ratio=ratio)
    mem = peak_mib(runs[0]), peak_mib(runs[1])
    if None not in mem:
        print(f"    (peak memory: .nii.gz {mem[0]:.0f} MiB, .nii {mem[1]:.0f} MiB)", flush=True)
    for f in (scan, field_gz, field):
        f.unlink()


def main(quick: bool = False, pairs: int | None = None, big: bool = False) -> None:
    pairs = pairs or (3 if quick else 5)
    sizes = (96, 128) if quick else (160, 256)
    with tempfile.TemporaryDirectory(prefix="volwarp-bench-apply-") as tmp:
        folder = Path(tmp)
        chain_rows(sizes, pairs, folder)
        field_read_row(512 if big else (128 if quick else 256), folder, pairs)
        if not quick:  # (256^3: the budget must leave the blocks room beside the libraries)
            over_budget_row(folder, pairs)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--pairs", type=int)
    parser.add_argument("--big", action="store_true", help="a 512^3 field (1.5 GiB)")
    args = parser.parse_args()
    main(args.quick, args.pairs, args.big)
