"""Sample types, counts and casting: what a volume's samples may be, and converting them.

Shared by the readers and writers (``io/``) and by the numeric core (a warp or
a morph frame cast back to the input's type), so it lives in neither.
"""

from __future__ import annotations

import math
import threading

import numpy as np

from .errors import FormatError, VolwarpError

#: The sample types volwarp reads and writes unchanged.
SUPPORTED_DTYPES = ("uint8", "int8", "uint16", "int16", "uint32", "int32", "float32", "float64")


def check_dtype(dtype, where: str = "") -> np.dtype:
    """Return the native-order dtype for a supported sample type, else raise."""
    dt = np.dtype(dtype)
    native = dt.newbyteorder("=")
    if native.name not in SUPPORTED_DTYPES:
        prefix = f"{where}: " if where else ""
        raise FormatError(f"{prefix}unsupported sample type {dt.name!r} "
                          f"(supported: {', '.join(SUPPORTED_DTYPES)})")
    return native


#: the most samples a volume may have along an axis (2^31: beyond it no memory or disk
#: holds a volume, and numpy may not even make its shape)
MAX_AXIS = 1 << 31


def holds_value(dtype, value: float) -> bool:
    """Whether samples of ``dtype`` hold ``value`` exactly (integer types: in range, whole)."""
    dtype = np.dtype(dtype)
    if dtype.kind not in "iu":
        return True  # (floats: the value as that float, as every sample of it is)
    info = np.iinfo(dtype)
    return float(value).is_integer() and info.min <= value <= info.max


def voxel_count(shape) -> int:
    """The number of samples of a grid of ``shape`` (any axis order), as a Python int.

    A Python int does not overflow, as a product of a header's sizes in int64
    could (``np.prod``) before the memory check sees it.
    """
    n = 1
    for s in shape:
        n *= int(s)
    return n


def _float_bounds(ftype, info) -> tuple:
    """The smallest and largest floats of ``ftype`` inside an integer type's range ``info``."""
    ftype = np.dtype(ftype).type
    lo, hi = ftype(info.min), ftype(info.max)
    if float(lo) < info.min:
        lo = np.nextafter(lo, ftype(0))
    if float(hi) > info.max:
        hi = np.nextafter(hi, ftype(0))
    return lo, hi


def cast_samples(data: np.ndarray, dtype, *, what: str = "volume") -> np.ndarray:
    """Convert samples to ``dtype``: integers are rounded and clipped to the type's range.

    NaN cannot be stored in an integer type and is refused rather than
    silently turned into 0; finite samples beyond float32's range are refused
    rather than turned into infinities. Clipping is said (:func:`_say_clipped`):
    every sample of a CT cast to uint8 came out 0 without a word.
    """
    dt = check_dtype(dtype)
    if data.dtype == dt:
        return data
    if dt.kind in "iu":
        info = np.iinfo(dt)
        if data.dtype.kind == "f":
            out = np.rint(data)
            low, high = (float(out.min()), float(out.max())) if out.size else (0.0, 0.0)
            if math.isnan(low) or math.isnan(high):  # (min and max pass NaN on)
                raise VolwarpError(f"{what}: samples that are NaN cannot be written as "
                                   f"{dt.name} (an integer type holds no NaN): keep a float "
                                   "type, or replace the NaN first")
            _note_rounding(what, dt, data, out, low, high)
            if low >= info.min and high <= info.max:  # (Python's float-int order: exact)
                return out.astype(dt)
            _note_clipped(what, dt, low, high)
            lo, hi = _float_bounds(out.dtype, info)
            if float(lo) == info.min and float(hi) == info.max:  # (the range exact here)
                np.clip(out, lo, hi, out=out)
                return out.astype(dt)
            # the type's range is not exact in these floats (int32 from float32: its max
            # rounds up to 2**31, which wrapped to -2**31): clipped inside it, then the ends
            over, under = out > hi, out < lo
            np.clip(out, lo, hi, out=out)
            res = out.astype(dt)
            res[over], res[under] = info.max, info.min
            return res
        src = np.iinfo(data.dtype)
        if src.min >= info.min and src.max <= info.max:
            return data.astype(dt)
        low, high = (int(data.min()), int(data.max())) if data.size else (0, 0)
        if low >= info.min and high <= info.max:
            return data.astype(dt)
        _note_clipped(what, dt, low, high)
        return np.clip(data, info.min, info.max).astype(dt)
    if dt == np.float32 and data.dtype == np.float64:
        with np.errstate(over="ignore"):
            out = data.astype(dt)
        over = np.isinf(out) & np.isfinite(data)
        if over.any():
            worst = float(np.abs(data[over]).max())
            raise VolwarpError(f"{what}: samples as large as {worst:.3g} ({int(over.sum())} "
                               f"of them) do not fit float32 (at most {float(np.finfo(dt).max):.3g}) "
                               "and would become infinite: keep float64 (--dtype float64) "
                               "or scale them first")
        return out
    if dt.kind == "f" and data.dtype.kind in "iu" and data.size:
        return _integers_as_floats(data, dt, what)
    return data.astype(dt)


def _integers_as_floats(data: np.ndarray, dt: np.dtype, what: str) -> np.ndarray:
    """Integer samples as floats of ``dt``; those the floats cannot hold exactly are noted.

    float32 holds every integer up to 2**24 (16,777,216), float64 up to 2**53:
    an int32 CT or label count beyond that was rounded without a word (by up to
    64 from int32 to float32). Said once a run (:func:`_note_inexact`).
    """
    out = data.astype(dt)
    exact = 2 ** (np.finfo(dt).nmant + 1)
    bits = 8 * data.dtype.itemsize - (data.dtype.kind == "i")
    # (every int8/int16/uint16 fits float32 and every int32 float64; volwarp's sample types
    # are at most 32-bit integers, which float64 holds with their error: int64, an API's
    # own array, is cast as it is)
    if 2 ** bits <= exact or data.dtype.itemsize > 4:
        return out
    low, high = int(data.min()), int(data.max())
    if -exact <= low and high <= exact:
        return out
    worst = 0.0
    flat_in, flat_out = data.reshape(-1), out.reshape(-1)
    for start in range(0, flat_in.size, 1 << 20):  # (by pieces: a block's memory is counted)
        piece = slice(start, start + (1 << 20))
        error = np.abs(flat_out[piece].astype(np.float64) - flat_in[piece])
        worst = max(worst, float(error.max()))
    if worst > 0:
        _note_inexact(what, dt, worst)
    return out


def _note_inexact(what: str, dt: np.dtype, worst: int) -> None:
    """Note integer samples rounded to the nearest ``dt``, by up to ``worst``; said once a run."""
    from .runscope import said_files

    if said_files() is None:
        _say_inexact(what, dt, worst)
        return
    _gathered(("inexact", dt.name), [-worst, worst, True, what])


def _say_inexact(what: str, dt: np.dtype, worst) -> None:
    from .progress import log

    exact = 2 ** (np.finfo(dt).nmant + 1)
    log.warning("warning: %s: integer samples beyond +/-%d are not all %s numbers and were "
                "rounded to the nearest, by up to %d; keep an integer type (or float64), or "
                "scale them first", what, exact, dt.name, int(worst),
                extra={"once": ("inexact", dt.name)})


#: fewer integer levels than this between a float cast's extremes: its fractions may be
#: most of what it holds (:func:`_say_rounded_away`)
FEW_LEVELS = 16


def _note_rounding(what: str, dt: np.dtype, data, rounded, low, high) -> None:
    """Note a float cast's reach and fractions; said if the whole is a few integers with fractions.

    A 0..1 density or opacity cast to uint8 comes out 0 and 1: an antialiased
    field made a binary mask without a word (a review of convert and morph;
    sweep scales its fields to the type first, and says so). A cast is often
    one block of many (a slab of planes): the reach of the whole output,
    gathered over its blocks, is judged when the run ends (a block at a
    warp's edge holds 0..3 of a 0..255 field); in a library call
    (:func:`volwarp_cli.runscope.call_scope`), when it returns. Outside
    both (a script's own cast), each cast is judged alone.
    """
    from .runscope import said_files

    if said_files() is None:
        if high - low < FEW_LEVELS and not np.array_equal(data, rounded):
            _say_rounded_away(what, dt, low, high)
        return
    seen = _gathered(("rounding", what, dt.name), [low, high, False])
    with _rounding_lock:  # (the threads of a run cast their planes at once)
        look = not seen[2] and seen[1] - seen[0] < FEW_LEVELS  # (a wide output: no more)
    if look and not np.array_equal(data, rounded):
        with _rounding_lock:
            seen[2] = True


_rounding_lock = threading.Lock()

#: the kinds of :func:`_gathered` notes: a run's casts, judged or said at its end
_NOTE_KINDS = ("rounding", "clipped", "inexact", "ids", "reached")


def _gathered(key: tuple, note: list) -> list:
    """The run's note ``key`` (``[low, high, flag, ...]``), ``note`` merged into it.

    The first of a key in a run is kept (and judged at the run's end,
    :func:`_note_at_end`); a later one widens its reach and ors its flag.
    """
    from .runscope import said_files

    files = said_files()  # (a run's, or a library call's: said when it returns)
    with _rounding_lock:
        seen = files.decided.get(key)
        if seen is None:
            seen = files.decided[key] = _copied(key, note)
            files.ends.append(lambda: _note_at_end(key, seen, files))
        elif key[0] == "ids":
            seen[0].extend(note[0])
            if seen[1] is None:
                seen[1] = note[1]
        elif key[0] == "reached":
            seen[0] = seen[0] or note[0]
            if seen[1] is None:
                seen[1] = note[1]
        else:
            seen[0], seen[1] = min(seen[0], note[0]), max(seen[1], note[1])
            seen[2] = seen[2] or note[2]
    return seen


def _copied(key: tuple, note: list) -> list:
    """A note's own copy: an ``ids`` note's list of pieces copied too (it grows)."""
    return [list(note[0]), *note[1:]] if key[0] == "ids" else list(note)


def expect_output_ids(what: str, expected) -> None:
    """Say, when the run ends, the ids of ``expected`` that no block of output ``what`` held.

    A label thinner than the output's voxels (a landmark, a one-voxel line
    resampled onto a coarser grid) or outside the output's grid is in no output
    voxel: nearest-neighbour resampling loses it without a word, where the
    warp's label report names it. The blocks note what they hold
    (:func:`note_output_ids`, worker processes' sent back with their results);
    the expected ids stay here, once.
    """
    from .runscope import said_files

    if said_files() is not None:
        _gathered(("ids", what), [[], _sorted_distinct(np.asarray(expected)), what])


def note_output_ids(what: str, block: np.ndarray) -> None:
    """Note the ids a block of output ``what`` holds (see :func:`expect_output_ids`)."""
    from .runscope import said_files

    if said_files() is not None:
        _gathered(("ids", what), [[distinct_values(block)], None, what])


def distinct_values(block: np.ndarray) -> np.ndarray:
    """The distinct values of ``block``, sorted.

    Marked in a table where their range is small (a pass, no sort), else sorted.
    """
    flat = np.asarray(block).reshape(-1)
    if flat.size and flat.dtype.kind in "iu" and flat.dtype.itemsize <= 2:
        unsigned = flat.view(flat.dtype.str.replace("i", "u"))  # (int16: as its bit patterns)
        present = np.zeros(1 << (8 * flat.itemsize), bool)
        present[unsigned] = True  # (bincount would make a copy of 8-byte counts first)
        return _sorted_distinct(np.flatnonzero(present).astype(unsigned.dtype).view(flat.dtype))
    return _sorted_distinct(flat)


def expect_reached(what: str, message: str) -> None:
    """Say ``message`` when the run (or library call) ends if no block of ``what`` reached anything.

    For outputs that a slip leaves all background, exit 0: a sweep whose
    templates meet no voxel centre (a grid beside the sweep), a resampling
    whose every point maps outside its input (transforms in the wrong order
    or direction). The blocks note whether they reached something
    (:func:`note_reached`; a worker process's notes go back with its
    results); the message stays here, once.
    """
    from .runscope import said_files

    if said_files() is not None:
        _gathered(("reached", what), [False, message])


def note_reached(what: str, reached) -> None:
    """Note whether a block of ``what`` reached something (see :func:`expect_reached`).

    ``reached``: a bool, or a call giving it, made only while no block has
    yet (a pass over an output saved once one block did).
    """
    from .runscope import said_files

    files = said_files()
    if files is None:
        return
    seen = files.decided.get(("reached", what))
    if seen is not None and seen[0]:
        return
    _gathered(("reached", what), [bool(reached() if callable(reached) else reached), None])


def _sorted_distinct(values: np.ndarray) -> np.ndarray:
    """The distinct values, sorted.

    A sort and a pass: numpy 2's unique hashes, 5x slower on 4 million uint32 ids.
    """
    flat = np.sort(np.asarray(values).reshape(-1))
    if flat.size < 2:
        return flat
    keep = np.empty(flat.size, bool)
    keep[0] = True
    np.not_equal(flat[1:], flat[:-1], out=keep[1:])
    return flat[keep]


def _say_missing_ids(note) -> None:
    from .progress import log

    pieces, expected, what = note
    if expected is None:
        return
    held = _sorted_distinct(np.concatenate(pieces)) if pieces else np.empty(0)
    at = np.minimum(np.searchsorted(held, expected), max(len(held) - 1, 0))
    found = held[at] == expected if len(held) else np.zeros(len(expected), bool)
    missing = expected[~found].tolist()
    if not missing:
        return
    missing = [int(v) if float(v).is_integer() else v for v in missing]
    shown = ", ".join(map(str, missing[:8])) + (f" and {len(missing) - 8} more"
                                               if len(missing) > 8 else "")
    log.warning("warning: %s: %d of the input's %d labels are in no output voxel (%s): "
                "thinner than the output's voxels, or outside its grid", what, len(missing),
                len(expected), shown, extra={"once": ("ids", what)})


def run_notes() -> tuple:
    """The current run's cast notes, ``((key, note), ...)``.

    A block task in another process sends them back with its result
    (:func:`merge_notes` in the command's).
    """
    from .runscope import run_files

    with _rounding_lock:
        return tuple((key, _copied(key, note)) for key, note in run_files().decided.items()
                     if isinstance(key, tuple) and key and key[0] in _NOTE_KINDS)


def merge_notes(notes) -> None:
    """Merge notes from :func:`run_notes` into the current run (judged at its end)."""
    for key, note in notes:
        _gathered(tuple(key), note)


def _note_at_end(key: tuple, seen: list, files) -> None:
    """At the run's end, if its outputs were written (``files``'s run): say what a note holds.

    A run of its own in a worker process writes nothing: its notes went back to
    the command with its blocks (:func:`run_notes`), judged there.
    """
    if not files.committed:
        return
    if key[0] == "rounding":
        _, what, name = key
        low, high, fractions = seen
        if fractions and high - low < FEW_LEVELS:
            _say_rounded_away(what, np.dtype(name), low, high, files.said)
    elif key[0] == "ids":
        _say_missing_ids(seen)
    elif key[0] == "reached":
        if not seen[0] and seen[1] is not None:
            from .progress import log

            log.warning("warning: %s", seen[1], extra={"once": key})
    elif key[0] == "inexact":
        _, name = key
        _say_inexact(seen[3], np.dtype(name), seen[1])
    else:
        _, name = key
        low, high, _, what = seen
        _say_clipped(what, np.dtype(name), low, high)


def _note_clipped(what: str, dt: np.dtype, low, high) -> None:
    """Note samples from ``low`` to ``high`` clipped to ``dt`` for ``what``.

    In a run, the reach over all its casts to ``dt`` (every block and thread of
    every output: the first output named) is said once at its end, the same
    words whatever the cut into blocks (a library call's: when it returns);
    outside both, at once.
    """
    from .runscope import said_files

    if said_files() is None:
        _say_clipped(what, dt, low, high)
        return
    _gathered(("clipped", dt.name), [low, high, True, what])


def _say_rounded_away(what: str, dt: np.dtype, low, high, said=None) -> None:
    """Warn that a float field with fractions became a few integers in ``dt``.

    Once a run for each type (``said``: the run's said set; None: every time).
    """
    from .progress import log

    key = ("rounded away", dt.name)
    if said is not None:
        if key in said:
            return
        said.add(key)
    levels = int(high - low) + 1
    log.warning("warning: %s: samples with fractions became %d integer value%s (%g to %g) "
                "as %s: their fractions were rounded away (a 0..1 field becomes 0 and 1); "
                "keep a float type, or scale them first", what, levels,
                "" if levels == 1 else "s", low, high, dt.name, extra={"once": key})


def _say_clipped(what: str, dt: np.dtype, low, high) -> None:
    """Warn that samples from ``low`` to ``high`` were clipped to ``dt`` for ``what``.

    Said once a command's run for each type (:func:`_note_clipped` gathers the
    reach of all its casts first), naming the first output it happened to (a
    morph's 100 frames: one line, not 100); a library call's, once a call.
    Outside both (a script's own cast), every time.
    """
    from .progress import log

    info = np.iinfo(dt)
    key = ("clipped", dt.name)
    beyond = [f"as low as {float(low):.10g}"] if low < info.min else []
    beyond += [f"as high as {float(high):.10g}"] if high > info.max else []
    log.warning("warning: %s: samples %s lie outside %s's range [%d, %d] and are clipped to "
                "it", what, " and ".join(beyond), dt.name, info.min, info.max,
                extra={"once": key})
