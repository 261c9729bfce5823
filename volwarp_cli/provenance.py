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
        import hashlib  # (here: OpenSSL's load costs a command without a spec 3-10 ms)

        meta["volwarp_spec_sha256"] = hashlib.sha256(Path(spec).read_bytes()).hexdigest()
    return meta


#: The keys :func:`provenance` writes (an earlier step's are replaced; other
#: ``volwarp_*`` keys, such as ``volwarp_distance``, still describe the values)
PROVENANCE_KEYS = ("volwarp_version", "volwarp_command", "volwarp_input", "volwarp_spec_sha256")


def stamp(vol: Volume | Header, command: str, inputs, spec=None) -> Volume | Header:
    """``vol`` (a Volume or a Header) with its provenance key/values set.

    An earlier step's provenance is replaced.
    """
    meta = {k: v for k, v in vol.meta.items() if k not in PROVENANCE_KEYS}
    meta.update(provenance(command, inputs, spec))
    return vol.replace(meta=meta)
