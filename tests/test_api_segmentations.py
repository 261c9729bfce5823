"""api.read's segmentation options (``reference``, ``segment``, ``structure``) are the commands'.

What ``api.read`` returns, written with ``api.write``, is ``volwarp convert``'s
file byte for byte (a BINARY SEG whole, on its reference's grid and one segment
of it; an RTSTRUCT whole and one ROI), and the values are the label map the SEG
and RTSTRUCT were made from; every misuse is the command's one error, with its
exit code's class (``BadUsage``: exit 2; another ``VolwarpError``: exit 1) and
the command's message, word for word. The options reach the other functions too
(``api.distance`` of one segment is ``volwarp distance --segment``'s file), and
the reference series is an input of the run: ``api.write`` refuses to write into it.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pydicom")
pytest.importorskip("highdicom")

from test_dicom_seg import labels_fixture, make_seg, masks_of, write_ct  # noqa: E402
from test_rtstruct import square, world, write_rtstruct  # noqa: E402

from volwarp_cli import api  # noqa: E402
from volwarp_cli.errors import BadUsage, VolwarpError  # noqa: E402
from volwarp_cli.io.dicom import read_dicom  # noqa: E402
from volwarp_cli.runscope import run_scope  # noqa: E402

RS_SHAPE = (5, 14, 16)  # z, y, x


@pytest.fixture(autouse=True)
def _own_run():
    with run_scope():
        yield


@pytest.fixture
def case(tmp_path):
    """A BINARY SEG of :func:`labels_fixture` and an RTSTRUCT of two ROIs, each on its series."""
    seg_ct = tmp_path / "seg_ct"
    seg = make_seg(write_ct(seg_ct), masks_of(labels_fixture()), "BINARY", tmp_path / "seg.dcm")
    rs_ct = tmp_path / "rs_ct"
    paths = write_ct(rs_ct, RS_SHAPE, spacing=(0.9, 0.6, 2.0))
    vol = read_dicom(rs_ct)
    rs = write_rtstruct(tmp_path / "rs.dcm", paths, {
        3: ("liver", [("CLOSED_PLANAR", world(vol, k, square(2.5, 2.5, 8.5, 9.5)))
                      for k in (1, 2, 3)]),
        7: ("PTV", [("CLOSED_PLANAR", world(vol, k, square(10.5, 3.5, 13.5, 7.5)))
                    for k in (2, 3)])})
    rs_map = np.zeros(RS_SHAPE, np.uint8)  # the two ROIs' voxels, by hand
    rs_map[1:4, 3:10, 3:9] = 3
    rs_map[2:4, 4:8, 11:14] = 7
    return {"seg": seg, "seg_ct": seg_ct, "rs": rs, "rs_ct": rs_ct, "rs_map": rs_map,
            "tmp": tmp_path}


def _same_bytes(a: Path, b: Path) -> None:
    assert a.read_bytes() == b.read_bytes(), (a, b)


@pytest.mark.parametrize("which, options, kwargs", [
    ("seg", [], {}),
    ("seg", ["--segment", "2"], {"segment": 2}),
    ("seg", ["--reference", "{seg_ct}", "--segment", "3"], {"reference": "seg_ct", "segment": 3}),
    ("rs", ["--reference", "{rs_ct}"], {"reference": "rs_ct"}),
    ("rs", ["--reference", "{rs_ct}", "--structure", "PTV"],
     {"reference": "rs_ct", "structure": "PTV"}),
], ids=["seg", "seg-segment", "seg-on-reference", "rtstruct", "rtstruct-structure"])
def test_read_is_the_convert_command_s_file(case, run, which, options, kwargs):
    tmp = case["tmp"]
    cli, mine = tmp / "cli.nrrd", tmp / "api.nrrd"
    argv = [str(o).format(**case) for o in options]
    res = run("convert", case[which], *argv, "-o", cli)
    assert res.code == 0, res.stderr
    kwargs = {k: (case[v] if k == "reference" else v) for k, v in kwargs.items()}
    vol = api.read(case[which], **kwargs)
    api.write(vol, mine)
    _same_bytes(cli, mine)
    # and the values are what the file was made from (not only the same as the command's)
    if which == "seg":
        lab = labels_fixture()
        n = kwargs.get("segment")
        want = lab if n is None else (lab == n).astype(np.uint8)
        if "reference" not in kwargs:  # the SEG's own grid: its frames' slices, 1 to 4
            want = want[1:5]
        np.testing.assert_array_equal(vol.data, want)
    else:
        want = case["rs_map"]
        if "structure" in kwargs:
            want = (want == 7).astype(np.uint8)
        np.testing.assert_array_equal(vol.data, want)


@pytest.mark.parametrize("which, options, kwargs, exit_code", [
    # an RTSTRUCT has no pixels: it needs the series it was drawn on
    ("rs", [], {}, 2),
    ("rs", ["--structure", "liver"], {"structure": "liver"}, 2),
    # a name no ROI has
    ("rs", ["--reference", "{rs_ct}", "--structure", "nope"],
     {"reference": "rs_ct", "structure": "nope"}, 2),
    # the options of the other kind of segmentation
    ("rs", ["--reference", "{rs_ct}", "--segment", "1"], {"reference": "rs_ct", "segment": 1}, 2),
    ("seg", ["--structure", "organ 1"], {"structure": "organ 1"}, 2),
    # a segment the SEG does not have
    ("seg", ["--segment", "9"], {"segment": 9}, 2),
    # the reference of an image series, of a file that is not DICOM
    ("seg_ct", ["--reference", "{seg_ct}"], {"reference": "seg_ct"}, 2),
    ("nrrd", ["--reference", "{seg_ct}"], {"reference": "seg_ct"}, 2),
    # an RTSTRUCT on a series that is not the one it was drawn on
    ("rs", ["--reference", "{seg_ct}"], {"reference": "seg_ct"}, 1),
    # how the reference is read, without a reference
    ("seg", ["--duplicates", "first"], {"duplicates": "first"}, 2),
], ids=["no-reference", "structure-no-reference", "no-such-roi", "segment-of-rtstruct",
        "structure-of-seg", "no-such-segment", "image-series", "not-dicom", "other-series",
        "duplicates-without-reference"])
def test_errors_are_the_command_s(case, run, which, options, kwargs, exit_code):
    tmp = case["tmp"]
    if which == "nrrd":
        api.write(api.read(case["seg"]), tmp / "lab.nrrd")
        case = {**case, "nrrd": tmp / "lab.nrrd"}
    out = tmp / "x.nrrd"
    argv = [str(o).format(**case) for o in options]
    res = run("convert", case[which], *argv, "-o", out)
    assert res.code == exit_code, res.stderr
    assert res.stderr.count("\n") == 1 and res.stderr.startswith("volwarp: error: ")
    message = res.stderr[len("volwarp: error: "):].strip()
    message = re.sub(r" \(see '\S+ convert --help'\)$", "", message)  # (click's usage hint)
    kwargs = {k: (case[v] if k == "reference" else v) for k, v in kwargs.items()}
    with pytest.raises(VolwarpError) as err:
        api.read(case[which], **kwargs)
    assert isinstance(err.value, BadUsage) == (exit_code == 2)
    assert " ".join(str(err.value).split()) == message
    assert not out.exists()


@pytest.mark.parametrize("kwargs, clicks", [
    ({"segment": 0}, ["--segment", "0"]),
    ({"segment": 1.5}, ["--segment", "1.5"]),
    ({"segment": True}, None),
    ({"structure": 3}, None),
    ({"reference": 3}, None),
])
def test_values_the_command_line_refuses_are_usage_errors(case, run, kwargs, clicks):
    with pytest.raises(BadUsage, match=next(iter(kwargs))):
        api.read(case["seg"], **kwargs)
    if clicks:  # (click refuses them before the command runs: exit 2 too)
        assert run("convert", case["seg"], *clicks, "-o", case["tmp"] / "x.nrrd").code == 2


def test_options_reach_every_function_taking_a_path(case, run):
    tmp = case["tmp"]
    cli, mine = tmp / "cli.nrrd", tmp / "api.nrrd"
    res = run("distance", case["seg"], "--segment", "2", "-o", cli)
    assert res.code == 0, res.stderr
    api.write(api.distance(case["seg"], segment=2), mine)
    _same_bytes(cli, mine)
    # an RTSTRUCT's ROI meshed from its path: the surface of the same mask read first
    a = api.mesh(case["rs"], reference=case["rs_ct"], structure="liver", iso=0.5)
    b = api.mesh(api.read(case["rs"], reference=case["rs_ct"], structure="liver"), iso=0.5)
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.faces, b.faces)


def test_the_reference_series_is_an_input_of_the_run(case):
    vol = api.read(case["rs"], reference=case["rs_ct"])
    with pytest.raises(BadUsage, match="never replaces an input"):
        api.write(vol, case["rs_ct"] / "labels.nrrd")
    assert not (case["rs_ct"] / "labels.nrrd").exists()
