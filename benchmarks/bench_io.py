"""Volume I/O: `volwarp convert` and the in-process readers/writers vs SimpleITK, same run."""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from common import command_time, median_time, row, volwarp_argv  # noqa: E402


def main(quick: bool = False) -> None:
    import SimpleITK as sitk

    from volwarp_cli.io import read_volume, write_volume
    from volwarp_cli.volume import Volume

    n = 128 if quick else 256
    rng = np.random.default_rng(0)
    data = (rng.random((n, n, n), dtype=np.float32) * 1000).astype(np.int16)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        src = tmp / "src.nrrd"
        write_volume(Volume(data, spacing=(0.8, 0.8, 1.5)), src)
        src_gz = tmp / "src_gz.nrrd"
        write_volume(Volume(data, spacing=(0.8, 0.8, 1.5)), src_gz, compress=True)
        for label, path, compress in (("raw", src, False), ("gzip", src_gz, True)):
            ours = median_time(lambda p=path: read_volume(p), repeat=5)
            peer = median_time(lambda p=path: sitk.ReadImage(str(p)), repeat=5)
            row(f"read {n}^3 int16 NRRD ({label})", ours, peer, "SimpleITK")
            vol = read_volume(path)
            img = sitk.ReadImage(str(path))
            ours = median_time(lambda c=compress, v=vol: write_volume(v, tmp / "o.nrrd", compress=c),
                               repeat=3)
            peer = median_time(lambda c=compress, im=img: sitk.WriteImage(im, str(tmp / "s.nrrd"),
                                                                   useCompression=c), repeat=3)
            row(f"write {n}^3 int16 NRRD ({label})", ours, peer, "SimpleITK")
        ours = command_time(volwarp_argv("convert", str(src), "-o", str(tmp / "c.nii.gz")))
        peer = command_time([sys.executable, "-c",
                             "import SimpleITK as s, sys; "
                             "s.WriteImage(s.ReadImage(sys.argv[1]), sys.argv[2], True)",
                             str(src), str(tmp / "s.nii.gz")])
        row(f"whole command: NRRD -> .nii.gz, {n}^3", ours, peer, "SimpleITK script")


if __name__ == "__main__":
    main(quick="--quick" in sys.argv)
