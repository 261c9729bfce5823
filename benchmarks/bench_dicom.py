"""DICOM input: ``read_dicom`` vs SimpleITK's ImageSeriesReader on one CT series, same run."""

from __future__ import annotations

import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from common import paired_times, row, volwarp_argv  # noqa: E402


def write_ct_series(folder: Path, nx: int, ny: int, nz: int) -> None:
    """``nz`` files of ``ny`` x ``nx`` int16 CT slices (12 bits stored, intercept -1024)."""
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.uid import CTImageStorage, ExplicitVRLittleEndian, generate_uid

    rng = np.random.default_rng(0)
    base = rng.integers(0, 2000, size=(ny, nx), dtype=np.int16)
    series, frame = generate_uid(), generate_uid()
    for k in range(nz):
        meta = FileMetaDataset()
        meta.MediaStorageSOPClassUID = CTImageStorage
        meta.MediaStorageSOPInstanceUID = generate_uid()
        meta.TransferSyntaxUID = ExplicitVRLittleEndian
        ds = Dataset()
        ds.file_meta = meta
        ds.SOPClassUID = CTImageStorage
        ds.SOPInstanceUID = meta.MediaStorageSOPInstanceUID
        ds.Modality = "CT"
        ds.StudyInstanceUID = generate_uid()
        ds.SeriesInstanceUID = series
        ds.FrameOfReferenceUID = frame
        ds.InstanceNumber = k + 1
        ds.ImagePositionPatient = [-250.0, -250.0, -300.0 + 1.25 * k]
        ds.ImageOrientationPatient = [1, 0, 0, 0, 1, 0]
        ds.PixelSpacing = [0.9765625, 0.9765625]
        ds.SliceThickness = 1.25
        ds.Rows, ds.Columns = ny, nx
        ds.SamplesPerPixel = 1
        ds.PhotometricInterpretation = "MONOCHROME2"
        ds.BitsAllocated, ds.BitsStored, ds.HighBit = 16, 12, 11
        ds.PixelRepresentation = 1
        ds.RescaleSlope, ds.RescaleIntercept = 1, -1024
        ds.PixelData = (base + k).tobytes()
        # file names in reverse order of position: the reader must sort
        ds.save_as(folder / f"IM{nz - k:05d}.dcm", enforce_file_format=True)


def main(quick: bool = False) -> None:
    import SimpleITK as sitk

    from volwarp_cli.io.dicom import read_dicom

    sitk.ProcessObject_SetGlobalWarningDisplay(False)
    nx = ny = 256 if quick else 512
    nz = 60 if quick else 300
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "series"  # (the outputs beside it: volwarp writes none inside an input)
        folder.mkdir()
        write_ct_series(folder, nx, ny, nz)

        def ours():
            return read_dicom(folder)

        def peer():
            reader = sitk.ImageSeriesReader()
            reader.SetFileNames(reader.GetGDCMSeriesFileNames(str(folder)))
            return reader.Execute()

        a, b = ours(), peer()  # warm the page cache; check that both read the same volume
        if not np.array_equal(a.data, sitk.GetArrayFromImage(b)):
            raise AssertionError("volwarp and SimpleITK read different samples")
        t_ours, t_peer, ratio = paired_times(ours, peer, pairs=3 if quick else 5)
        row(f"read {nx}x{ny}x{nz} int16 CT series ({nz} files)", t_ours, t_peer, "SimpleITK",
            ratio=ratio)
        # the whole command, process start-up and the NRRD write included
        out = Path(tmp) / "out"
        out.mkdir()
        script = ("import SimpleITK as s, sys; r = s.ImageSeriesReader(); "
                  "r.SetFileNames(r.GetGDCMSeriesFileNames(sys.argv[1])); "
                  "s.WriteImage(r.Execute(), sys.argv[2])")

        def ours_cmd():
            subprocess.run(volwarp_argv("convert", str(folder), "-o", str(out / "v.nrrd")),
                           check=True, stdout=subprocess.DEVNULL)

        def peer_cmd():
            subprocess.run([sys.executable, "-c", script, str(folder), str(out / "s.nrrd")],
                           check=True, stdout=subprocess.DEVNULL)

        ours_cmd()
        peer_cmd()
        t_ours, t_peer, ratio = paired_times(ours_cmd, peer_cmd, pairs=3 if quick else 5)
        row(f"`convert` {nz}-file CT series -> NRRD (whole command)", t_ours, t_peer,
            "SimpleITK script", ratio=ratio)


if __name__ == "__main__":
    main(quick="--quick" in sys.argv)
