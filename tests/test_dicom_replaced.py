"""A DICOM series changed after its headers were read: refused, never a mix.

A series' pixels are read after its headers are scanned, by the offsets and
the slice order the scan found: at once for a whole read, slab by slab as the
work goes for a lazy one (a command by blocks, a warp streaming its input). A
series exported again into its folder meanwhile (a PACS push, a script
rewriting the folder) gave the new files' pixels as the old slices: a volume
mixing two series, written with exit 0. Each file's pixels now come from the
file whose header was scanned (:func:`volwarp_cli.io.dicom._pixels.open_unchanged`),
whatever the change: copied over in place, renamed in, rewritten with its
modification time put back. A change of its metadata alone (a chmod) is not
one.
"""

from __future__ import annotations

import os
import shutil

import numpy as np
import pytest
from changed_input import change_after_first_read, distance_by_blocks_refused
from test_io_dicom import write_series

from volwarp_cli.errors import FormatError
from volwarp_cli.io.dicom import _read, read_dicom
from volwarp_cli.io.dicom._read import open_dicom_lazy

SHAPE = (24, 12, 10)
OTHER_SERIES = "1.2.826.0.1.3680043.8.498.7"


def _stored(seed: int) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 3000, size=SHAPE).astype(np.int16)


@pytest.fixture
def folders(tmp_path):
    """``(A, B)``: series A (read) and B (the same layout, other pixels and UIDs), same names."""
    a = tmp_path / "A"
    b = tmp_path / "B"
    write_series(a, _stored(0), shuffle=False)
    write_series(b, _stored(1), shuffle=False, series=OTHER_SERIES)
    return a, b


def _copied_over(src, dst) -> None:  # (cp: the same file, its bytes rewritten)
    shutil.copyfile(src, dst)


def _renamed_in(src, dst) -> None:  # (a writer's temporary renamed over it: another file)
    tmp = f"{dst}.part"
    shutil.copyfile(src, tmp)
    os.replace(tmp, dst)


def _rewritten_time_kept(src, dst) -> None:
    """Another image written over it in place, its size and modification time kept (cp,
    then touch -r): ``dst``'s bytes with ``src``'s pixels and another SOP Instance UID."""
    import pydicom

    st = os.stat(dst)
    data = bytearray(dst.read_bytes())
    pixels = len(pydicom.dcmread(src).PixelData)
    data[-pixels:] = src.read_bytes()[-pixels:]
    uid = pydicom.dcmread(dst).SOPInstanceUID.encode()
    at = data.index(uid)
    data[at + len(uid) - 1] = ord("1") if uid[-1:] != b"1" else ord("2")
    with open(dst, "r+b") as fh:
        fh.write(data)
    assert os.stat(dst).st_size == st.st_size
    os.utime(dst, ns=(st.st_atime_ns, st.st_mtime_ns))


CHANGES = [_copied_over, _renamed_in, _rewritten_time_kept]


def _export_again(a, b, change) -> None:
    for f in sorted(b.iterdir()):
        change(f, a / f.name)


@pytest.mark.parametrize("change", CHANGES, ids=lambda c: c.__name__.strip("_"))
def test_a_lazy_stack_refuses_slices_of_files_changed_after_the_scan(folders, change):
    """Before: the slabs read after the change were B's pixels, as A's slices."""
    a, b = folders
    _, lazy = open_dicom_lazy(a)
    first = lazy[0:4]
    assert np.array_equal(first, _stored(0)[0:4])
    _export_again(a, b, change)
    with pytest.raises(FormatError, match=r"IM00\d\d\.dcm: the file changed after its header "
                                          r"was read \(replaced or rewritten"):
        lazy[4:8]


def test_a_whole_read_refuses_files_changed_between_the_scan_and_the_pixels(folders,
                                                                            monkeypatch):
    """The window of a whole read is shorter, but the same: headers first, pixels after."""
    a, b = folders
    real = _read.read_frames

    def exported_meanwhile(*args):
        _export_again(a, b, _copied_over)
        return real(*args)

    monkeypatch.setattr(_read, "read_frames", exported_meanwhile)
    with pytest.raises(FormatError, match="the file changed after its header was read"):
        read_dicom(a)


def test_metadata_changes_alone_are_not_a_change(folders):
    """A chmod, a hard link (the change time moves, the bytes do not): read as before."""
    a, _ = folders
    _, lazy = open_dicom_lazy(a)
    names = sorted(a.iterdir())
    for f in names[::2]:
        os.chmod(f, 0o600)
    os.link(names[1], a.parent / "link.dcm")
    assert np.array_equal(np.asarray(lazy), _stored(0))


def test_a_command_by_blocks_writes_nothing_from_a_series_changed_meanwhile(run, folders,
                                                                          tmp_path,
                                                                          monkeypatch):
    """The hunt's case: a distance by blocks, the folder exported again after the first
    slab. Before: exit 0 and a field of A's first slices and B's others."""
    a, b = folders
    out = tmp_path / "d.nrrd"
    out.write_bytes(b"old output")
    slabs = change_after_first_read(monkeypatch, _read.LazyDicom,
                                    lambda: _export_again(a, b, _renamed_in))
    distance_by_blocks_refused(run, a, out, tmp_path, slabs,
                               "the file changed after its header was read", ["A", "B", "d.nrrd"])
