"""How an output was made, in its key/values: the command, its inputs' names, its spec.

Deterministic (no time, no host): the same inputs and spec give the same
bytes, which batch's content-addressed cache relies on.
"""

from __future__ import annotations

from .volume import Header, Volume


def provenance(command: str, inputs, spec=None) -> dict[str, str]:
    """Key/values recording how an output was made (deterministic: no time, no host).

    ``volwarp_version``, ``volwarp_command``, ``volwarp_input`` (the input
    files' names, not their folders, so moving a tree does not change bytes)
    and, when a spec drove the work, ``volwarp_spec_sha256`` of its bytes.
    """
    from pathlib import Path

    from . import __version__

    if isinstance(inputs, (str, Path)):
        inputs = [inputs]
    meta = {
        "volwarp_version": __version__,
        "volwarp_command": command,
        "volwarp_input": " ".join(Path(p).name for p in inputs),
    }
    if spec is not None:
        digest = _spec_digests.get(_key(spec))
        if digest is None:
            digest = _sha256(Path(spec).read_bytes()).hexdigest()
        meta["volwarp_spec_sha256"] = digest
    return meta


#: the sha256 of each spec file as :func:`~volwarp_cli.spec.loader.load_spec` last read it
_spec_digests: dict[str, str] = {}


def _key(path) -> str:
    import os

    return os.path.abspath(os.fspath(path))


def remember_spec(path, data: bytes) -> None:
    """Record the bytes a spec was read from, for its ``volwarp_spec_sha256``.

    A spec read from a pipe (``--spec /dev/stdin``, ``<(...)``) cannot be read
    twice: hashed again when the output is stamped, its hash was the empty
    input's. A file changed after it was read is hashed as it was used.
    """
    _spec_digests[_key(path)] = _sha256(data).hexdigest()


def _sha256(data: bytes):
    """A SHA-256 of ``data`` without loading OpenSSL when CPython's own one is there.

    ``hashlib`` loads OpenSSL's library on import (5-7 ms, a twentieth of a
    small warp command, for the hash of a spec of a few kB); CPython's
    built-in module gives the same digest (``_sha2`` since 3.12, ``_sha256``
    before). Falls back to ``hashlib`` where neither is built.
    """
    try:
        from _sha2 import sha256
    except ImportError:
        try:
            from _sha256 import sha256
        except ImportError:  # pragma: no cover - a CPython built without them
            from hashlib import sha256
    return sha256(data)


#: The keys :func:`provenance` writes (an earlier step's are replaced; other
#: ``volwarp_*`` keys, such as ``volwarp_distance``, still describe the values)
PROVENANCE_KEYS = ("volwarp_version", "volwarp_command", "volwarp_input", "volwarp_spec_sha256")


#: Key/values of an input file's fields true of its samples as they are, on its grid:
#: ``convert`` carries them (the same samples, the same grid); an output a command
#: computes does not (:func:`stamp`): a display window would hide the new values, a slice
#: thickness, slice axis or timing is no longer the acquisition's, a distance map's units
#: are millimetres and its range is not its input's (:data:`volwarp_cli.io.nifti.AS_READ_FIELDS`,
#: :data:`volwarp_cli.io.nrrd.AS_READ_FIELDS`, :data:`volwarp_cli.io.metaimage.AS_READ_FIELDS`)
AS_READ_KEYS = frozenset((
    "NIfTI_cal_min", "NIfTI_cal_max", "NIfTI_dim_info", "NIfTI_slice_code",
    "NIfTI_slice_start", "NIfTI_slice_end", "NIfTI_slice_duration", "NIfTI_toffset",
    "NIfTI_aux_file", "NRRD_sample units", "NRRD_thicknesses", "NRRD_labels",
    "MetaImage_ElementMin", "MetaImage_ElementMax"))
#: those of :data:`AS_READ_KEYS` that name the file's axes or slices by their index order:
#: dropped too where the samples are stored reindexed (an OME-Zarr store of a flipped or
#: permuted grid, :func:`volwarp_cli.io.omezarr.reindexed_header`)
AS_READ_AXIS_KEYS = frozenset((
    "NIfTI_dim_info", "NIfTI_slice_code", "NIfTI_slice_start", "NIfTI_slice_end",
    "NRRD_thicknesses", "NRRD_labels"))


def computed_meta(meta) -> dict:
    """An input's key/values as an output computed from it carries them.

    Without the earlier step's provenance (:data:`PROVENANCE_KEYS`, replaced)
    and the fields true of the input's samples only (:data:`AS_READ_KEYS`).
    """
    return {k: v for k, v in meta.items() if k not in PROVENANCE_KEYS and k not in AS_READ_KEYS}


def stamp(vol: Volume | Header, command: str, inputs, spec=None) -> Volume | Header:
    """``vol`` (a Volume or a Header) with its provenance key/values set.

    An earlier step's provenance is replaced; the input's fields true of its
    samples as read only are dropped (:func:`computed_meta`).
    """
    meta = computed_meta(vol.meta)
    meta.update(provenance(command, inputs, spec))
    return vol.replace(meta=meta)
