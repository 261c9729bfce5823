"""Segment and ROI descriptions as a label map's key/values, and back.

A SEG or RTSTRUCT read as a label map (:func:`seg_keys`, :func:`roi_keys`)
records what each label is in the volume's key/values, which every command
keeps; a SEG or RTSTRUCT written from a map (:func:`label_descriptions`) takes
each label's name, colour and codes from them. ``N`` is the label's value in
the map: the segment number (a SEG), the ROI Number (an RTSTRUCT), or 1 for a
``--segment N`` / ``--structure NAME`` mask.

=================================  ===========================================
key                                value
=================================  ===========================================
``DICOM_Segment_N_Label``          SegmentLabel
``DICOM_Segment_N_Category``       SegmentedPropertyCategoryCode: ``scheme^value^meaning``
``DICOM_Segment_N_Type``           SegmentedPropertyTypeCode: ``scheme^value^meaning``
``DICOM_Segment_N_CIELab``         RecommendedDisplayCIELabValue: ``L a b``, each 0..65535
``DICOM_Segment_N_Algorithm``      SegmentAlgorithmType (MANUAL, SEMIAUTOMATIC, AUTOMATIC)
``DICOM_Segment_N_AlgorithmName``  the algorithm's name, ``..._AlgorithmVersion`` its
                                   version, ``..._AlgorithmFamily`` its family
                                   (``scheme^value^meaning``)
``DICOM_ROI_N``                    ROIName
``DICOM_ROI_N_Color``              ROIDisplayColor: ``R G B``, each 0..255
``DICOM_ROI_nested``               ROIs lying inside others: ``2 in 1; 5 in 3``
                                   (inner and outer labels; the map holds the
                                   inner ROI's voxels, the outer one the rest)
=================================  ===========================================

Writing, for each label: a name from ``--segments``, else from these keys (a
SEG: the segment's label, else the ROI's name; an RTSTRUCT the other way
round), else the default; a colour from the keys (converted between CIELab and
RGB with highdicom's :class:`~highdicom.color.CIELabColor` when the map came
from the other kind), else the default (a SEG: none; an RTSTRUCT: volwarp's
made-up colour); a SEG's codes and algorithm from the keys, else SCT Tissue /
Tissue, MANUAL. A key that cannot be parsed is an error naming it. An outer
ROI of ``DICOM_ROI_nested`` is written whole (:func:`nested_labels`): its
voxels and those of the labels inside it.
"""

from __future__ import annotations

from dataclasses import dataclass

from ..errors import VolwarpError

SEG_PREFIX = "DICOM_Segment_"
ROI_PREFIX = "DICOM_ROI_"
#: the key listing the ROIs that lie inside others (:func:`nested_keys`)
NESTED_KEY = "DICOM_ROI_nested"

Code3 = tuple[str, str, str]  # (scheme, value, meaning)


@dataclass(frozen=True)
class LabelDescription:
    """What the key/values say of one label (None: nothing)."""

    seg_label: str | None = None
    roi_name: str | None = None
    cielab: tuple[int, int, int] | None = None
    rgb: tuple[int, int, int] | None = None
    category: Code3 | None = None
    type: Code3 | None = None
    algorithm: str | None = None
    algorithm_name: str | None = None
    algorithm_version: str | None = None
    algorithm_family: Code3 | None = None

    def __bool__(self) -> bool:
        return any(v is not None for v in self.__dict__.values())


# -- reading: a SEG's or an RTSTRUCT's descriptions as key/values --------------------------

def _code_text(seq) -> str | None:
    if not seq:
        return None
    item = seq[0]
    value = item.get("CodeValue") or item.get("LongCodeValue") or item.get("URNCodeValue")
    if value in (None, ""):
        return None
    return f"{item.get('CodingSchemeDesignator', '')}^{value}^{item.get('CodeMeaning', '')}"


def _ints(values, top: int) -> tuple[int, ...] | None:
    try:
        out = tuple(int(v) for v in values)
    except (TypeError, ValueError):
        return None
    return out if len(out) == 3 and all(0 <= v <= top for v in out) else None


def seg_keys(ds, segment: int | None = None) -> dict[str, str]:
    """The key/values describing a SEG's segments (``segment``: only that one, as label 1)."""
    meta: dict[str, str] = {}
    for item in ds.get("SegmentSequence", []):
        number = int(item.SegmentNumber)
        if (segment is not None and number != segment) or number == 0:
            continue  # (a LABELMAP SEG's segment 0 is its background, no label)
        key = f"{SEG_PREFIX}{1 if segment is not None else number}_"
        if item.get("SegmentLabel") not in (None, ""):
            meta[key + "Label"] = str(item.SegmentLabel)
        for name, seq in (("Category", "SegmentedPropertyCategoryCodeSequence"),
                          ("Type", "SegmentedPropertyTypeCodeSequence")):
            text = _code_text(item.get(seq))
            if text is not None:
                meta[key + name] = text
        lab = _ints(item.get("RecommendedDisplayCIELabValue") or (), 0xFFFF)
        if lab is not None:
            meta[key + "CIELab"] = " ".join(map(str, lab))
        if item.get("SegmentAlgorithmType") not in (None, ""):
            meta[key + "Algorithm"] = str(item.SegmentAlgorithmType)
        ident = (item.get("SegmentationAlgorithmIdentificationSequence") or [None])[0]
        name = (ident.get("AlgorithmName") if ident is not None else None) or \
            item.get("SegmentAlgorithmName")
        if name not in (None, ""):
            meta[key + "AlgorithmName"] = str(name)
        if ident is not None:
            if ident.get("AlgorithmVersion") not in (None, ""):
                meta[key + "AlgorithmVersion"] = str(ident.AlgorithmVersion)
            family = _code_text(ident.get("AlgorithmFamilyCodeSequence"))
            if family is not None:
                meta[key + "AlgorithmFamily"] = family
    return meta


def roi_colours(ds) -> dict[int, tuple[int, int, int]]:
    """{ROI Number: ROIDisplayColor} of an RTSTRUCT's ROIs that have a valid one."""
    out = {}
    for c in ds.get("ROIContourSequence", []):
        rgb = _ints(c.get("ROIDisplayColor") or (), 255)
        if rgb is not None and "ReferencedROINumber" in c:
            out[int(c.ReferencedROINumber)] = rgb
    return out


def roi_keys(names: dict[int, str], colours: dict[int, tuple[int, int, int]]) -> dict[str, str]:
    """``DICOM_ROI_N`` (the name) and ``DICOM_ROI_N_Color`` (``R G B``) of each ROI."""
    meta = {f"{ROI_PREFIX}{n}": name for n, name in names.items()}
    meta.update({f"{ROI_PREFIX}{n}_Color": " ".join(map(str, rgb))
                 for n, rgb in colours.items() if n in names})
    return meta


def nested_keys(pairs: list[tuple[int, int]]) -> dict[str, str]:
    """``DICOM_ROI_nested`` of the pairs ``(inner, outer)`` (none: no key)."""
    return {NESTED_KEY: "; ".join(f"{a} in {b}" for a, b in pairs)} if pairs else {}


# -- writing: each label's description from the key/values ---------------------------------

def nested_labels(meta: dict, values, source: str) -> dict[int, list[int]]:
    """{outer label: every label of ``values`` inside it, however deep} from ``DICOM_ROI_nested``.

    A map read from an RTSTRUCT gives a voxel to the smallest ROI holding it, so
    an outer ROI's own mask is its label's voxels and those of the labels
    nested in it: written back without them, it has their holes.
    """
    text = str(meta.get(NESTED_KEY) or "").strip()
    if not text:
        return {}
    inside: dict[int, set[int]] = {}
    for part in filter(None, (p.strip() for p in text.split(";"))):
        words = part.split()
        if len(words) != 3 or words[1] != "in" or not all(
                w.lstrip("-").isdigit() for w in words[::2]):
            raise VolwarpError(f"{source}: key/value {NESTED_KEY}={text!r} does not say "
                               "which labels lie in which: want 'INNER in OUTER' pairs of "
                               "labels separated by ';' (docs/segmentations.md)")
        inside.setdefault(int(words[2]), set()).add(int(words[0]))
    present = {int(v) for v in values}
    out = {}
    for outer in sorted(inside.keys() & present):
        seen, todo = set(), list(inside[outer])
        while todo:  # (every depth: GTV in CTV in PTV)
            label = todo.pop()
            if label not in seen and label != outer:
                seen.add(label)
                todo.extend(inside.get(label, ()))
        if seen & present:
            out[outer] = sorted(seen & present)
    return out



def _bad(source: str, key: str, value: str, want: str) -> VolwarpError:
    return VolwarpError(f"{source}: key/value {key}={value!r} does not describe a segment: "
                        f"want {want} (docs/segmentations.md)")


def _parse_code(source: str, key: str, value: str) -> Code3 | None:
    """``scheme^value^meaning``; None (the default code) where a SEG read left a part empty.

    SEGs in the wild break the standard's limits (an 81-character meaning, an
    empty one) and read fine: such a code, read by volwarp, must not stop the
    map from being written back. A meaning over DICOM's 64 characters is cut
    there, an empty part gives the default code; either is said.
    """
    from ..progress import log

    parts = [p.strip() for p in value.split("^", 2)]
    if len(parts) != 3:
        raise _bad(source, key, value, "scheme^value^meaning")
    if not all(parts):
        log.warning("warning: %s: %s = %r has an empty part: the default code is written",
                    source, key, value)
        return None
    if len(parts[2]) > 64:
        log.warning("warning: %s: %s's meaning is over DICOM's 64 characters: cut there",
                    source, key)
        parts[2] = parts[2][:64].rstrip()
    return parts[0], parts[1], parts[2]


def _parse_triple(source: str, key: str, value: str, top: int, what: str) -> tuple[int, int, int]:
    out = _ints(value.split(), top) if value.replace(" ", "").isdigit() else None
    if out is None:
        raise _bad(source, key, value, f"three whole numbers 0..{top} ({what})")
    return out  # type: ignore[return-value]


def label_descriptions(meta: dict, values, source: str) -> dict[int, LabelDescription]:
    """{label: what the key/values ``meta`` say of it} for the labels ``values``."""
    out = {}
    for v in (int(x) for x in values):
        s, r = f"{SEG_PREFIX}{v}_", f"{ROI_PREFIX}{v}"

        def get(key):
            value = meta.get(key)
            return None if value is None or not str(value).strip() else str(value).strip()
        kw: dict = {"seg_label": get(s + "Label"), "roi_name": get(r)}
        for name, key in (("category", "Category"), ("type", "Type"),
                          ("algorithm_family", "AlgorithmFamily")):
            if get(s + key) is not None:
                kw[name] = _parse_code(source, s + key, get(s + key))
        if get(s + "CIELab") is not None:
            kw["cielab"] = _parse_triple(source, s + "CIELab", get(s + "CIELab"), 0xFFFF,
                                         "DICOM's CIELab")
        if get(r + "_Color") is not None:
            kw["rgb"] = _parse_triple(source, r + "_Color", get(r + "_Color"), 255, "RGB")
        algorithm = get(s + "Algorithm")
        if algorithm is not None:
            if algorithm.upper() not in ("MANUAL", "SEMIAUTOMATIC", "AUTOMATIC"):
                raise _bad(source, s + "Algorithm", algorithm,
                           "MANUAL, SEMIAUTOMATIC or AUTOMATIC")
            kw["algorithm"] = algorithm.upper()
        kw["algorithm_name"] = get(s + "AlgorithmName")
        kw["algorithm_version"] = get(s + "AlgorithmVersion")
        d = LabelDescription(**kw)
        if d:
            out[v] = d
    return out


def seg_colour(d: LabelDescription | None):
    """The segment's highdicom CIELabColor (from the SEG's key, else the ROI's RGB), or None."""
    import highdicom as hd

    if d is None:
        return None
    if d.cielab is not None:
        return hd.color.CIELabColor.from_dicom_value(d.cielab)
    if d.rgb is not None:
        return hd.color.CIELabColor.from_rgb(*d.rgb)
    return None


def roi_colour(d: LabelDescription | None) -> tuple[int, int, int] | None:
    """The ROI's RGB colour (from the ROI's key, else the SEG's CIELab), or None."""
    if d is None:
        return None
    if d.rgb is not None:
        return d.rgb
    if d.cielab is not None:
        import highdicom as hd

        return tuple(int(c) for c in hd.color.CIELabColor.from_dicom_value(d.cielab).to_rgb())
    return None


def seg_algorithm(d: LabelDescription | None):
    """``(algorithm type, highdicom AlgorithmIdentificationSequence or None)`` of a segment.

    A type other than MANUAL needs the algorithm's name, family and version (the
    standard's Type 1C); without all three the segment is written MANUAL, as a
    map without keys is.
    """
    if d is None or d.algorithm in (None, "MANUAL"):
        return "MANUAL", None
    if d.algorithm_name is None or d.algorithm_family is None or d.algorithm_version is None:
        return "MANUAL", None
    import highdicom as hd

    family = hd.sr.CodedConcept(d.algorithm_family[1], d.algorithm_family[0],
                                d.algorithm_family[2])
    return d.algorithm, hd.AlgorithmIdentificationSequence(
        name=d.algorithm_name[:64], family=family, version=d.algorithm_version[:64])
