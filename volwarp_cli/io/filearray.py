"""A volume's raw samples in a file, read and written by box with pread/pwrite.

For inputs and outputs larger than memory. A memory map would do the same
with less code, but every page it touches counts in the process's resident
set (and in a cluster worker's memory accounting) until it is unmapped: a
block task writing a column of a memory-mapped output holds pages of every
plane it crosses, many times the block's own bytes when its rows are short.
Reads and writes through the file descriptor leave the data in the page
cache only, which the kernel reclaims as it needs.

Samples are C order ``[z, y, x]`` from byte ``offset``, of a fixed-endian
``dtype``. A box is read a plane's row range at a time (one ``pread`` of the
rows, the columns cut after), or a row segment at a time where that would
skip long stretches of the rows (:data:`ROW_SKIP`); it is written one row segment at a time (whole rows together when
the box spans them).
"""

from __future__ import annotations

import os

import numpy as np

from ..errors import FormatError

#: bytes of a row a read may skip over rather than make a read per row (a system call
#: costs about what copying this many bytes does)
ROW_SKIP = 16 << 10


class FileArray:
    """``shape`` (z, y, x) samples of ``dtype`` at ``offset`` in ``path``: numpy slicing reads.

    Picklable (the path, not an open file): a worker process opens the file
    itself. ``writable``: ``array[z0:z1, y0:y1, x0:x1] = block`` writes too;
    ``write_back`` (an output's samples, not a scratch file's): each write of
    a contiguous span asks for it to be written out (:mod:`.writeback`).
    """

    def __init__(self, path, dtype, offset: int, shape, *, writable: bool = False,
                 write_back: bool = False):
        self.path = str(path)
        self.dtype = np.dtype(dtype)
        self.offset = int(offset)
        self.shape = tuple(int(n) for n in shape)
        self.ndim = 3
        self.writable = writable
        self.write_back = write_back and writable
        self._fd = None

    # -- the file ----------------------------------------------------------------------------
    def _file(self) -> int:
        if self._fd is None:
            self._fd = os.open(self.path, os.O_RDWR if self.writable else os.O_RDONLY)
        return self._fd

    def close(self) -> None:
        """Close the file (reopened by the next access)."""
        if self._fd is not None:
            fd, self._fd = self._fd, None  # (forgotten first: a failed close frees it anyway)
            os.close(fd)

    def __del__(self):
        try:
            self.close()
        except Exception:  # pragma: no cover - interpreter shutdown
            pass

    def __getstate__(self):
        state = dict(self.__dict__)
        state["_fd"] = None
        return state

    # -- indexing ------------------------------------------------------------------------------
    def _ranges(self, key):
        return box_of_key(key, self.shape)

    def __getitem__(self, key) -> np.ndarray:
        ((z0, z1), (y0, y1), (x0, x1)), pick = self._ranges(key)
        _, ny, nx = self.shape
        item = self.dtype.itemsize
        out = np.empty((z1 - z0, y1 - y0, x1 - x0), dtype=self.dtype.newbyteorder("="))
        if out.size:
            fd = self._file()
            rows = y1 - y0
            native = self.dtype == out.dtype
            whole = x0 == 0 and x1 == nx
            if (nx - (x1 - x0)) * item <= ROW_SKIP:  # the rows in one read, cut after
                rows_buf = None if (whole and native) else np.empty((rows, nx), self.dtype)
                for z in range(z0, z1):
                    dest = out[z - z0] if rows_buf is None else rows_buf
                    self._read_into(fd, dest, self.offset + ((z * ny + y0) * nx) * item, z)
                    if rows_buf is not None:
                        out[z - z0] = rows_buf[:, x0:x1]
            else:  # a narrow box of long rows: each row's segment, a read per row
                row = np.empty(x1 - x0, self.dtype)
                for z in range(z0, z1):
                    for y in range(y0, y1):
                        self._read_into(fd, row, self.offset + ((z * ny + y) * nx + x0) * item,
                                        z)
                        out[z - z0, y - y0] = row
        return out[pick]

    def _read_into(self, fd: int, dest: np.ndarray, offset: int, z: int) -> None:
        """Fill the contiguous ``dest`` from ``offset`` (no intermediate bytes object)."""
        view = memoryview(dest).cast("B")
        done = 0
        while done < len(view):
            n = os.preadv(fd, [view[done:]], offset + done)
            if n == 0:
                raise FormatError(f"{self.path}: file is truncated (plane {z} ends "
                                  f"{len(view) - done} bytes short)")
            done += n

    def __setitem__(self, key, value) -> None:
        if not self.writable:
            raise ValueError(f"{self.path}: opened read-only")
        ((z0, z1), (y0, y1), (x0, x1)), pick = self._ranges(key)
        if any(not isinstance(p, slice) or p.step != 1 for p in pick):
            raise IndexError("writes take boxes (slices without steps)")
        block = np.asarray(value)
        shape = (z1 - z0, y1 - y0, x1 - x0)
        block = np.ascontiguousarray(np.broadcast_to(block, shape), dtype=self.dtype)
        if block.size == 0:
            return
        fd = self._file()
        _, ny, nx = self.shape
        item = self.dtype.itemsize
        whole_rows = x0 == 0 and x1 == nx
        for i, z in enumerate(range(z0, z1)):
            if whole_rows:  # the plane's rows are contiguous in the file
                _write_all(fd, block[i], self.offset + (z * ny + y0) * nx * item)
                continue
            for j, y in enumerate(range(y0, y1)):
                _write_all(fd, block[i, j], self.offset + ((z * ny + y) * nx + x0) * item)
        if self.write_back and whole_rows and (z1 - z0 == 1 or (y0 == 0 and y1 == ny)):
            from . import writeback  # (the bytes written are one span of the file)

            writeback.start(fd, self.offset + (z0 * ny + y0) * nx * item, block.nbytes)

    def __array__(self, dtype=None, copy=None):
        out = self[:, :, :]
        return out if dtype is None else out.astype(dtype)


def box_of_key(key, shape):
    """A numpy index of a 3-D volume of ``shape`` as the box to read and what to pick from it.

    ``(box, pick)``: per axis the index range ``(lo, hi)`` covering every
    index asked for, and ``pick``, the index that takes the answer from that
    box (a slice of it, any step; an int drops the axis): ``read(box)[pick]``
    equals ``whole[key]``. For lazy arrays that read boxes (files, zarr stores).
    """
    if not isinstance(key, tuple):
        key = (key,)
    if any(k is Ellipsis for k in key):
        i = next(j for j, k in enumerate(key) if k is Ellipsis)
        key = key[:i] + (slice(None),) * (3 - len(key) + 1) + key[i + 1:]
    if len(key) > 3:
        raise IndexError(f"too many indices for a 3-D volume: {len(key)}")
    key = key + (slice(None),) * (3 - len(key))
    box, pick = [], []
    for axis, (k, n) in enumerate(zip(key, shape, strict=True)):
        if isinstance(k, slice):
            idx = range(*k.indices(n))
            if len(idx) == 0:
                box.append((0, 0))
                pick.append(slice(0, 0))
                continue
            lo, hi = min(idx), max(idx) + 1
            box.append((lo, hi))
            stop = idx.stop - lo
            pick.append(slice(idx.start - lo, stop if stop >= 0 else None, idx.step))
        else:
            i = int(k)
            i = i + n if i < 0 else i
            if not 0 <= i < n:
                raise IndexError(f"index {k} is out of bounds for axis {axis} of size {n}")
            box.append((i, i + 1))
            pick.append(0)
    return box, tuple(pick)


def _write_all(fd: int, data: np.ndarray, offset: int) -> None:
    """Write the contiguous ``data`` at ``offset`` (its own buffer, not a copy)."""
    view = memoryview(np.ascontiguousarray(data)).cast("B")
    while view:
        n = os.pwrite(fd, view, offset)
        view = view[n:]
        offset += n
