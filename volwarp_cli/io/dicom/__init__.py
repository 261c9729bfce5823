"""DICOM input: a folder of slices, a DICOMDIR, or one (multi-frame) file, read as a Volume.

The world frame is DICOM's patient frame, LPS, so positions and cosines are
taken as they are. Geometry matches SimpleITK's ``ImageSeriesReader`` (ITK +
GDCM) wherever ITK is right; the rules, and why:

Finding files
    A folder is searched recursively; files without the ``DICM`` preamble
    (README, thumbnails) are skipped, and so are DICOMDIR files (Media Storage
    Directory). A DICOMDIR given as the path is read with pydicom and only the
    files its records reference are used. One file without the preamble is
    read when it is named explicitly and ends in ``.dcm`` (old files). A
    folder whose newest file is younger than a few seconds is read with a
    warning (once a run): a series still being stored would be read short,
    and nothing in it says so (``volwarp batch`` waits for it: ``inputs.settle``).

Candidates (:func:`scan_dicom`)
    A file that is an exact copy of another (the same SOPInstanceUID, frames
    and pixel data, as ``cp`` leaves it) is one image stored twice: dropped
    (the first in path order kept) with one warning saying how many.
    Images are grouped by SeriesInstanceUID, and a series is split where its
    geometry differs: FrameOfReferenceUID, ImageOrientationPatient, Rows /
    Columns, PixelSpacing, EchoNumbers; and, when a stack has several images
    at one position, by TemporalPositionIdentifier or AcquisitionNumber when
    that gives whole stacks at the same positions, one image per position
    (time points, repeated acquisitions). Any other split would cut one
    volume into partial ones (a re-acquired slice; scanners giving every
    slice its own AcquisitionNumber): its images at one position are
    duplicates, resolved by ``duplicates`` below.
    Localizer images (ImageType ``LOCALIZER``) in another orientation than the
    series' main stack are dropped, and the main stack's ``why`` says so.
    Every other split part is a candidate of its own with ``why`` saying why.
    When a path holds several candidates the caller must choose one
    (``series=`` a SeriesInstanceUID or a 0-based index): volwarp never picks
    the first silently (:class:`DicomSeriesChoiceError`).
    Enhanced multi-frame files (and any file with per-frame functional groups,
    one frame too: a Legacy Converted Enhanced MR or PET of one slice has its
    geometry and rescale only there) give one frame record per frame from the per-frame groups
    (PlanePosition, PlaneOrientation, PixelMeasures, PixelValueTransformation,
    the shared groups as fallback); different orientations, StackIDs, temporal
    positions or segments are different candidates. RT Dose frames lie at
    GridFrameOffsetVector: distances along the normal from ImagePositionPatient
    when the first offset is 0, else the frames' z coordinates (PS3.3
    C.8.8.3.2), frame 0 at ImagePositionPatient: its z must be the first offset
    (within 0.01 mm) and the normal must have a z component, else a FormatError.

Geometry
    Slices are sorted by their position projected on the slice normal (row
    cosine x column cosine), never by InstanceNumber or file name. Direction
    columns are the row cosine (x), the column cosine (y) and the stack
    direction (a row cosine within 1e-4 of square to the column, as rounded
    cosines leave it, made square to it as ITK does); the origin is the first sorted slice's ImagePositionPatient.
    The slice spacing comes from the positions, never from SliceThickness;
    gaps must agree within max(1e-3 * spacing, 0.01 mm), else a FormatError
    names the gap (a multiple of the spacing is reported as missing slices),
    unless ``irregular="resample"``: then the stack is linearly interpolated
    onto a uniform grid of the smallest gap, along the normal, with a warning
    (an extent within that tolerance of a whole number of gaps is that number,
    and a grid slice within 1e-3 gap of an input slice is that slice:
    positions are decimal strings of a few digits).
    Images at one position (exact copies dropped before): an error, or
    ``duplicates="first"``/``"last"`` keeps the first/last of them in file
    order (files sorted by path, frames by frame number), at every position.
    One slice: z spacing is SpacingBetweenSlices, else 1 (what ITK does: it
    ignores SliceThickness). A multi-frame file without per-frame positions (a
    classic NM, MR, CT ...): its frames in file order SpacingBetweenSlices
    apart from ImagePositionPatient along the normal (a negative one: against
    it), as ITK does; an NM file's ImagePositionPatient / Orientation from its
    DetectorInformationSequence first, as GDCM's (the top-level ones, which
    GDCM leaves out for NM, as fallback; detectors placed differently refused).
    Without SpacingBetweenSlices, unit spacing as ITK's (SliceThickness is not
    the spacing), with a warning; whatever the file leaves out and volwarp
    assumed (that spacing, origin 0, identity orientation, 1 mm pixels where
    neither PixelSpacing nor ImagerPixelSpacing is given, as ITK takes them:
    with a warning too) is said in the key ``DICOM_geometry``. A gantry-tilted stack (slice
    origins moving in-plane along the stack) is by default resampled onto the
    orthogonal grid that has the normal as third axis, slice by slice in the
    slice planes (bilinear = trilinear with integer z), out-of-field voxels
    set to the volume's minimum (a voxel is interpolated from samples of the
    field only, or is that fill; a slice's shift within 1e-3 pixel of whole
    pixels is whole: its edge column stays in the field), with the tilt angle logged; ``keep_shear``
    returns the exact sheared geometry instead (third direction column the
    unit vector between successive slice origins, as ITK does).

Values
    Modality rescale per slice: the output is the stored type when every slope
    is 1 and intercept 0, else int16 or int32 when every slope and intercept is
    an integer and the whole stored range (BitsStored, PixelRepresentation)
    maps into the type, else float32; computed in int64/float64 first. RT Dose
    is ``stored * DoseGridScaling`` as float32 (SimpleITK leaves it unscaled),
    in the file's DoseUnits (``GY``, or ``RELATIVE`` to a reference dose: never
    taken for Gy), kept as ``DICOM_DoseUnits``.
    Resampled volumes (tilt, irregular) are float32. Colour images are refused,
    PALETTE COLOR too (one sample per pixel, but an index into colour tables).
    The grid's spacing, origin and direction obey
    :func:`volwarp_cli.geometry.check_placement` (a refusal names the tag).

Meta
    ``DICOM_<Keyword>`` for Modality, SeriesDescription, PatientPosition,
    StudyInstanceUID, SeriesInstanceUID, FrameOfReferenceUID, SeriesNumber,
    (RT Dose) DoseUnits, DoseType, DoseSummationType. Identifying tags
    (PatientName, PatientID, PatientBirthDate, ...) only with ``keep_phi``.
    ``DICOM_geometry``: what of the grid the file does not give (above).

Segmentations
    A SEG file (BINARY, FRACTIONAL, LABELMAP) or an RTSTRUCT file is read as a
    label map (:mod:`volwarp_cli.io.dicom_seg`, :mod:`volwarp_cli.io.rtstruct`):
    an RTSTRUCT on the grid of the image series given as ``reference``, a SEG
    on its own frames' grid or on the reference's.

Pixel data is read once per file, after the header scan, into one
preallocated array: uncompressed little-endian files straight from disk,
everything else through pydicom's decoders (gdcm, pylibjpeg-openjpeg,
pylibjpeg-rle); Deflated Explicit VR Little Endian files are inflated by
pydicom's ``dcmread`` first.
"""

from __future__ import annotations

from ._read import ReferenceSeries, read_dicom, read_reference, segmentation_kind
from ._scan import Candidate, DicomSeriesChoiceError, is_dicom_path, scan_dicom

__all__ = ["Candidate", "DicomSeriesChoiceError", "ReferenceSeries", "is_dicom_path",
           "read_dicom", "read_reference", "scan_dicom", "segmentation_kind"]
