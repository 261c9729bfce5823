"""`volwarp batch` steps applying each scan's own transforms, from its row of the scans' table.

``-t {transform}`` (any column: ``-t {warp} -t {affine}``) is the file in the
scan's row; it is one of the files the scan's outputs are made from (an
elastix file with its initial transforms), so a changed registration redoes
its scan only.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from volwarp_cli.io import read_volume, write_volume
from volwarp_cli.volume import Volume


def _elastix(path, shift, initial=None):
    """A TranslationTransform parameter file on the scans' 14x12x10 grid (chained to ``initial``)."""
    path.write_text(
        '(Transform "TranslationTransform")\n(NumberOfParameters 3)\n'
        f"(TransformParameters {' '.join(str(v) for v in shift)})\n"
        f'(InitialTransformParametersFileName "{initial or "NoInitialTransform"}")\n'
        '(HowToCombineTransforms "Compose")\n(FixedImageDimension 3)\n'
        "(Size 14 12 10)\n(Spacing 1 1 1)\n(Origin 0 0 0)\n(Direction 1 0 0 0 1 0 0 0 1)\n"
        "(Index 0 0 0)\n")


@pytest.fixture
def subjects(tmp_path):
    """Two scans, each with its own ITK affine and elastix chain (1 -> 0), listed in a table."""
    rng = np.random.default_rng(4)
    z, y, x = np.mgrid[:10, :12, :14].astype(float)
    for k, name in enumerate(("p01", "p02")):
        folder = tmp_path / name
        folder.mkdir()
        data = (100 * np.exp(-((x - 7) ** 2 + (y - 6) ** 2 + (z - 5) ** 2) / (12 + 4 * k))
                + rng.normal(0, 1, x.shape)).astype(np.float32)
        write_volume(Volume(data), folder / "scan.nrrd")
        (folder / "a.tfm").write_text(
            "#Insight Transform File V1.0\n#Transform 0\n"
            "Transform: AffineTransform_double_3_3\n"
            f"Parameters: 1.02 0.03 0 -0.02 0.98 0 0 0.01 1 {0.4 + k} -0.6 {0.3 * k}\n"
            "FixedParameters: 7 6 5\n")
        _elastix(folder / "TransformParameters.0.txt", [0.5, -0.25 * k, 0.75])
        _elastix(folder / "TransformParameters.1.txt", [-0.3, 0.6, 0.1 * k],
                 initial=folder / "TransformParameters.0.txt")
    (tmp_path / "scans.csv").write_text(
        "path,transform,elastix\n"
        "p01/scan.nrrd,p01/a.tfm,p01/TransformParameters.1.txt\n"
        "p02/scan.nrrd,p02/a.tfm,p02/TransformParameters.1.txt\n")
    (tmp_path / "m.yaml").write_text(
        "version: 1\ninputs: {csv: scans.csv}\noutput_dir: out\nsteps:\n"
        "  - name: moved\n    run: apply\n    output: '{stem}_moved.nrrd'\n"
        "    options: [-t, '{transform}', --background-value, '0']\n"
        "  - name: chained\n    run: apply\n    output: '{stem}_el.nrrd'\n"
        "    options: [-t, '{elastix}', --background-value, '0', --interpolation, bspline]\n")
    return tmp_path


def _statuses(run, d):
    res = run("batch", d / "m.yaml", "-q", "--report-json", d / "r.json")
    assert res.code == 0, res.stderr
    report = json.loads((d / "r.json").read_text())
    return {s["scan"]: s["status"] for s in report["scans"]}


def test_each_scan_applies_its_own_transforms(run, subjects):
    """The outputs are those of `volwarp apply` with each row's files; a changed file redoes
    its scan only (an elastix chain's initial transform too)."""
    d = subjects
    res = run("batch", d / "m.yaml", "-q")
    assert res.code == 0, res.stderr
    for name in ("p01", "p02"):
        folder = d / name
        for out, args in (("scan_moved.nrrd", ["-t", folder / "a.tfm", "--background-value",
                                                "0"]),
                          ("scan_el.nrrd", ["-t", folder / "TransformParameters.1.txt",
                                            "--background-value", "0", "--interpolation",
                                            "bspline"])):
            want = d / f"want_{name}_{out}"
            assert run("apply", folder / "scan.nrrd", "-o", want, *args).code == 0
            got = read_volume(d / "out" / name / out).data
            assert np.array_equal(got, read_volume(want).data)
    assert not np.array_equal(read_volume(d / "out" / "p01" / "scan_moved.nrrd").data,
                              read_volume(d / "out" / "p02" / "scan_moved.nrrd").data)
    assert _statuses(run, d) == {"p01/scan": "skipped", "p02/scan": "skipped"}
    # a changed initial transform of p02's elastix chain (not named in the table) redoes p02
    _elastix(d / "p02" / "TransformParameters.0.txt", [0.9, 0.0, 0.0])
    assert _statuses(run, d) == {"p01/scan": "skipped", "p02/scan": "ok"}
    (d / "p01" / "a.tfm").write_text((d / "p01" / "a.tfm").read_text().replace("1.02", "1.03"))
    assert _statuses(run, d) == {"p01/scan": "ok", "p02/scan": "skipped"}


def test_a_fixed_elastix_transforms_initial_file_is_one_of_the_inputs(run, subjects):
    """The same elastix chain for every scan, written in the step's options (not a table
    column): its initial transform is read with it, so a change to it redoes every scan
    (the batch's dry run stops at the input's reading, before the chain is read)."""
    d = subjects
    chain = d / "p01" / "TransformParameters.1.txt"
    (d / "m.yaml").write_text(
        "version: 1\ninputs: {glob: 'p0*/scan.nrrd'}\noutput_dir: out\nsteps:\n"
        "  - name: chained\n    run: apply\n    output: '{stem}_el.nrrd'\n"
        f"    options: [-t, '{chain}', --background-value, '0']\n")
    assert _statuses(run, d) == {"p01/scan": "ok", "p02/scan": "ok"}
    assert _statuses(run, d) == {"p01/scan": "skipped", "p02/scan": "skipped"}
    _elastix(d / "p01" / "TransformParameters.0.txt", [3.5, 2.0, 1.0])
    assert _statuses(run, d) == {"p01/scan": "ok", "p02/scan": "ok"}


@pytest.mark.parametrize(("inputs", "options", "says"), [
    ("{glob: 'p0*/scan.nrrd'}", "[-t, '{transform}']", "inputs.csv with a 'transform' column"),
    ("{csv: scans.csv}", "[-t, '{warp}']", "scans.csv has no 'warp' column"),
    ("{csv: scans.csv}", "[-t, 'x/{transform}']", "is a whole option value"),
    ("{csv: scans.csv}", "[--background-value, '{transform}']", "the value of an input option"),
])
def test_transform_column_misuse_refused_before_any_work(run, subjects, inputs, options, says):
    d = subjects
    (d / "bad.yaml").write_text(
        f"version: 1\ninputs: {inputs}\noutput_dir: out\nsteps:\n"
        f"  - name: moved\n    run: apply\n    output: '{{stem}}_moved.nrrd'\n"
        f"    options: {options}\n")
    res = run("batch", d / "bad.yaml", "-q")
    assert res.code == 2, res.stderr
    assert says in res.stderr
    assert not (d / "out").exists()


def test_empty_transform_cell_refused(run, subjects):
    d = subjects
    (d / "scans.csv").write_text("path,transform,elastix\np01/scan.nrrd,,x\n")
    res = run("batch", d / "m.yaml", "-q")
    assert res.code == 2 and "transform: empty cell" in res.stderr


def _affine(path, shift):
    path.write_text("#Insight Transform File V1.0\n#Transform 0\n"
                    "Transform: AffineTransform_double_3_3\n"
                    f"Parameters: 1 0 0 0 1 0 0 0 1 {shift} 0 0\nFixedParameters: 0 0 0\n")


def _same_as_apply(run, d, scan, out, *args):
    """The batch's output of ``scan`` is `volwarp apply`'s with ``args``."""
    want = d / "want.nrrd"
    assert run("apply", scan, "-o", want, *args).code == 0
    assert np.array_equal(read_volume(out).data, read_volume(want).data)


def test_a_step_file_that_is_the_first_scan_is_every_scan_s_file(run, subjects):
    """--reference p01/scan.nrrd over every scan: the batch's dry run (on p01) dropped the
    files equal to its sample scan, so p02's step did not hash its reference, and a
    replaced p01 left p02's output as it was (a review)."""
    d = subjects
    (d / "id.tfm").write_text("#Insight Transform File V1.0\n#Transform 0\n"
                              "Transform: IdentityTransform_double_3_3\n")
    (d / "m.yaml").write_text(
        "version: 1\ninputs: {glob: 'p0*/scan.nrrd'}\noutput_dir: out\nsteps:\n"
        "  - name: on_p01\n    run: apply\n    output: '{stem}_on_p01.nrrd'\n"
        "    options: [-t, id.tfm, --reference, p01/scan.nrrd]\n")
    assert _statuses(run, d) == {"p01/scan": "ok", "p02/scan": "ok"}
    assert _statuses(run, d) == {"p01/scan": "skipped", "p02/scan": "skipped"}
    write_volume(Volume(np.zeros((5, 6, 7), np.float32), spacing=(2.0, 2.0, 2.0)),
                 d / "p01" / "scan.nrrd")  # (another grid)
    assert _statuses(run, d) == {"p01/scan": "ok", "p02/scan": "ok"}
    _same_as_apply(run, d, d / "p02" / "scan.nrrd", d / "out" / "p02" / "scan_on_p01.nrrd",
                   "-t", d / "id.tfm", "--reference", d / "p01" / "scan.nrrd")
    assert read_volume(d / "out" / "p02" / "scan_on_p01.nrrd").data.shape == (5, 6, 7)


def test_a_fixed_transform_that_is_the_first_row_s_cell_is_every_scan_s(run, subjects):
    """-t {transform} -t shared.tfm, p01's row naming shared.tfm too: dropped as one of the
    sample scan's cells, shared.tfm was no file of p02's step, and a changed one left
    p02's output as it was (a review)."""
    d = subjects
    _affine(d / "shared.tfm", 1)
    (d / "scans.csv").write_text("path,transform\np01/scan.nrrd,shared.tfm\n"
                                 "p02/scan.nrrd,p02/a.tfm\n")
    (d / "m.yaml").write_text(
        "version: 1\ninputs: {csv: scans.csv}\noutput_dir: out\nsteps:\n"
        "  - name: moved\n    run: apply\n    output: '{stem}_moved.nrrd'\n"
        "    options: [-t, '{transform}', -t, shared.tfm, --background-value, '0']\n")
    assert _statuses(run, d) == {"p01/scan": "ok", "p02/scan": "ok"}
    assert _statuses(run, d) == {"p01/scan": "skipped", "p02/scan": "skipped"}
    _affine(d / "shared.tfm", 3)
    assert _statuses(run, d) == {"p01/scan": "ok", "p02/scan": "ok"}
    _same_as_apply(run, d, d / "p02" / "scan.nrrd", d / "out" / "p02" / "scan_moved.nrrd",
                   "-t", d / "p02" / "a.tfm", "-t", d / "shared.tfm", "--background-value", "0")


@pytest.mark.parametrize("case", ["another-scan", "another-step", "report"])
def test_an_output_over_a_file_any_scan_s_cell_names_is_refused(run, subjects, case):
    """A table cell's file is an input of every scan's step, not only of its own: scan
    p02's output over p01's transform, one step's output over the file another step of
    the scan reads through its cell, or a report over one, replaced it with exit 0."""
    d = subjects
    victim = d / "out" / "p02" / "scan_el.nrrd"  # what p02's step 'chained' writes
    victim.parent.mkdir(parents=True)
    victim.write_bytes((d / "p01" / "a.tfm").read_bytes())
    before = victim.read_bytes()
    rows = {"another-scan": ["p01", "p02"], "another-step": ["p02"], "report": ["p01"]}[case]
    (d / "scans.csv").write_text("path,transform,elastix\n" + "".join(
        f"{name}/scan.nrrd,{victim if k == 0 else f'{name}/a.tfm'},"
        f"{name}/TransformParameters.1.txt\n" for k, name in enumerate(rows)))
    extra = ["--report-json", victim] if case == "report" else []
    res = run("batch", d / "m.yaml", "-q", *extra)
    assert res.code == 2, res.stderr
    assert victim.name in res.stderr and "never replaces an input" in res.stderr
    assert f"for scan {rows[0]}/scan" in res.stderr  # who reads it
    assert victim.read_bytes() == before
    assert not list((d / "out").rglob("*_moved.nrrd"))
