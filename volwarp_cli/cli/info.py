"""`volwarp info FILE`: format, geometry and statistics of a volume (or capture file)."""

from __future__ import annotations

import json

import click

from ..io import volume_format
from .common import describe_volume, load_input
from .options import INPUT_PATH, common_options, raw_options


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
        if k not in ("format", "shape", "dtype", "spacing", "origin", "direction", "space",
                     "file_space", "min", "max", "mean", "meta", "nonfinite"):
            lines.append(f"{k}: {json.dumps(v)}")
    return "\n".join(lines)


@click.command(name="info")
@click.argument("file", type=INPUT_PATH)
@click.option("--json", "as_json", is_flag=True,
              help="Print one JSON object (stable keys: format shape dtype spacing origin "
                   "direction space file_space min max mean meta). Geometry is in LPS "
                   "millimetres (space), whatever frame the file used (file_space).")
@raw_options
@common_options
def command(file, as_json, raw, volume_index):
    """Print FILE's format, size (x y z), type, geometry, value range and key/values."""
    if file.lower().endswith(".vwc"):
        from ..bspline.capture_file import describe_capture
        desc = describe_capture(file)
    else:
        vol = load_input(file, raw, volume_index)
        desc = describe_volume(vol, volume_format(file))
    if as_json:
        click.echo(json.dumps(desc, indent=2, sort_keys=False, allow_nan=False))
    elif desc.get("format") == "vwc":
        # a capture file: the lattice positions are many numbers; show their extent
        pts = desc.pop("lattice_points")
        flat = [p for plane in pts for row in plane for p in row]
        lo = [min(p[a] for p in flat) for a in range(3)]
        hi = [max(p[a] for p in flat) for a in range(3)]
        click.echo(_format_text(desc))
        click.echo(f"lattice_points: {len(flat)} points, world x {lo[0]:g}..{hi[0]:g}, "
                   f"y {lo[1]:g}..{hi[1]:g}, z {lo[2]:g}..{hi[2]:g} (all of them: --json)")
    else:
        click.echo(_format_text(desc))
