"""``--dtype``'s cast (:func:`volwarp_cli.samples.cast_samples`): rounded, clipped to the range.

float32 holds neither 2**31 - 1 nor 2**32 - 1: clipping float32 samples to
int32's range in float32 rounded the bound up to 2**31, and the cast wrapped
3e9 and +inf to -2**31 (uint32: 5e9 to 0), exit 0.
"""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from volwarp_cli.samples import cast_samples

TYPES = ["int8", "uint8", "int16", "uint16", "int32", "uint32"]


def _expected(x: float, dt: str) -> int:
    """The value rounded half to even, then clipped, in exact Python arithmetic."""
    info = np.iinfo(dt)
    if math.isinf(x):
        return info.max if x > 0 else info.min
    return max(info.min, min(info.max, round(x)))


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(allow_nan=False, width=32), min_size=1, max_size=20),
       st.sampled_from(TYPES), st.sampled_from(["float32", "float64"]))
def test_floats_are_rounded_and_clipped_to_the_type_s_range(values, dt, src):
    data = np.array(values, dtype=src)
    out = cast_samples(data, dt)
    assert out.dtype == np.dtype(dt)
    assert out.tolist() == [_expected(float(v), dt) for v in data]


def test_the_ends_of_int32_and_uint32_from_float32():
    data = np.array([3e9, 5e9, 1e10, np.inf, -3e9, -np.inf, 2147483520.0], np.float32)
    assert cast_samples(data, "int32").tolist() == [2**31 - 1] * 4 + [-2**31] * 2 + [2147483520]
    assert cast_samples(data, "uint32").tolist() == [3000000000] + [2**32 - 1] * 3 + [0, 0,
                                                                                     2147483520]


def test_a_cast_written_by_slabs_is_the_whole_s_cast(tmp_path, monkeypatch):
    """Uncompressed outputs cast (and put in their byte order) a slab of planes at a time:
    the bytes of the whole's cast, whatever the slabs, every format that does it."""
    import io

    import pytest

    from volwarp_cli.errors import VolwarpError
    from volwarp_cli.io import common, write_volume
    from volwarp_cli.io.deflate import gzip_bytes, gzip_to
    from volwarp_cli.volume import Volume

    rng = np.random.default_rng(3)
    data = (rng.standard_normal((7, 5, 6)) * 4e4).astype(np.float32)
    data[0, 0, :3] = [np.inf, -np.inf, 2.5]
    for dt in ("int16", "uint8", "float64", "int32"):
        for order in ("little", "big"):
            for name in ("a.nrrd", "b.nhdr", "c.mha", "d.mhd", "e.raw", "f.nii"):
                if name == "f.nii" and order == "big":
                    continue
                whole = tmp_path / f"whole-{dt}-{order}" / name
                whole.parent.mkdir(exist_ok=True)
                write_volume(Volume(cast_samples(data, dt)), whole, byte_order=order)
                monkeypatch.setattr(common, "SLAB_BYTES", 2 * 5 * 6)  # (a plane or two a slab)
                sliced = tmp_path / f"slabs-{dt}-{order}" / name
                sliced.parent.mkdir(exist_ok=True)
                write_volume(Volume(data), sliced, dtype=dt, byte_order=order)
                monkeypatch.undo()
                for a in sorted(whole.parent.iterdir()):
                    assert a.read_bytes() == (sliced.parent / a.name).read_bytes(), (dt, order, a)
    data[6, 4, 5] = np.nan  # (found in the last slab: refused, nothing left)
    with pytest.raises(VolwarpError, match="samples that are NaN cannot be written as int16"):
        write_volume(Volume(data), tmp_path / "n.nrrd", dtype="int16")
    assert not (tmp_path / "n.nrrd").exists()
    big = rng.integers(0, 50, 9 << 20, dtype=np.uint8)  # (over BLOCKS_FROM: by blocks)
    for parts in ((big,), (b"head", big), (b"small",)):
        out = io.BytesIO()
        gzip_to(out, *parts)
        assert out.getvalue() == gzip_bytes(*parts)


def test_clipping_is_said_once_a_run_with_what_lay_beyond(caplog):
    """An int16 CT cast to uint8 came out 0 everywhere without a word (exit 0): clipping is
    now a warning naming the output, the reach and the type's range, once a command's run
    for each type (a morph's frames: one line for all, naming the first); samples within
    the range say nothing. Outside a run (the API), each cast that clips says so."""
    from volwarp_cli.runscope import run_scope

    ct = np.array([-1147.0, -614.0, -700.4], np.float32)
    with caplog.at_level("WARNING", logger="volwarp"), run_scope() as files:
        assert cast_samples(ct, "uint8", what="f_00.nrrd").tolist() == [0, 0, 0]
        # the next block, whose reach widens the run's (said as the run ends: the same
        # words whatever the cut into blocks and threads, the whole's reach)
        cast_samples(np.array([300.0, 2.0], np.float32), "uint8", what="f_00.nrrd")
        cast_samples(ct, "uint8", what="f_01.nrrd")  # (the next frame: one line for both)
        assert cast_samples(np.array([60000, -3], np.int32), "int16", what="o.nrrd").tolist() \
            == [32767, -3]
        assert cast_samples(np.array([0.4, 254.6]), "uint8", what="fits.nrrd").tolist() == [0, 255]
        assert not caplog.records
        files.committed.append("f_00.nrrd")  # (its outputs written: a failed run says none)
    lines = [r.getMessage() for r in caplog.records]
    assert sorted(lines) == [
        "warning: f_00.nrrd: samples as low as -1147 and as high as 300 lie outside uint8's "
        "range [0, 255] and are clipped to it",
        "warning: o.nrrd: samples as high as 60000 lie outside int16's range [-32768, 32767] "
        "and are clipped to it"], lines
    caplog.clear()
    with caplog.at_level("WARNING", logger="volwarp"), run_scope():
        cast_samples(ct, "uint8", what="failed.nrrd")
    assert not caplog.records
    caplog.clear()
    with caplog.at_level("WARNING", logger="volwarp"):  # (no run: a script's calls)
        cast_samples(ct, "uint8", what="a")
        cast_samples(ct, "uint8", what="b")
    assert [r.getMessage()[:12] for r in caplog.records] == ["warning: a: ", "warning: b: "]


def test_a_field_of_fractions_rounded_to_a_few_integers_is_said(caplog, run, tmp_path):
    """convert --dtype uint8 of a 0..1 density made a binary mask without a word (a
    user-day review; sweep scales its fields first): a cast whose whole output lies fewer
    than FEW_LEVELS integers apart and has fractions says so, once a run, when the run's
    outputs are in place. The reach is the whole output's, over its blocks: a warp's edge
    slab of 0..3 in a 0..255 output said it wrongly in a first version. Whole numbers in
    floats, and a wide field with fractions (a CT as float), say nothing."""
    from volwarp_cli.io import read_volume, write_volume
    from volwarp_cli.runscope import run_files, run_scope
    from volwarp_cli.samples import FEW_LEVELS
    from volwarp_cli.volume import Volume

    density = np.linspace(0, 1, 24, dtype=np.float32).reshape(2, 3, 4)
    edge, body = np.array([0.2, 2.7]), np.array([0.5, 254.6])
    with caplog.at_level("WARNING", logger="volwarp"):
        with run_scope():
            assert set(cast_samples(density, "uint8", what="d.nrrd").ravel()) == {0, 1}
            cast_samples(density, "uint8", what="d.nrrd")  # (the next block)
            cast_samples(np.array([0.0, 3.0, 7.0]), "uint8", what="whole.nrrd")
            cast_samples(np.array([-1000.3, 2000.6]), "int16", what="ct.nrrd")
            cast_samples(np.array([0.5, FEW_LEVELS + 0.25]), "uint8", what="wide.nrrd")
            cast_samples(edge, "uint8", what="warped.nrrd")  # (a first slab: 0..3)
            cast_samples(body, "uint8", what="warped.nrrd")  # (the rest: 0..255)
            run_files().committed.append("d.nrrd")
            assert not caplog.records  # (said when the run ends)
        with run_scope():  # (a run that wrote nothing says nothing)
            cast_samples(density, "uint8", what="d.nrrd")
        cast_samples(density, "int8", what="api")  # (outside a run: at once)
    assert [r.getMessage() for r in caplog.records] == [
        "warning: d.nrrd: samples with fractions became 2 integer values (0 to 1) as uint8: "
        "their fractions were rounded away (a 0..1 field becomes 0 and 1); keep a float "
        "type, or scale them first",
        "warning: api: samples with fractions became 2 integer values (0 to 1) as int8: "
        "their fractions were rounded away (a 0..1 field becomes 0 and 1); keep a float "
        "type, or scale them first"]
    src = tmp_path / "dens.nrrd"
    write_volume(Volume(density), src)
    res = run("convert", src, "-o", tmp_path / "d8.nrrd", "--dtype", "uint8")
    assert res.code == 0 and res.stderr.count("fractions were rounded away") == 1
    assert read_volume(tmp_path / "d8.nrrd").data.max() == 1


def test_float64_beyond_float32_is_refused_not_made_infinite():
    """float64 samples of 1e300 cast to float32 became +inf (59 of 60, exit 0; only `info`
    counted them afterwards): refused, naming the largest; infinities already there and
    values within float32's range are kept."""
    import pytest

    from volwarp_cli.errors import VolwarpError

    with pytest.raises(VolwarpError, match=r"big.nrrd: samples as large as 1e\+300 \(2 of them\) "
                                           "do not fit float32"):
        cast_samples(np.array([1e300, -1e300, 1.0]), "float32", what="big.nrrd")
    out = cast_samples(np.array([np.inf, -np.inf, 3e38, 1.5]), "float32")
    assert out.dtype == np.float32 and out.tolist()[:2] == [np.inf, -np.inf]
    assert out.tolist()[3] == 1.5 and np.isfinite(out[2])


def test_apply_by_blocks_in_other_processes_names_its_output_once(run, tmp_path):
    """A cast in a block task of another process (the operation pickled without its
    target) names the output: the first version of this warning looked the target up
    there and failed (internal error: KeyError). Said once for all the blocks."""
    from volwarp_cli.io import read_volume, write_volume
    from volwarp_cli.volume import Volume

    z, y, x = np.mgrid[:24, :20, :16]
    # (every block that clips holds 300 and nothing else beyond: the same words from any;
    # a step of ids, which the label rule takes for labels: --values intensity)
    write_volume(Volume(np.where(x < 8, x, 300).astype(np.float32)), tmp_path / "ramp.nrrd")
    (tmp_path / "id.tfm").write_text(
        "#Insight Transform File V1.0\n#Transform 0\nTransform: AffineTransform_double_3_3\n"
        "Parameters: 1 0 0 0 1 0 0 0 1 0 0 0\nFixedParameters: 0 0 0\n")
    r = run("apply", tmp_path / "ramp.nrrd", "-o", tmp_path / "o.nrrd", "-t",
            tmp_path / "id.tfm", "--dtype", "int8", "--values", "intensity", "--chunked",
            "--block", "8",
            "--scheduler", "processes", "--workers", "2")
    assert r.code == 0, r.stderr
    said = [line for line in r.stderr.splitlines() if "clipped" in line]
    assert said == [f"volwarp: warning: {tmp_path / 'o.nrrd'}: samples as high as 300 lie "
                    "outside int8's range [-128, 127] and are clipped to it"], r.stderr
    out = read_volume(tmp_path / "o.nrrd").data
    assert out.max() == 127 and out[:, :, 0].max() == 0


def test_the_same_warnings_whatever_the_blocks_and_the_processes(run, tmp_path):
    """The clipping warning named the reach of the first block (or thread's part) that
    clipped: its words changed with the cut and from run to run (-609, -595, -486 for one
    warp). A worker process's cast notes never came back: "rounded away" went unsaid
    with --scheduler processes. Both are now the whole output's, said once at the end."""
    from volwarp_cli.io import write_volume
    from volwarp_cli.volume import Volume

    z, y, x = np.indices((20, 22, 24), dtype=np.float32)
    r = np.sqrt((x - 11) ** 2 + (y - 10) ** 2 + (z - 9) ** 2)
    src = tmp_path / "mask.nrrd"
    write_volume(Volume((r <= 6).astype(np.float32), spacing=(0.9, 1.1, 1.6)), src)
    ways = ([], ["--chunked", "--block", "3,5,7"],
            ["--chunked", "--block", "5,22,24", "--scheduler", "processes", "--threads", "2"])
    assert run("distance", src, "--iso", "0.5", "-o", tmp_path / "f.nrrd").code == 0
    from volwarp_cli.io import read_volume

    low = float(np.rint(read_volume(tmp_path / "f.nrrd").data.min()))  # (the whole's)
    assert low < -1
    for options, want in ((["--dtype", "uint8"], f"samples as low as {low:g} lie outside uint8"),
                          (["--dtype", "int8", "--max-distance", "1.5"],
                           "became 5 integer values (-2 to 2) as int8")):
        said = set()
        for way in ways:
            res = run("distance", src, "--iso", "0.5", "-o", tmp_path / "d.nrrd", *options, *way)
            assert res.code == 0, res.stderr
            lines = [ln for ln in res.stderr.splitlines() if "warning" in ln]
            assert len(lines) == 1 and want in lines[0], (way, res.stderr)
            said.add(lines[0])
        assert len(said) == 1, said


def test_integers_a_float_type_cannot_hold_are_said(caplog):
    """int32 samples beyond 2**24 cast to float32 were rounded (by up to 64) without a word;
    those the type holds exactly (2**24, 4e9) say nothing, nor do the label ids it holds."""
    from volwarp_cli.errors import BadUsage
    from volwarp_cli.labelmap import refuse_merged_ids

    values = np.array([-2**31, 2**24 + 1, 123456789, 7], np.int32)
    with caplog.at_level("WARNING", logger="volwarp"):
        out = cast_samples(values, "float32", what="ct.nrrd")
        assert out.dtype == np.float32
        worst = int(np.abs(out.astype(np.float64) - values.astype(np.float64)).max())
        assert worst == 3  # (123456789 -> 123456792)
        cast_samples(np.array([2**24, -2**24, 4_000_000_000], np.int64).astype(np.uint32)[:2],
                     "float32", what="exact.nrrd")
        cast_samples(np.array([4_000_000_000], np.uint32), "float32", what="exact2.nrrd")
        cast_samples(values, "float64", what="wide.nrrd")
    assert [r.getMessage() for r in caplog.records] == [
        "warning: ct.nrrd: integer samples beyond +/-16777216 are not all float32 numbers and "
        "were rounded to the nearest, by up to 3; keep an integer type (or float64), or scale "
        "them first"]
    refuse_merged_ids(np.array([0, 4_000_000_000], np.uint32), "float32", "ok.nrrd")
    with pytest.raises(BadUsage, match="label ids 4000000001 "):
        refuse_merged_ids(np.array([0, 4_000_000_000, 4_000_000_001], np.uint32), "float32",
                          "lab.nrrd")


def test_label_ids_a_float_cannot_hold_are_refused_whatever_they_are():
    """(the exact check of float ids: inf and 1e300 overflowed it, a fraction beside 2**25
    passed it)"""
    from volwarp_cli.errors import BadUsage
    from volwarp_cli.labelmap import refuse_merged_ids

    for ids, shown in (([0, 1e300], "1.0000000000000001e+300"), ([0, np.inf], "inf"),
                       ([0, 2**25, 2**25 + 0.5], "33554432.5")):
        with pytest.raises(BadUsage, match=re.escape(f"label ids {shown} ")):
            refuse_merged_ids(np.array(ids), "float32", "lab.nrrd")
