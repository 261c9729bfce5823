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


def stamp(vol: Volume | Header, command: str, inputs, spec=None) -> Volume | Header:
    """``vol`` (a Volume or a Header) with its provenance key/values set.

    An earlier step's provenance is replaced.
    """
    meta = {k: v for k, v in vol.meta.items() if k not in PROVENANCE_KEYS}
    meta.update(provenance(command, inputs, spec))
    return vol.replace(meta=meta)
