"""A batch step is skipped only when what it reads and what it made are unchanged.

Ways it skipped a step whose output was no longer current (reviews' findings,
each a stale output reported as up to date): the images a DICOMDIR lists
(under any name), an output option of one fixed name, an elastix file's
initial transform found from another folder than the one the step runs in,
a level linked into an OME-Zarr store, a ``-tFILE`` option's file, and a
change to volwarp's code without a version bump.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pydicom = pytest.importorskip("pydicom")

from volwarp_cli.errors import BadUsage  # noqa: E402
from volwarp_cli.io import read_volume, write_volume  # noqa: E402
from volwarp_cli.io.inputs import refuse_output_over_input  # noqa: E402
from volwarp_cli.runscope import run_scope  # noqa: E402
from volwarp_cli.volume import Volume  # noqa: E402


def volwarp(*args, cwd=None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "volwarp_cli", *map(str, args)], cwd=cwd,
                          capture_output=True, text=True, timeout=300)


def batch(manifest: Path, cwd=None) -> str:
    """The batch's summary line (it must succeed)."""
    res = volwarp("batch", manifest, cwd=cwd)
    assert res.returncode == 0, res.stderr
    return [line for line in res.stderr.splitlines() if line.startswith("volwarp batch:")][0]


def dicomdir_series(folder: Path) -> Path:
    """A 6-slice CT series (:func:`test_io_dicom.write_slice`) in a DICOM file set; its DICOMDIR."""
    from pydicom.fileset import FileSet
    from test_io_dicom import write_slice

    fs = FileSet()
    study = {"StudyDate": "20260101", "StudyTime": "120000", "StudyID": "1",
             "AccessionNumber": "A1"}  # (what a file set's study record needs)
    for k in range(6):
        write_slice(folder.parent / f"slice{k}.dcm", (np.arange(64) + 100 * k).reshape(8, 8),
                    position=(0.0, 0.0, 2.0 * k), instance=k + 1, extra=study)
        fs.add(folder.parent / f"slice{k}.dcm")
    fs.write(folder)
    fs._stage["t"].cleanup()  # (pydicom's staging folder: else cleaned up, with a warning, at exit)
    for k in range(6):
        (folder.parent / f"slice{k}.dcm").unlink()
    return folder / "DICOMDIR"


@pytest.mark.parametrize("name", ["DICOMDIR", "INDEX.DCM"])
def test_an_image_a_dicomdir_lists_changed_redoes_the_step(tmp_path, name):
    """A DICOMDIR is known by content, as its reader knows it: under another name
    (INDEX.DCM) it was hashed alone, and a changed image was skipped (a review)."""
    dicomdir = dicomdir_series(tmp_path / "fs")
    if name != "DICOMDIR":
        dicomdir = dicomdir.rename(dicomdir.with_name(name))
    (tmp_path / "m.yaml").write_text(
        f"version: 1\ninputs: {{list: [fs/{name}]}}\noutput_dir: out\nsteps:\n"
        "  - {name: conv, run: convert, output: \"{stem}.nrrd\"}\n")
    assert batch(tmp_path / "m.yaml") == "volwarp batch: 1 scan, 1 ok, 0 skipped, 0 failed"
    assert batch(tmp_path / "m.yaml") == "volwarp batch: 1 scan, 0 ok, 1 skipped, 0 failed"
    image = sorted(p for p in dicomdir.parent.rglob("*") if p.is_file() and p != dicomdir)[0]
    ds = pydicom.dcmread(image)
    ds.PixelData = np.full(64, 1234, "<i2").tobytes()
    ds.save_as(image)
    assert batch(tmp_path / "m.yaml") == "volwarp batch: 1 scan, 1 ok, 0 skipped, 0 failed"
    out = read_volume(tmp_path / "out" / "fs" / f"{dicomdir.name.split('.')[0]}.nrrd").data
    assert (out == 1234).sum() == 64  # the changed slice
    res = volwarp("convert", dicomdir, "-o", tmp_path / "fresh.nrrd")
    assert res.returncode == 0, res.stderr
    assert np.array_equal(out, read_volume(tmp_path / "fresh.nrrd").data)
    with run_scope(), pytest.raises(BadUsage, match="would overwrite the data file"):
        refuse_output_over_input(image, [dicomdir])  # (its images are the input's files)


def test_an_output_option_of_one_fixed_name_is_recorded_and_checked(tmp_path):
    """--points-to q.csv (one name: one scan) deleted or edited by hand redoes the step."""
    write_volume(Volume(np.zeros((6, 6, 6), np.float32)), tmp_path / "mov.nrrd")
    (tmp_path / "a.tfm").write_text(
        "#Insight Transform File V1.0\n#Transform 0\nTransform: AffineTransform_double_3_3\n"
        "Parameters: 1 0 0 0 1 0 0 0 1 1 2 3\nFixedParameters: 0 0 0\n")
    (tmp_path / "p.csv").write_text("x,y,z\n1,2,3\n")
    (tmp_path / "m.yaml").write_text(
        "version: 1\ninputs: {list: [mov.nrrd]}\noutput_dir: out\nsteps:\n"
        "  - {name: moved, run: apply, output: \"{stem}_moved.nrrd\", options: "
        "[-t, a.tfm, --points-in, p.csv, --points-to, q.csv]}\n")
    assert batch(tmp_path / "m.yaml") == "volwarp batch: 1 scan, 1 ok, 0 skipped, 0 failed"
    made = (tmp_path / "q.csv").read_bytes()
    assert batch(tmp_path / "m.yaml") == "volwarp batch: 1 scan, 0 ok, 1 skipped, 0 failed"
    (tmp_path / "q.csv").unlink()
    assert batch(tmp_path / "m.yaml") == "volwarp batch: 1 scan, 1 ok, 0 skipped, 0 failed"
    assert (tmp_path / "q.csv").read_bytes() == made
    (tmp_path / "q.csv").write_text("edited by hand\n")
    assert batch(tmp_path / "m.yaml") == "volwarp batch: 1 scan, 1 ok, 0 skipped, 0 failed"
    assert (tmp_path / "q.csv").read_bytes() == made


ELASTIX = """(Transform "TranslationTransform")
(NumberOfParameters 3)
(TransformParameters {t})
(InitialTransformParametersFileName "{initial}")
(HowToCombineTransforms "Compose")
(FixedImageDimension 3)
(MovingImageDimension 3)
(Size 6 6 6)
(Spacing 1 1 1)
(Origin 0 0 0)
(Direction 1 0 0 0 1 0 0 0 1)
(Index 0 0 0)
"""


def test_an_initial_transform_is_the_file_the_step_reads(tmp_path):
    """TP1 names TP0: the step (run in the manifest's folder) reads the TP0 there, as elastix
    does (relative to where it ran); the batch hashed the one beside TP1 when started from
    another folder, and kept an output made from the other TP0."""
    root = tmp_path / "proj"
    (root / "reg").mkdir(parents=True)
    data = np.zeros((6, 6, 6), np.float32)
    data[2:4, 2:4, 2:4] = 100
    write_volume(Volume(data), root / "mov.nrrd")
    (root / "reg" / "TP1.txt").write_text(ELASTIX.format(t="0 0 0", initial="TP0.txt"))
    (root / "reg" / "TP0.txt").write_text(ELASTIX.format(t="0 0 0", initial="NoInitialTransform"))
    (root / "TP0.txt").write_text(ELASTIX.format(t="1 0 0", initial="NoInitialTransform"))
    (root / "m.yaml").write_text(
        "version: 1\ninputs: {list: [mov.nrrd]}\noutput_dir: out\nsteps:\n"
        "  - {name: moved, run: apply, output: \"{stem}_moved.nrrd\", options: "
        "[-t, reg/TP1.txt, --interpolation, nearest]}\n")
    start = tmp_path  # (not the manifest's folder)
    assert batch(root / "m.yaml", cwd=start) == \
        "volwarp batch: 1 scan, 1 ok, 0 skipped, 0 failed"
    assert batch(root / "m.yaml", cwd=start) == \
        "volwarp batch: 1 scan, 0 ok, 1 skipped, 0 failed"
    (root / "TP0.txt").write_text(ELASTIX.format(t="2 0 0", initial="NoInitialTransform"))
    assert batch(root / "m.yaml", cwd=start) == \
        "volwarp batch: 1 scan, 1 ok, 0 skipped, 0 failed"
    out = read_volume(root / "out" / "mov_moved.nrrd").data
    fresh = tmp_path / "fresh.nrrd"
    res = volwarp("apply", root / "mov.nrrd", "-t", "reg/TP1.txt", "--interpolation", "nearest",
                  "-o", fresh, cwd=root)
    assert res.returncode == 0, res.stderr
    assert np.array_equal(out, read_volume(fresh).data)


def test_transforms_swapped_between_a_scan_s_columns_redo_the_step(tmp_path):
    """-t {first} -t {second}: the step's inputs were compared by name, so swapping the
    two files between the columns (or giving one twice) kept the old output as up to date
    (a review's finding); the chain's order is what the output is made of."""
    import SimpleITK as sitk

    data = np.zeros((12, 12, 12), np.float32)
    data[3:9, 4:8, 2:10] = 100.0
    (tmp_path / "scans").mkdir()
    write_volume(Volume(data), tmp_path / "scans" / "p01.nrrd")
    scale = sitk.AffineTransform(3)
    scale.SetMatrix([1.2, 0, 0, 0, 1, 0, 0, 0, 1])
    sitk.WriteTransform(scale, str(tmp_path / "A.tfm"))
    sitk.WriteTransform(sitk.TranslationTransform(3, (2.0, 0.0, 0.0)), str(tmp_path / "B.tfm"))
    (tmp_path / "m.yaml").write_text(
        "version: 1\ninputs: {csv: scans.csv}\noutput_dir: out\nsteps:\n"
        "  - {name: moved, run: apply, output: \"{stem}_moved.nrrd\", "
        "options: [-t, \"{first}\", -t, \"{second}\"]}\n")
    out = tmp_path / "out" / "scans" / "p01_moved.nrrd"
    made = {}
    for row in ("A.tfm,B.tfm", "B.tfm,A.tfm", "A.tfm,A.tfm", "A.tfm,B.tfm"):
        (tmp_path / "scans.csv").write_text(f"path,first,second\nscans/p01.nrrd,{row}\n")
        assert batch(tmp_path / "m.yaml", cwd=tmp_path).endswith("1 ok, 0 skipped, 0 failed")
        first, second = row.split(",")
        res = volwarp("apply", tmp_path / "scans" / "p01.nrrd", "-o", tmp_path / "d.nrrd",
                      "-t", tmp_path / first, "-t", tmp_path / second)
        assert res.returncode == 0, res.stderr
        assert np.array_equal(read_volume(out).data, read_volume(tmp_path / "d.nrrd").data)
        made[row] = read_volume(out).data
    assert not np.array_equal(made["A.tfm,B.tfm"], made["B.tfm,A.tfm"])
    # unchanged: skipped
    assert batch(tmp_path / "m.yaml", cwd=tmp_path).endswith("0 ok, 1 skipped, 0 failed")


@pytest.mark.parametrize("pattern", ["../scans/{stem}_c.nrrd", "/tmp/elsewhere_{stem}.nrrd"])
def test_an_output_pattern_that_leaves_output_dir_is_refused(tmp_path, pattern):
    """'../scans/{stem}_c.nrrd' wrote beside the scans, outside the batch's lock: the next
    run took it for a scan and stopped; two batches wrote one file unlocked (a review)."""
    (tmp_path / "scans").mkdir()
    write_volume(Volume(np.zeros((4, 4, 4), np.float32)), tmp_path / "scans" / "p01.nrrd")
    for where in ("output", "option"):
        step = (f"{{name: c, run: convert, output: \"{pattern}\"}}" if where == "output" else
                "{name: m, run: mesh, output: \"{stem}.ply\", options: [--iso, \"0.5\", "
                f"--render, \"{pattern.replace('.nrrd', '.png')}\"]}}")
        (tmp_path / "m.yaml").write_text("version: 1\ninputs: {glob: \"scans/*.nrrd\"}\n"
                                         f"output_dir: out\nsteps:\n  - {step}\n")
        res = volwarp("batch", tmp_path / "m.yaml", cwd=tmp_path)
        assert res.returncode == 2 and "leaves output_dir" in res.stderr, res.stderr
        assert sorted(p.name for p in (tmp_path / "scans").iterdir()) == ["p01.nrrd"]


def test_an_output_pattern_with_dotdot_inside_output_dir_is_told_what_to_write(tmp_path):
    """'./sub/../{stem}_c.nrrd' stays in output_dir; it is refused all the same ('..' in a
    pattern), but was said to leave output_dir: the message names the plain path."""
    (tmp_path / "scans").mkdir()
    write_volume(Volume(np.zeros((4, 4, 4), np.float32)), tmp_path / "scans" / "p01.nrrd")
    (tmp_path / "m.yaml").write_text(
        "version: 1\ninputs: {glob: \"scans/*.nrrd\"}\noutput_dir: out\nsteps:\n"
        "  - {name: c, run: convert, output: \"./sub/../{stem}_c.nrrd\"}\n")
    res = volwarp("batch", tmp_path / "m.yaml", cwd=tmp_path)
    assert res.returncode == 2, res.stderr
    assert "leaves output_dir" not in res.stderr
    assert "has '..' in it" in res.stderr and "'{stem}_c.nrrd'" in res.stderr
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").rglob("*.nrrd"))


def test_a_level_linked_into_an_ome_zarr_store_is_what_the_step_reads(tmp_path):
    """zarr reads a store's keys through linked folders; the batch's walk did not follow
    them, so a changed level linked in from elsewhere was skipped (a review). A link back
    up the store ends no walk."""
    import shutil

    store = tmp_path / "scans" / "z.ome.zarr"
    store.parent.mkdir()
    data = np.zeros((6, 6, 6), np.float32)
    data[2:4, 2:4, 2:4] = 100
    write_volume(Volume(data), store)
    (tmp_path / "levels").mkdir()
    (store / "0").rename(tmp_path / "levels" / "z0")
    (store / "0").symlink_to("../../levels/z0")
    (tmp_path / "levels" / "z0" / "up").symlink_to("../../scans")  # (a loop)
    (tmp_path / "m.yaml").write_text(
        "version: 1\ninputs: {list: [scans/z.ome.zarr], settle: 0}\noutput_dir: out\nsteps:\n"
        "  - {name: conv, run: convert, output: \"z.nrrd\"}\n")
    assert batch(tmp_path / "m.yaml") == "volwarp batch: 1 scan, 1 ok, 0 skipped, 0 failed"
    assert batch(tmp_path / "m.yaml") == "volwarp batch: 1 scan, 0 ok, 1 skipped, 0 failed"
    write_volume(Volume(data * 2), tmp_path / "other.ome.zarr")
    shutil.rmtree(tmp_path / "levels" / "z0" / "c")
    shutil.copytree(tmp_path / "other.ome.zarr" / "0" / "c", tmp_path / "levels" / "z0" / "c")
    assert batch(tmp_path / "m.yaml") == "volwarp batch: 1 scan, 1 ok, 0 skipped, 0 failed"
    res = volwarp("convert", store, "-o", tmp_path / "fresh.nrrd")
    assert res.returncode == 0, res.stderr
    out = read_volume(tmp_path / "out" / "scans" / "z.nrrd").data
    assert out.max() == 200 and np.array_equal(out, read_volume(tmp_path / "fresh.nrrd").data)


IDENTITY = ("#Insight Transform File V1.0\n#Transform 0\nTransform: AffineTransform_double_3_3\n"
            "Parameters: 1 0 0 0 1 0 0 0 1 {shift} 0 0\nFixedParameters: 0 0 0\n")


@pytest.mark.parametrize("item", ["-tid.tfm", "-qtid.tfm"])
def test_an_attached_short_option_s_file_is_the_manifest_folder_s(tmp_path, item):
    """-tFILE (click's attached form) was not known as -t's value: its file was hashed from
    the folder the batch started in, not the manifest's, where the step reads it (a review)."""
    root, start = tmp_path / "proj", tmp_path / "elsewhere"
    (root / "scans").mkdir(parents=True)
    start.mkdir()
    data = np.zeros((6, 6, 6), np.float32)
    data[2:4, 2:4, 2:4] = 100
    write_volume(Volume(data), root / "scans" / "b.nrrd")
    (root / "id.tfm").write_text(IDENTITY.format(shift=0))
    (start / "id.tfm").write_text(IDENTITY.format(shift=0))  # (never the step's)
    (root / "m.yaml").write_text(
        "version: 1\ninputs: {glob: 'scans/*.nrrd'}\noutput_dir: out\nsteps:\n"
        f"  - {{name: moved, run: apply, output: \"{{stem}}_moved.nrrd\", options: [{item}]}}\n")
    assert batch(root / "m.yaml", cwd=start).endswith("1 ok, 0 skipped, 0 failed")
    assert batch(root / "m.yaml", cwd=start).endswith("0 ok, 1 skipped, 0 failed")
    (root / "id.tfm").write_text(IDENTITY.format(shift=2))
    assert batch(root / "m.yaml", cwd=start).endswith("1 ok, 0 skipped, 0 failed")
    res = volwarp("apply", root / "scans" / "b.nrrd", "-t", root / "id.tfm", "-o",
                  tmp_path / "fresh.nrrd")
    assert res.returncode == 0, res.stderr
    out = read_volume(root / "out" / "b_moved.nrrd").data
    assert np.array_equal(out, read_volume(tmp_path / "fresh.nrrd").data)
    assert not np.array_equal(out, data)


def test_an_attached_output_option_is_refused(tmp_path):
    """-oNAME is -o NAME: set by the step's output key, as -o is (it overrode the output)."""
    (tmp_path / "scans").mkdir()
    write_volume(Volume(np.zeros((4, 4, 4), np.float32)), tmp_path / "scans" / "b.nrrd")
    (tmp_path / "m.yaml").write_text(
        "version: 1\ninputs: {glob: 'scans/*.nrrd'}\noutput_dir: out\nsteps:\n"
        "  - {name: conv, run: convert, output: \"{stem}.nrrd\", options: [-qox.nrrd]}\n")
    res = volwarp("batch", tmp_path / "m.yaml")
    assert res.returncode == 2 and "-o is set by the step's output key" in res.stderr, res.stderr
    assert not (tmp_path / "x.nrrd").exists() and not (tmp_path / "out").exists()


def test_any_change_to_volwarp_s_code_redoes_every_step(tmp_path):
    """A commit may change what a command writes without a version bump; the records of an
    older tree were taken as current (a review). Here volwarp runs from a copy of its package
    (a compiled file appears: __pycache__ is no source), then one of its files changes."""
    import shutil

    import volwarp_cli

    package = tmp_path / "site" / "volwarp_cli"
    shutil.copytree(Path(volwarp_cli.__file__).parent, package,
                    ignore=shutil.ignore_patterns("__pycache__"))
    (tmp_path / "scans").mkdir()
    write_volume(Volume(np.arange(64, dtype=np.float32).reshape(4, 4, 4)),
                 tmp_path / "scans" / "b.nrrd")
    (tmp_path / "m.yaml").write_text(
        "version: 1\ninputs: {glob: 'scans/*.nrrd'}\noutput_dir: out\nsteps:\n"
        "  - {name: conv, run: convert, output: \"{stem}.nii.gz\"}\n")
    env = dict(os.environ, PYTHONPATH=str(package.parent))

    def run_batch() -> dict:
        res = subprocess.run([sys.executable, "-m", "volwarp_cli", "batch", tmp_path / "m.yaml",
                              "-q", "--report-json", tmp_path / "r.json"], env=env, cwd=tmp_path,
                             capture_output=True, text=True, timeout=300)
        assert res.returncode == 0, res.stderr
        return json.loads((tmp_path / "r.json").read_text())["scans"][0]["steps"][0]

    assert run_batch()["status"] == "ok"
    (package / "cli" / "__pycache__").mkdir(exist_ok=True)  # (as a run may compile the copy)
    (package / "cli" / "__pycache__" / "batch.cpython-311.pyc").write_bytes(b"compiled")
    assert run_batch()["status"] == "skipped"
    with open(package / "io" / "nifti.py", "a") as fh:
        fh.write("\n# a commit that changes no version\n")
    step = run_batch()
    assert step["status"] == "ok" and "volwarp's code changed" in step["reason"], step
    assert volwarp("convert", tmp_path / "scans" / "b.nrrd", "-o", tmp_path / "d.nii.gz"
                   ).returncode == 0
    assert np.array_equal(read_volume(tmp_path / "out" / "b.nii.gz").data,
                          read_volume(tmp_path / "d.nii.gz").data)
