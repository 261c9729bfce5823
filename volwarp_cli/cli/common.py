"""Small helpers the subcommands share: loading inputs, describing volumes."""

from __future__ import annotations

import click
import numpy as np

from ..io import read_volume
from ..progress import timed
from ..volume import Volume


def load_input(path, raw=None, volume_index=None, mmap=False) -> Volume:
    if raw is not None and not str(path).lower().endswith((".raw", ".bin")):
        # a file with a header describes itself: the options would be ignored
        raise click.UsageError(f"--raw-* options describe headerless .raw/.bin inputs, "
                               f"not {path}")
    with timed(f"read {path}"):
        return read_volume(path, raw=raw, volume_index=volume_index, mmap=mmap)


def describe_volume(vol: Volume, fmt: str) -> dict:
    """The stable ``volwarp info --json`` description of a volume.

    min, max and mean are those of the finite samples; ``nonfinite`` (only
    when there are any) counts the NaN and infinite ones, so the JSON stays
    strict (no NaN or Infinity tokens)."""
    data = vol.data
    nonfinite = 0
    if data.size:
        lo = data.min()
        hi = data.max()
        mean = float(data.mean(dtype=np.float64))
        if not (np.isfinite(lo) and np.isfinite(hi)):  # NaN or inf: describe the rest
            finite = data[np.isfinite(data)]
            nonfinite = data.size - finite.size
            lo, hi = (finite.min(), finite.max()) if finite.size else (None, None)
            mean = float(finite.mean(dtype=np.float64)) if finite.size else None
    else:  # pragma: no cover - volumes always have samples
        lo = hi = mean = None
    def num(v):
        if v is None:
            return None
        return int(v) if np.issubdtype(type(v), np.integer) else float(v)
    extra = {"nonfinite": nonfinite} if nonfinite else {}
    return {
        "format": fmt,
        "shape": list(vol.shape_xyz),
        "dtype": data.dtype.name,
        "spacing": [float(v) for v in vol.spacing],
        "origin": [float(v) for v in vol.origin],
        "direction": [[float(v) for v in row] for row in vol.direction],
        "space": vol.space,
        "file_space": vol.file_space,
        "min": num(lo),
        "max": num(hi),
        "mean": mean,
        "meta": {str(k): str(v) for k, v in sorted(vol.meta.items())},
        **extra,
    }


def provenance(command: str, inputs, spec=None) -> dict[str, str]:
    """Key/values recording how an output was made (deterministic: no time, no host).

    ``volwarp_version``, ``volwarp_command``, ``volwarp_input`` (the input
    files' names, not their folders, so moving a tree does not change bytes)
    and, when a spec drove the work, ``volwarp_spec_sha256`` of its bytes.
    """
    import hashlib
    from pathlib import Path

    from .. import __version__

    if isinstance(inputs, (str, Path)):
        inputs = [inputs]
    meta = {
        "volwarp_version": __version__,
        "volwarp_command": command,
        "volwarp_input": " ".join(Path(p).name for p in inputs),
    }
    if spec is not None:
        meta["volwarp_spec_sha256"] = hashlib.sha256(Path(spec).read_bytes()).hexdigest()
    return meta


#: The keys :func:`provenance` writes (an earlier step's are replaced; other
#: ``volwarp_*`` keys, such as ``volwarp_distance``, still describe the values)
PROVENANCE_KEYS = ("volwarp_version", "volwarp_command", "volwarp_input", "volwarp_spec_sha256")


def stamp(vol: Volume, command: str, inputs, spec=None) -> Volume:
    """``vol`` with its provenance key/values set (an earlier step's replaced)."""
    meta = {k: v for k, v in vol.meta.items() if k not in PROVENANCE_KEYS}
    meta.update(provenance(command, inputs, spec))
    return vol.with_data(vol.data, meta=meta)
