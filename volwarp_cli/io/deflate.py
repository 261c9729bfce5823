"""Deflate (gzip and zlib streams) for volume files: ISA-L when it is installed, else zlib.

ISA-L's igzip (python-isal) compresses a 256^3 int16 volume at level 1 in
0.12 s where zlib takes 0.83 s, into a slightly smaller stream, and inflates
about 1.5x faster; the streams are standard deflate, read by every gzip/zlib
reader (SimpleITK, pynrrd, nibabel, ITK's MetaIO). Outputs stay
byte-deterministic (gzip headers carry mtime 0) for a given installation:
the fallback to zlib, where python-isal has no wheel, writes other (equally
valid) bytes. ISA-L has levels 0..3; volwarp's level 1 is the same in both.
"""

from __future__ import annotations

import contextlib
import contextvars
import zlib

try:  # pragma: no branch - the test install has it
    from isal import igzip as _igzip
    from isal import isal_zlib as _zlib_impl

    ERRORS: tuple[type[BaseException], ...] = (zlib.error, _zlib_impl.error)
except ImportError:  # pragma: no cover - platforms without python-isal wheels
    _igzip = None
    _zlib_impl = zlib
    ERRORS = (zlib.error,)

#: the window bits that read a gzip or a zlib header (as zlib's MAX_WBITS | 32)
AUTO_HEADER = zlib.MAX_WBITS | 32


#: data from this size on is deflated by blocks on up to four threads (python-isal's
#: igzip_threaded, pigz's scheme: 1 MiB blocks, each with its predecessor's last 32 KiB as
#: dictionary): a 256^3 int16 volume in 0.057-0.067 s instead of 0.095 s (16 MB: 0.75x,
#: 8 MB: even, 4 MB: 1.09x on two cores); the bytes are the same whatever the thread
#: count (a machine of one core writes what one of 64 writes, 1.1x its one-call time)
BLOCKS_FROM = 8 << 20


def gzip_bytes(*parts, level: int = 1) -> bytes:
    """The buffers ``parts``, one after the other, as one gzip member with mtime 0.

    Deterministic for a given installation: the same bytes whatever the
    thread count (:data:`BLOCKS_FROM`). Several parts (a header and the
    samples) are deflated as they lie, without a joined copy.
    """
    views = [memoryview(p).cast("B") for p in parts]
    if _igzip is None:
        import gzip

        return gzip.compress(views[0] if len(views) == 1 else b"".join(views),
                             compresslevel=level, mtime=0)
    if sum(v.nbytes for v in views) < BLOCKS_FROM:
        return _igzip.compress(views[0] if len(views) == 1 else b"".join(views),
                               compresslevel=min(level, 3), mtime=0)
    import io

    out = io.BytesIO()
    _gzip_blocks(out, views, level)
    return out.getvalue()


def gzip_to(fh, *parts, level: int = 1) -> None:
    """:func:`gzip_bytes` of ``parts`` written to the binary file ``fh`` as it is made.

    The same bytes; from :data:`BLOCKS_FROM` on, the stream goes to ``fh``
    block by block, so the write holds a few blocks in flight rather than
    the whole compressed file (a 64 MiB float32 scan's 40 MB of gzip, plus
    the buffer's growth: 53 MiB).
    """
    views = [memoryview(p).cast("B") for p in parts]
    if _igzip is None or sum(v.nbytes for v in views) < BLOCKS_FROM:
        fh.write(gzip_bytes(*views, level=level))
        return
    _gzip_blocks(fh, views, level)


def _gzip_blocks(out, views, level: int) -> None:
    """``views`` as one gzip member written to ``out`` by blocks on up to four threads."""
    from isal import igzip_threaded

    from ..parallel import threads
    from ..signals import blocked

    # (a file object: closing the writer leaves it open; a stop waits for the end, a tenth
    # of a second: raised inside, it left the writer's threads waiting on each other and
    # the command hung)
    with blocked(), igzip_threaded.open(out, "wb", compresslevel=min(level, 3),
                                        threads=max(1, min(threads(), 4)),
                                        block_size=_BLOCK) as fh:
        for block in _blocks(views, _BLOCK):  # (a block a write: the blocks, and so the
            fh.write(block)                   # bytes, whatever the parts)


_BLOCK = 1 << 20


def _blocks(views, size: int):
    """The concatenation of ``views`` in pieces of ``size`` bytes (the last shorter).

    Only a piece across two parts is copied.
    """
    carry = bytearray()
    for v in views:
        at = 0
        if carry:
            at = min(size - len(carry), v.nbytes)
            carry += v[:at]
            if len(carry) < size:
                continue
            yield bytes(carry)
            carry = bytearray()
        while v.nbytes - at >= size:
            yield v[at:at + size]
            at += size
        carry += v[at:]
    if carry:
        yield bytes(carry)


def zlib_bytes(data, level: int = 1) -> bytes:
    """``data`` as one zlib stream (MetaImage's CompressedData)."""
    return _zlib_impl.compress(data, min(level, 3) if _igzip is not None else level)


#: compressed bytes handed to the inflater at a time, and the most it may return a call:
#: deflate expands up to 1032:1, so a call without a limit could return 66 MB from a
#: piece of zeros; with the limit the rest waits in ``unconsumed_tail`` (at most a piece,
#: copied at each call: small pieces keep that cheap). ISA-L inflates a 200 MB field in
#: 0.47 s so (1 MB a call); with 4 MB pieces and an 8 MB limit it took 1.1 s.
INFLATE_INPUT = 1 << 16
INFLATE_OUTPUT = 1 << 20


class Truncated(Exception):
    """A stream that ends before its end-of-stream marker (``args[0]``: the bytes inflated)."""


def inflate_pieces(fh):
    """The inflated pieces of the gzip (or zlib) members read from ``fh``, in order.

    Members may follow one another, empty ones too (bgzip's end-of-file
    block), with NUL padding between and after them, as gzip readers allow;
    at most :data:`INFLATE_OUTPUT` bytes a piece. Raises one of :data:`ERRORS`
    for corrupt data (trailing bytes that are no member included), and
    :class:`Truncated` when the file ends inside a member.
    """
    dec = decompressobj()
    done = 0
    while chunk := fh.read(INFLATE_INPUT):
        while chunk:
            if dec.eof:  # a member ended: padding, or the next member
                chunk = chunk.lstrip(b"\0")
                if not chunk:
                    break
                dec = decompressobj()
            piece = dec.decompress(chunk, INFLATE_OUTPUT)
            done += len(piece)
            yield piece
            chunk = dec.unused_data if dec.eof else dec.unconsumed_tail
    if not dec.eof:
        raise Truncated(done)


#: inflated bytes from which a batch goes to :func:`sink_beside`'s thread (a piece is at
#: most :data:`INFLATE_OUTPUT`); two batches may wait for it, so at most four, 6 MB, are
#: held besides the destination
BESIDE_BATCH = 1 << 19


@contextlib.contextmanager
def sink_beside(sink, total: int):
    """``sink(at, piece)`` called on a thread of its own, in order, while the caller inflates.

    Yields the function to hand the pieces to. Placing a piece of a field's
    component into its interleaved vectors (fresh memory: page faults) took
    a fifth of a large ``.nii.gz`` field's read on the inflating thread;
    beside it, the inflation (which releases the GIL) goes on meanwhile
    (256^3 ``apply``: 0.91x the time). Not for a plain copy: that one cost
    more in the hand-over than it gained (a 256^3 scan's read: 1.04x).

    The pieces go over in batches of :data:`BESIDE_BATCH` bytes (one
    hand-over a piece contended for the GIL). ``total`` under four batches,
    or one thread (:func:`~volwarp_cli.parallel.threads`): ``sink`` itself,
    here. The sink's error is raised in the caller (at its next piece, or at
    the end); an error of the caller's stops the thread before it is raised.
    """
    from ..parallel import threads

    if total < 4 * BESIDE_BATCH or threads() <= 1:
        yield sink
        return
    import queue
    import threading

    batches: queue.Queue = queue.Queue(2)
    failed: list[BaseException] = []
    stop = threading.Event()

    def place() -> None:
        while (batch := batches.get()) is not None:
            if failed or stop.is_set():
                continue  # (drained, so the caller never waits on a full queue)
            try:
                for at, piece in batch:
                    sink(at, piece)
            except BaseException as exc:  # (raised in the caller)
                failed.append(exc)

    batch: list = []
    size = 0

    def hand(at: int, piece) -> None:
        nonlocal batch, size
        if failed:
            raise failed[0]
        batch.append((at, piece))
        size += len(piece)
        if size >= BESIDE_BATCH:
            batches.put(batch)
            batch, size = [], 0

    from ..signals import blocked

    worker = threading.Thread(target=contextvars.copy_context().run, args=(place,),
                              daemon=True, name="volwarp-inflate-sink")
    worker.start()
    try:
        yield hand
        if batch:
            batches.put(batch)
    except BaseException:
        stop.set()
        raise
    finally:
        with blocked():  # (a second stop here would leave the thread waiting for its end)
            batches.put(None)
            worker.join()
    if failed:
        raise failed[0]


def decompressobj(wbits: int = AUTO_HEADER):
    """A streaming inflater with zlib's interface; its errors are in :data:`ERRORS`.

    The interface: ``decompress(data, max_length)``, ``unconsumed_tail``,
    ``unused_data``, ``eof``.
    """
    return _zlib_impl.decompressobj(wbits)
