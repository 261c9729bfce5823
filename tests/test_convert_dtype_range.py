"""Writers, read back by other programs: what an output's header says of its samples."""

from __future__ import annotations

import numpy as np
import pytest

SimpleITK = pytest.importorskip("SimpleITK")


def _header(path) -> dict:
    """A MetaImage header's fields, as MetaIO reads them (``Key = value`` lines)."""
    head = path.read_bytes().split(b"ElementDataFile")[0].decode()
    return dict(line.split(" = ", 1) for line in head.splitlines())


@pytest.fixture
def ranged_mha(tmp_path):
    """An int16 MetaImage of -1000..1000 whose header says so (ElementMin/ElementMax)."""
    data = np.linspace(-1000, 1000, 60).reshape(3, 4, 5).astype(np.int16)
    path = tmp_path / "ranged.mha"
    SimpleITK.WriteImage(SimpleITK.GetImageFromArray(data), str(path))
    path.write_bytes(path.read_bytes().replace(
        b"ElementType", b"ElementMin = -1000\nElementMax = 1000\nElementType", 1))
    return path


def test_a_dtype_cast_leaves_no_stale_element_range(run, ranged_mha, tmp_path):
    """`convert --dtype uint8` clips -1000..1000 to 0..255: a header still saying
    ElementMin = -1000 described samples the file does not hold."""
    out = tmp_path / "u8.mha"
    assert run("convert", ranged_mha, "-o", out, "--dtype", "uint8",
               "--values", "intensity", "-q").code == 0
    samples = SimpleITK.GetArrayFromImage(SimpleITK.ReadImage(str(out)))
    assert samples.dtype == np.uint8
    got = _header(out)
    for key, value in (("ElementMin", samples.min()), ("ElementMax", samples.max())):
        assert key not in got or float(got[key]) == value, (key, got.get(key))


def test_a_convert_without_a_cast_keeps_the_element_range(run, ranged_mha, tmp_path):
    out = tmp_path / "same.mha"
    assert run("convert", ranged_mha, "-o", out, "-q").code == 0
    got = _header(out)
    assert (got["ElementMin"], got["ElementMax"]) == ("-1000", "1000")
