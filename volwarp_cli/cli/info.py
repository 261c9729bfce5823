"""`volwarp info FILE`: format, geometry and statistics of a volume (or capture file)."""

from __future__ import annotations

import json

import click

from ..errors import ChoiceNeeded
from ..io import volume_format
from .common import describe_volume, load_input
from .options import INPUT_PATH, Command, common_options, examples, input_options


def _format_text(d: dict) -> str:
    def vec(v):
        return " ".join(f"{x:g}" for x in v)

    def num(v, fmt):
        return "-" if v is None else format(v, fmt)
    lines = [
        f"format:    {d['format']}",
        f"shape:     {vec(d['shape'])} (x y z)",
        f"dtype:     {d['dtype']}",
        f"spacing:   {vec(d['spacing'])}",
        f"origin:    {vec(d['origin'])}",
        "direction: " + "; ".join(vec(r) for r in d["direction"]),
        f"space:     {d['space'] or '-'}" + (
            f" (the file's own: {d['file_space']}, converted)"
            if d.get("file_space") and d["file_space"] != d["space"] else ""),
        f"min/max:   {num(d['min'], 'g')} / {num(d['max'], 'g')}",
        f"mean:      {num(d['mean'], '.6g')}",
    ]
    if d.get("nonfinite"):
        lines.append(f"nonfinite: {d['nonfinite']} samples (NaN or infinite; not in min/max/mean)")
    for k, v in d["meta"].items():
        lines.append(f"meta:      {k} = {v}")
    for k, v in d.items():
        if k == "label_map":
            vals = " ".join(map(str, v["values"])) + (" ..." if v["labels"] > len(v["values"])
                                                         else "")
            what = f"is {v['why']}" if v.get("why") else "looks like a label map"
            lines.append(f"hint:      {what} ({v['labels']} distinct values: "
                         f"{vals}): warp, distance and mesh take it as labels by default "
                         "(--values intensity to take its samples as intensities); mesh "
                         "--label N or --labels for one label's surface or each one's")
        elif k == "segments":
            lines.append(f"segments:  {len(v)} ({d.get('segmentation_type', '')})")
            lines += _segment_lines(v)
        elif k in ("dicom_type", "segmentation_type", "volume_index"):
            continue
        elif k == "volumes":
            lines.append(f"volumes:   {v} in the file (components, time points or images); shown: "
                         f"volume {d.get('volume_index', 0)} (--volume-index K for another)")
        elif k == "candidates":
            lines.append(f"candidates: {len(v)} volume{'s' if len(v) > 1 else ''} in the input")
        elif k not in ("format", "shape", "dtype", "spacing", "origin", "direction", "space",
                       "file_space", "min", "max", "mean", "meta", "nonfinite"):
            lines.append(f"{k}: {json.dumps(v)}")
    return "\n".join(lines)


@click.command(name="info", cls=Command, epilog=examples(
    "volwarp info head.nii.gz",
    "volwarp info ct_series/ --series 2 --json",
))
@click.argument("file", type=INPUT_PATH)
@click.option("--json", "as_json", is_flag=True,
              help="Print one JSON object (stable keys: format shape dtype spacing origin "
                   "direction space file_space min max mean meta). Geometry is in LPS "
                   "millimetres (space), whatever frame the file used (file_space).")
@input_options
@common_options
def command(file, as_json, raw, volume_index, dicom):
    """Print FILE's format, size (x y z), type, geometry, value range and key/values."""
    if file.lower().endswith(".vwc"):
        if raw is not None or volume_index is not None or dicom is not None:
            raise click.UsageError("--raw-*, --volume-index and the DICOM options describe "
                                   f"volume inputs, not the capture file {file}")
        from ..warp.capture_file import describe_capture
        desc = describe_capture(file)
    elif volume_format(file, reading=True) == "dicom":
        desc = _describe_dicom(file, raw, volume_index, dicom)
    else:
        try:
            vol = load_input(file, raw, volume_index, dicom=dicom)
            count = None
        except ChoiceNeeded:  # (a vector field, a 4-D series: described, not refused)
            count = None if volume_index is not None else _volume_count(file, raw)
            if count is None:
                raise
            vol = load_input(file, raw, 0, dicom=dicom)
        desc = describe_volume(vol, volume_format(file, reading=True))
        if count is not None:
            desc["volumes"] = count
            desc["volume_index"] = 0
        _label_hint(desc, vol)
    if "structures" in desc and "shape" not in desc:  # an RTSTRUCT: no grid of its own
        click.echo(json.dumps(desc, indent=2) if as_json else _structures_text(desc))
    elif desc.get("segments_overlap"):  # a SEG no one label map holds: no grid to show
        click.echo(json.dumps(desc, indent=2) if as_json else _overlap_text(desc))
    elif desc.get("format") == "dicom" and "shape" not in desc:  # several volumes, none chosen
        click.echo(json.dumps(desc, indent=2) if as_json else _candidates_text(desc))
    elif as_json:
        click.echo(json.dumps(desc, indent=2, sort_keys=False, allow_nan=False))
    elif desc.get("format") == "vwc":
        # a capture file: the lattice positions are many numbers; show their extent
        pts = desc.pop("lattice_points")
        flat = [p for plane in pts for row in plane for p in row]
        lo = [min(p[a] for p in flat) for a in range(3)]
        hi = [max(p[a] for p in flat) for a in range(3)]
        click.echo(_format_text(desc))
        for line in _lattice_lines(desc, pts):
            click.echo(line)
        click.echo(f"lattice_points: {len(flat)} points, world x {lo[0]:g}..{hi[0]:g}, "
                   f"y {lo[1]:g}..{hi[1]:g}, z {lo[2]:g}..{hi[2]:g} (all of them: --json)")
    else:
        click.echo(_format_text(desc))


#: the most volumes (components, time points) info counts in one file
MAX_VOLUMES = 100_000


def _volume_count(file, raw) -> int | None:
    """How many volumes (components or time points) ``file`` holds, by its header; None: not that.

    For ``info`` of a file every other command asks ``--volume-index`` of (a
    displacement field's 3 components, a 4-D series): volume 0 is described
    and the count said (it was a usage error, exit 2, so volwarp's own
    fields could not be inspected).
    """
    from ..errors import BadUsage
    from ..io.lazy import open_volume_header

    if raw is not None:
        return None
    if volume_format(file, reading=True) == "nifti":  # (its header says: a .nii.gz
        from ..io.nifti import open_nifti  # opened once a probe inflated it each time)

        nf = open_nifti(file)
        count = max(nf.volumes, nf.components)
        return count if count > 1 else None

    def exists(i: int) -> bool:
        try:
            open_volume_header(file, volume_index=i)
        except ChoiceNeeded:
            raise
        except BadUsage:
            return False
        return True

    try:
        if not exists(0):
            return None
        hi = 1
        while hi < MAX_VOLUMES and exists(hi):  # (doubling, then halving: a few headers)
            hi *= 2
        lo = hi // 2
        while hi - lo > 1:
            mid = (lo + hi) // 2
            lo, hi = (mid, hi) if exists(mid) else (lo, mid)
        return hi if exists(hi) else lo + 1
    except ChoiceNeeded:  # (not a choice of volumes: a series, ...)
        return None


def _lattice_lines(desc: dict, pts) -> list[str]:
    """Where a capture file's control points lie, in words a spec's ``move.index`` can use.

    ``pts[i][j][k]`` is the world position of control point ``[i, j, k]``. The index
    runs along the input's voxel axes (the shape's x y z), which are world axes only
    for an identity direction: the lines give each index step as a world vector, and
    which indices lie inside the volume's voxel box.
    """
    import numpy as np

    p = np.asarray(pts, dtype=np.float64)  # [i, j, k, 3]
    n = p.shape[:3]
    fmt = " ".join
    lines = [f"lattice index: [i, j, k], 0-based (0..{n[0] - 1} 0..{n[1] - 1} 0..{n[2] - 1}), "
             "along the input's voxel axes x y z (not world x y z)",
             f"lattice [0, 0, 0]: world {fmt(f'{v:g}' for v in p[0, 0, 0])} mm; "
             f"[{n[0] - 1}, {n[1] - 1}, {n[2] - 1}]: world "
             f"{fmt(f'{v:g}' for v in p[-1, -1, -1])} mm"]
    origin = np.asarray(desc["origin"], dtype=np.float64)
    m = np.asarray(desc["direction"], dtype=np.float64) * np.asarray(desc["spacing"])
    idx = np.linalg.solve(m, (p.reshape(-1, 3) - origin).T).T.reshape(p.shape)  # input voxels
    axes = [idx[:, 0, 0, 0], idx[0, :, 0, 1], idx[0, 0, :, 2]]  # each index axis's positions
    steps = [np.diff(p, axis=a) for a in range(3)]
    uniform = all(np.allclose(st, st.reshape(-1, 3)[0], atol=1e-6) for st in steps)
    if uniform:
        parts = [f"{name} +1 = world {fmt(f'{v:g}' for v in st.reshape(-1, 3)[0])} mm"
                 for name, st in zip("ijk", steps, strict=True)]
        lines.append("lattice steps: " + "; ".join(parts))
        spacing = [float(np.linalg.norm(st.reshape(-1, 3)[0])) for st in steps]
        lines.append(f"lattice reach: a moved control point changes the model within 2 steps "
                     f"of it along i, j, k ({fmt(f'{2 * h:g}' for h in spacing)} mm)")
    else:  # the tripled placement: positions along each axis, in input voxel indices
        for a, (name, axis) in enumerate(zip("ijk", axes, strict=True)):
            lines.append(f"lattice {name} (input voxel {'xyz'[a]}): "
                         f"{fmt(f'{v:.6g}' for v in axis)}")
    shape = np.asarray(desc["shape"], dtype=np.float64)
    inside = []
    for a, axis in enumerate(axes):
        ok = np.flatnonzero((axis >= -0.5 - 1e-6) & (axis <= shape[a] - 0.5 + 1e-6))
        inside.append(f"{ok[0]}..{ok[-1]}" if ok.size else "none")
    lines.append(f"lattice inside: [{', '.join(inside)}] lie within the volume's voxel box; "
                 "the others outside it")
    return lines


def _label_hint(desc: dict, vol) -> None:
    """Add ``label_map`` (distinct values, the first 16) when the volume looks like one.

    The rule ``warp`` and ``distance`` follow (integer ids, or floats that are
    all integers), whatever the number of values
    (:func:`volwarp_cli.labelmap.label_map_hint`).
    """
    if vol.data.dtype.kind in "iuf":
        from ..labelmap import label_map_hint

        hint = label_map_hint(vol.data, vol.meta)
        if hint is not None:
            desc["label_map"] = hint


def _describe_dicom(file, raw, volume_index, dicom) -> dict:
    """A DICOM input: the chosen (or only) volume with the list of candidates.

    When it holds several and ``--series`` chose none, the candidates alone (UID,
    description, size, spacing, why split) so that the user can choose.
    """
    from ..io.dicom import scan_dicom, segmentation_kind

    if raw is not None or volume_index is not None:
        load_input(file, raw, volume_index)  # the usage error those options get
    kind = segmentation_kind(file)
    if kind is not None:
        return _describe_segmentation(file, kind, dicom)
    scanned = scan_dicom(file)
    candidates = [c.describe() for c in scanned]
    if len(candidates) > 1 and not (dicom and "series" in dicom):
        return {"format": "dicom", "candidates": candidates}
    vol = load_input(file, dicom={**(dicom or {}), "candidates": scanned})
    return {**describe_volume(vol, "dicom"), "candidates": candidates}


def _describe_segmentation(file, kind: str, dicom) -> dict:
    """A SEG: its label map (its own grid) with ``segments``; an RTSTRUCT: its ``structures``.

    A SEG whose segments overlap has no label map: its ``segments`` alone, and
    ``segments_overlap``, so that the user can choose one with ``--segment N``.
    An RTSTRUCT has no grid without the series it was drawn on: its ROIs, the
    series and frame of reference it names; with ``--reference`` also the label
    map rasterised on that series' grid.
    """
    if kind == "rtstruct":
        from ..io.rtstruct import (
            describe_structures,
            frames_of_reference,
            open_rtstruct,
            referenced_series,
        )

        desc = {"format": "dicom"}
        if dicom:  # (without --reference: the usage error those options get without a grid)
            desc = describe_volume(load_input(file, dicom=dicom), "dicom")
        ds = open_rtstruct(file)
        return {**desc, "dicom_type": "RTSTRUCT",
                "referenced_series": list(referenced_series(ds)),
                "frame_of_reference": list(frames_of_reference(ds)),
                "structures": describe_structures(ds)}
    from ..io.dicom_seg import SegmentsOverlap, describe_segments, open_seg, seg_type

    seg = open_seg(file)
    try:
        desc = describe_volume(load_input(file, dicom=dicom), "dicom")
    except SegmentsOverlap:
        desc = {"format": "dicom", "segments_overlap": True}
    desc["dicom_type"] = "SEG"
    desc["segmentation_type"] = seg_type(seg)
    desc["segments"] = describe_segments(seg)
    return desc


def _segment_lines(segments: list[dict]) -> list[str]:
    """One line per segment: its number, label, coded category and type."""
    lines = []
    for seg in segments:
        what = " / ".join(c["meaning"] for c in (seg["category"], seg["type"]) if c)
        lines.append(f"  [{seg['number']}] {seg['label']!r}" + (f": {what}" if what else ""))
    return lines


def _overlap_text(desc: dict) -> str:
    return "\n".join([f"format:    dicom SEG ({desc['segmentation_type']}), "
                      f"{len(desc['segments'])} segment(s) that overlap (a voxel in two): no "
                      "one label map holds them; read one as a 0/1 mask with --segment N"]
                     + _segment_lines(desc["segments"]))


def _structures_text(desc: dict) -> str:
    lines = [f"format:    dicom RTSTRUCT, {len(desc['structures'])} structure(s) "
             "(a grid needs the series it was drawn on: volwarp convert --reference)",
             f"series:    {' '.join(desc['referenced_series']) or '-'}"]
    for r in desc["structures"]:
        lines.append(f"  [{r['number']}] {r['name']!r}: {r['contours']} contour(s)")
    return "\n".join(lines)


def _candidates_text(desc: dict) -> str:
    lines = [f"format:    dicom, {len(desc['candidates'])} volumes (choose one with --series "
             "UID|N)"]
    for c in desc["candidates"]:
        x, y, z = c["shape_xyz"]
        sx, sy, sz = c["spacing"]
        text = f" {c['description']!r}" if c["description"] else ""
        why = f"; {c['why']}" if c["why"] else ""
        lines.append(f"  [{c['index']}] {c['series_uid']}{text} {c['modality']} "
                     f"{x}x{y}x{z}, spacing {sx:g} {sy:g} {sz:g}, {c['files']} file(s){why}")
    return "\n".join(lines)
