"""Files as common tools write them, read as before today's stricter readers.

Reference: SimpleITK (teem's NrrdIO inside ITK) for the placement and the samples.
"""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk

from volwarp_cli.errors import FormatError
from volwarp_cli.io import read_volume
from volwarp_cli.io.lazy import open_volume_lazy

# A volume sequence as 3D Slicer writes it (.seq.nrrd, the ITK NRRD writer of Slicer 5.10:
# per-axis metadata for every axis, the time axis' unit among them): 2 frames of 4 x 3 x 2
SEQ_DATA = np.arange(2 * 3 * 4 * 2, dtype=np.int16).reshape(2, 3, 4, 2)  # z y x list
SEQ_HEAD = """NRRD0004
# Complete NRRD file format specification at:
# http://teem.sourceforge.net/nrrd/format.html
type: short
dimension: 4
space: left-posterior-superior
sizes: 2 4 3 2
space directions: none (-1.95,0,0) (0,-1.95,0) (0,0,2.5)
kinds: list domain domain domain
labels: "time" "" "" ""
{units}endian: little
encoding: raw
space origin: (137.16,36.8,-309.7)
DataNodeClassName:=vtkMRMLScalarVolumeNode
axis 0 index type:=numeric
axis 0 index values:=1.2 1.4

"""


@pytest.mark.parametrize("units", ['units: "s" "" "" ""\n',
                                   "spacings: 0.2 NaN NaN NaN\naxis mins: 1.2 NaN NaN NaN\n"],
                         ids=["units", "spacing-and-min"])
def test_a_sequences_time_axis_unit_is_read_as_teem_reads_it(tmp_path, run, units):
    """teem refuses units, spacings and axis mins only on an axis *with* a direction vector:
    a Slicer sequence's ``units: "s" "" "" ""`` (its list axis, direction ``none``) was
    refused ("'units' beside 'space directions'"), a file ITK and Slicer read."""
    path = tmp_path / "frames.seq.nrrd"
    path.write_bytes(SEQ_HEAD.format(units=units).encode() + SEQ_DATA.tobytes())
    itk = sitk.ReadImage(str(path))
    theirs = sitk.GetArrayFromImage(itk)  # z y x component
    for index in (0, 1):
        vol = read_volume(path, volume_index=index)
        for geo, data in ((vol, vol.data), open_volume_lazy(path, volume_index=index)):
            np.testing.assert_allclose(geo.spacing, itk.GetSpacing())
            np.testing.assert_allclose(geo.origin, itk.GetOrigin())
            np.testing.assert_allclose(np.ravel(geo.direction), itk.GetDirection())
            assert np.array_equal(np.asarray(data[...]), theirs[..., index])
    res = run("info", path, "--volume-index", "1")
    assert res.code == 0, res.stderr


def test_units_on_an_axis_with_a_direction_are_still_refused(tmp_path):
    """The list axis' unit is allowed; a unit on one of the space axes is not (teem's rule)."""
    path = tmp_path / "frames.seq.nrrd"
    path.write_bytes(SEQ_HEAD.format(units='units: "s" "" "cm" ""\n').encode()
                     + SEQ_DATA.tobytes())
    with pytest.raises(FormatError, match="'units' beside 'space directions'"):
        read_volume(path, volume_index=0)
