"""Samples and masks kept out of memory: a long record in an anonymous temporary file,
read back in slices (:class:`SpilledSignals`), and a mask at one bit a row
(:class:`PackedMask`, written by a :class:`MaskPacker`)."""

from __future__ import annotations

import hashlib
import itertools
import logging
import os
import tempfile
import weakref
from collections.abc import Iterable, Iterator
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

from canrls.core.samples import ROLES, Signals

__all__ = ["ColumnLike", "Sliced", "SpilledSignals", "SpilledColumn", "SpilledBytes",
           "PackedMask", "MaskPacker", "as_packed", "join_blocks", "spill_blocks"]

_log = logging.getLogger(__name__)
#: the warning that a mask cannot go to a temporary file was given (once per process)
_mask_warned = False

F64 = npt.NDArray[np.float64]


# ------------------------------------------------------------- a record on disk
def _pread(fd: int, view: memoryview, offset: int, what: str) -> None:
    """Fill ``view`` from byte ``offset`` of the temporary ``what`` file (``os.preadv``
    until it is full)."""
    got = 0
    while got < len(view):
        m = os.preadv(fd, [view[got:]], offset + got)
        if m <= 0:
            raise OSError(f"the temporary {what} file ended at byte {offset + got}")
        got += m


class SpilledSignals:
    """A record of samples in an anonymous temporary file, read back in slices.

    The rows are appended block by block (:meth:`append`) and stored in chunks of
    :data:`ROWS` rows, each chunk column after column (``ROWS`` float64 of ``t``, then
    of each channel present in the order of :data:`ROLES`: 8 bytes per row and channel,
    40 with ``current``, ``speed``, ``position`` and ``voltage``). A slice is read back
    with ``os.preadv`` into fresh arrays, so the values are those appended, bit for bit,
    and only the slices being used are in memory (not ``mmap``: mapped pages would count
    as the process's resident memory); the file's pages live in the kernel's page cache.
    The file is made by :func:`tempfile.TemporaryFile` in the usual temporary directory
    (``TMPDIR``): it has no name (unlinked at once), so it goes with the process, even
    a killed one; :meth:`close` frees it earlier.

    It has the interface of :class:`Signals` the diagnosis reads: ``len``,
    :meth:`has`, :meth:`slice` (a :class:`Signals` block in memory) and the channels
    as :class:`SpilledColumn` (``None`` when absent) that read slices and sorted rows.

    :raises OSError: the temporary file cannot be made (a read-only or full temporary
        directory); :meth:`append` raises it when the file cannot be written.
    """

    #: rows per chunk of the file (the write buffer holds one chunk)
    ROWS = 65536

    def __init__(self, dir: str | None = None) -> None:
        self._file = tempfile.TemporaryFile(prefix="canrls-samples-", dir=dir)
        self._fd = self._file.fileno()
        #: channels stored in the file, in order (known at the first block)
        self._roles: list[str] = []
        #: of those, the ones every block had (a channel one block lacks is absent, as
        #: :meth:`Signals.concat` has it)
        self._present: set[str] = set()
        self._buf: npt.NDArray[np.float64] | None = None  # (channels, ROWS): the chunk open
        self._fill = 0  # rows of the open chunk in the buffer
        self._chunks = 0  # chunks written to the file
        self._n = 0  # rows appended
        #: the channels, read back where indexed (``None``: absent)
        self.t: SpilledColumn | None = None
        self.current: SpilledColumn | None = None
        self.speed: SpilledColumn | None = None
        self.position: SpilledColumn | None = None
        self.voltage: SpilledColumn | None = None
        self.torque: SpilledColumn | None = None

    # -- writing -------------------------------------------------------------------
    def append(self, block: Signals) -> None:
        """Add the rows of ``block`` at the end. On an ``OSError`` (the file cannot be
        written) none of the block's rows count: the record is the rows before it."""
        n = len(block)
        if not n:
            return
        if self._buf is None:
            self._roles = ["t", *(r for r in ROLES if block.has(r))]
            self._present = set(self._roles)
            self._buf = np.empty((len(self._roles), self.ROWS))
            self._columns()
        have = {"t", *(r for r in ROLES if block.has(r))}
        if not self._present <= have:
            self._present &= have
            self._columns()
        cols = [getattr(block, r) if r in self._present else None for r in self._roles]
        a = 0
        while a < n:
            if self._fill == self.ROWS:
                self._write_chunk()
            take = min(n - a, self.ROWS - self._fill)
            for j, v in enumerate(cols):
                if v is not None:
                    self._buf[j, self._fill:self._fill + take] = v[a:a + take]
            self._fill += take
            a += take
        self._n += n

    def _columns(self) -> None:
        for r in ("t", *ROLES):
            setattr(self, r, SpilledColumn(self, self._roles.index(r))
                    if r in self._present else None)

    def _write_chunk(self) -> None:
        assert self._buf is not None
        off = self._chunks * self._buf.nbytes
        data = self._buf.data.cast("B")
        done = 0
        while done < len(data):
            done += os.pwrite(self._fd, data[done:], off + done)
        self._chunks += 1
        self._fill = 0

    @classmethod
    def from_blocks(cls, blocks: Iterable[Signals], dir: str | None = None) -> SpilledSignals:
        """A record of ``blocks`` appended in turn."""
        out = cls(dir)
        for b in blocks:
            out.append(b)
        return out

    def close(self) -> None:
        """Free the file (the record cannot be read after)."""
        self._file.close()

    def __enter__(self) -> SpilledSignals:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- reading -------------------------------------------------------------------
    def __len__(self) -> int:
        return self._n

    @property
    def nbytes(self) -> int:
        """Bytes of the file (and of the chunk held for writing)."""
        return 0 if self._buf is None else (self._chunks + 1) * self._buf.nbytes

    def has(self, role: str) -> bool:
        """True when the optional channel ``role`` is present."""
        return role in self._present

    def read(self, col: int, a: int, b: int, out: npt.NDArray[np.float64]) -> None:
        """Rows ``a:b`` of channel number ``col`` (of the file's) into ``out``."""
        if self._file.closed:
            raise ValueError("the record's temporary file is closed")
        assert self._buf is not None or b <= a
        rows = self.ROWS
        while a < b:
            k = a // rows
            e = min(b, (k + 1) * rows)
            dst = out[:e - a]
            if k == self._chunks:  # the chunk still in the buffer
                assert self._buf is not None
                dst[:] = self._buf[col, a - k * rows:e - k * rows]
            else:
                off = (k * len(self._roles) + col) * rows * 8 + (a - k * rows) * 8
                _pread(self._fd, dst.data.cast("B"), off, "sample")
            out = out[e - a:]
            a = e

    def slice(self, start: int, stop: int) -> Signals:
        """Rows ``start:stop`` as a new block in memory (``stop`` at most the end)."""
        a, b, _ = slice(start, stop).indices(self._n)
        b = max(a, b)

        def col(r: str) -> npt.NDArray[np.float64] | None:
            if r not in self._present:
                return None
            out = np.empty(b - a)
            self.read(self._roles.index(r), a, b, out)
            return out

        return Signals.from_roles({r: col(r) for r in ("t", *ROLES)})

    def in_memory(self) -> Signals:
        """The whole record as :class:`Signals`."""
        return self.slice(0, self._n)


class Sliced(Protocol):
    """A float64 channel read in slices (step 1), block by block: an array, or one
    computed or read back only where sliced (:class:`ColumnLike`)."""

    def __len__(self) -> int: ...

    def __getitem__(self, key: slice, /) -> F64: ...


class ColumnLike(Protocol):
    """A float64 channel as the diagnosis reads it: an array, or a column read back or
    computed where indexed (:class:`SpilledColumn`, the diagnosis's ``Filtered``):
    index it by a slice or sorted rows; ``np.asarray`` makes the whole array."""

    def __len__(self) -> int: ...

    def __getitem__(self, key: Any, /) -> Any: ...

    def __array__(self, dtype: None = None, /, *, copy: bool | None = None) -> F64: ...


class SpilledColumn:
    """One channel of a :class:`SpilledSignals`, read back where indexed: a slice
    (step 1) or sorted row numbers read only those rows' chunks; a row gives a float;
    anything else (``np.asarray``) reads the whole channel."""

    def __init__(self, record: SpilledSignals, col: int) -> None:
        self.record = record
        self.col = col

    def __len__(self) -> int:
        return len(self.record)

    @property
    def shape(self) -> tuple[int]:
        return (len(self.record),)

    def _rows(self, a: int, b: int) -> npt.NDArray[np.float64]:
        out = np.empty(max(b - a, 0))
        self.record.read(self.col, a, b, out)
        return out

    def __array__(self, dtype: Any = None, copy: bool | None = None) -> F64:
        a = self._rows(0, len(self))
        return a if dtype is None else a.astype(dtype)

    def __getitem__(self, key: Any) -> Any:
        n = len(self)
        if isinstance(key, int | np.integer):
            k = int(key) + (n if key < 0 else 0)
            if not 0 <= k < n:
                raise IndexError(f"row {int(key)} of a record of {n}")
            return float(self._rows(k, k + 1)[0])
        if isinstance(key, slice):
            a, b, step = key.indices(n)
            if step == 1:
                return self._rows(a, max(a, b))
        elif (isinstance(key, np.ndarray) and key.dtype.kind in "iu" and key.ndim == 1
              and (len(key) < 2 or bool(np.all(key[1:] >= key[:-1])))):
            out = np.empty(len(key))
            if not len(key):
                return out
            if key[0] < 0 or key[-1] >= n:
                raise IndexError(f"rows {int(key[0])}..{int(key[-1])} of a record of {n}")
            # the rows of each chunk from one read of the chunk's span
            rows = self.record.ROWS
            starts = np.searchsorted(key, np.arange(0, n + rows, rows))
            for lo, hi in zip(starts[:-1], starts[1:], strict=True):
                if hi > lo:
                    a, b = int(key[lo]), int(key[hi - 1]) + 1
                    out[lo:hi] = self._rows(a, b)[key[lo:hi] - a]
            return out
        return np.asarray(self)[key]


# ------------------------------------------------------------------ a packed mask
class SpilledBytes:
    """A byte array (``uint8``) in an anonymous temporary file, written once from the
    front (:meth:`append`) and read back in slices: what a long :class:`PackedMask`
    keeps its bits in (:class:`MaskPacker` moves them there past
    :data:`MaskPacker.MEMORY` bytes). Reads use ``os.preadv`` into fresh arrays (the
    file's pages live in the kernel's page cache, not in the process); the last page
    read is kept, so that reading one byte after another costs no system call each.

    :raises OSError: the temporary file cannot be made or written.
    """

    #: bytes of the page kept from the last read of a single byte
    PAGE = 4096

    def __init__(self, dir: str | None = None) -> None:
        # unlinked at once (no name: it goes with the process); the descriptor is closed
        # when the array is collected or closed
        fd, path = tempfile.mkstemp(prefix="canrls-mask-", dir=dir)
        try:
            os.unlink(path)
        except OSError:  # pragma: no cover - a file just made in a writable directory
            os.close(fd)
            raise
        self._fd = fd
        self._close = weakref.finalize(self, os.close, fd)
        self._n = 0
        self._page: tuple[int, npt.NDArray[np.uint8]] | None = None

    def append(self, data: npt.NDArray[np.uint8]) -> None:
        """Add ``data`` at the end."""
        if not self._close.alive:
            raise ValueError("the mask's temporary file is closed")
        view = np.ascontiguousarray(data, dtype=np.uint8).data.cast("B")
        done = 0
        while done < len(view):
            done += os.pwrite(self._fd, view[done:], self._n + done)
        self._n += len(view)

    def __len__(self) -> int:
        return self._n

    @property
    def nbytes(self) -> int:
        """Bytes in memory (the page kept), not the file's."""
        return 0 if self._page is None else int(self._page[1].nbytes)

    def _read(self, a: int, b: int) -> npt.NDArray[np.uint8]:
        if not self._close.alive:
            raise ValueError("the mask's temporary file is closed")
        out = np.empty(max(b - a, 0), np.uint8)
        _pread(self._fd, out.data.cast("B"), a, "mask")
        return out

    def __getitem__(self, key: int | slice) -> Any:
        if isinstance(key, slice):
            a, b, step = key.indices(self._n)
            if step != 1:
                raise IndexError("SpilledBytes: only step-1 slices")
            return self._read(a, max(a, b))
        k = int(key) + (self._n if key < 0 else 0)
        if not 0 <= k < self._n:
            raise IndexError(f"byte {int(key)} of {self._n}")
        p = k - k % self.PAGE
        if self._page is None or self._page[0] != p:
            self._page = (p, self._read(p, min(self._n, p + self.PAGE)))
        return int(self._page[1][k - p])

    def any(self) -> bool:
        """True when a byte is not zero."""
        return any(bool(self._read(a, min(self._n, a + PackedMask.CHUNK)).any())
                   for a in range(0, self._n, PackedMask.CHUNK))

    def close(self) -> None:
        """Free the file (the bytes cannot be read after)."""
        self._close()


def _bit_count(bits: npt.NDArray[np.uint8]) -> int:
    if hasattr(np, "bitwise_count"):
        return int(np.bitwise_count(bits).sum())
    return int(np.count_nonzero(np.unpackbits(bits)))  # pragma: no cover - numpy < 2


class PackedMask:
    """A boolean mask over a record at one bit a row (:func:`numpy.packbits`); the bits
    of a long one are in a temporary file (:class:`SpilledBytes`, past
    :data:`MaskPacker.MEMORY` bytes), read back where needed.

    Read like the mask it packs where read in pieces: ``m[a:b]`` (a step-1 slice),
    ``m[k]`` and ``m[rows]`` (sorted row numbers) unpack only those rows' bytes;
    ``len``, :meth:`count` (also ``sum()``), :meth:`any`, :meth:`blocks` and
    :meth:`intersect` (``&`` of two masks, packed) go block by block; ``np.asarray(m)``,
    any other index, ``~m`` and ``m & x`` unpack it all (an array). Built from a whole
    mask or block by block (:meth:`from_blocks`, :class:`MaskPacker`).
    """

    #: bytes of bits read at a time where the whole mask is gone through
    CHUNK = 1 << 16

    def __init__(self, bits: npt.NDArray[np.uint8] | SpilledBytes, n: int) -> None:
        self.bits = bits
        self.n = n

    @classmethod
    def pack(cls, mask: npt.ArrayLike) -> PackedMask:
        """``mask`` packed."""
        m = np.asarray(mask, dtype=np.bool_)
        return cls(np.packbits(m), len(m))

    @classmethod
    def from_blocks(cls, blocks: Iterable[npt.ArrayLike]) -> PackedMask:
        """The blocks joined end to end, packed as they come (:class:`MaskPacker`)."""
        packer = MaskPacker()
        for b in blocks:
            packer.append(b)
        return packer.mask()

    def __len__(self) -> int:
        return self.n

    @property
    def shape(self) -> tuple[int]:
        return (self.n,)

    @property
    def spilled(self) -> bool:
        """True when the bits are in a temporary file."""
        return isinstance(self.bits, SpilledBytes)

    def _unpack(self, a: int, b: int) -> npt.NDArray[np.bool_]:
        if b <= a:
            return np.zeros(0, np.bool_)
        byte = a >> 3
        u = np.unpackbits(self.bits[byte:(b + 7) >> 3], count=b - (byte << 3))
        return u[a - (byte << 3):].view(np.bool_)

    def __array__(self, dtype: Any = None, copy: bool | None = None) -> npt.NDArray[Any]:
        a = self._unpack(0, self.n)
        return a if dtype is None else a.astype(dtype)

    def __getitem__(self, key: Any) -> Any:
        if isinstance(key, int | np.integer):
            k = int(key) + (self.n if key < 0 else 0)
            if not 0 <= k < self.n:
                raise IndexError(f"row {int(key)} of a mask of {self.n}")
            return bool((self.bits[k >> 3] >> (7 - (k & 7))) & 1)
        if isinstance(key, slice):
            a, b, step = key.indices(self.n)
            if step == 1:
                return self._unpack(a, max(a, b))
        elif (isinstance(key, np.ndarray) and key.dtype.kind in "iu" and key.ndim == 1
              and (len(key) < 2 or bool(np.all(key[1:] >= key[:-1])))):
            # sorted rows: the bytes of each block of rows they fall in
            out = np.zeros(len(key), np.bool_)
            if not len(key):
                return out
            if key[0] < 0 or key[-1] >= self.n:
                raise IndexError(f"rows {int(key[0])}..{int(key[-1])} of a mask of {self.n}")
            rows = 8 * self.CHUNK
            starts = np.searchsorted(key, np.arange(0, self.n + rows, rows))
            for lo, hi in zip(starts[:-1], starts[1:], strict=True):
                if hi > lo:
                    a, b = int(key[lo]), int(key[hi - 1]) + 1
                    out[lo:hi] = self._unpack(a, b)[key[lo:hi] - a]
            return out
        return np.asarray(self)[key]

    def __invert__(self) -> npt.NDArray[np.bool_]:
        """``~mask`` unpacked (a whole array)."""
        return ~np.asarray(self)

    def __and__(self, other: npt.ArrayLike) -> npt.NDArray[np.bool_]:
        """``mask & other`` unpacked (a whole array; :meth:`intersect` keeps it packed)."""
        return np.asarray(self) & np.asarray(other, dtype=np.bool_)

    __rand__ = __and__

    def intersect(self, other: PackedMask | npt.NDArray[np.bool_]) -> PackedMask:
        """``self & other`` packed, block by block (``other`` as long, packed or not)."""
        if len(other) != self.n:
            raise ValueError(f"masks of {self.n} and {len(other)} rows")
        out = MaskPacker()
        for a, u in self.blocks():
            out.append(u & np.asarray(other[a:a + len(u)], dtype=np.bool_))
        return out.mask()

    def count(self, a: int = 0, b: int | None = None) -> int:
        """True rows in ``a:b`` (default: all)."""
        b = self.n if b is None else min(b, self.n)
        if b <= a:
            return 0
        lo, hi = -(-a // 8), b // 8  # whole bytes inside a:b
        if hi <= lo:
            return int(np.count_nonzero(self._unpack(a, b)))
        whole = sum(_bit_count(self.bits[c:min(hi, c + self.CHUNK)])
                    for c in range(lo, hi, self.CHUNK))
        return (whole + int(np.count_nonzero(self._unpack(a, lo * 8)))
                + int(np.count_nonzero(self._unpack(hi * 8, b))))

    def sum(self) -> int:
        """True rows (as ``ndarray.sum`` of the mask)."""
        return self.count()

    def any(self) -> bool:
        """True when a row is true."""
        return bool(self.bits.any())

    def digest(self) -> bytes:
        """A hash of the rows (equal masks, equal digests), block by block."""
        h = hashlib.blake2b(str(self.n).encode(), digest_size=16)
        for c in range(0, len(self.bits), self.CHUNK):
            h.update(np.asarray(self.bits[c:c + self.CHUNK]).tobytes())
        return h.digest()

    @property
    def nbytes(self) -> int:
        """Bytes in memory (a mask in a temporary file: the page it keeps)."""
        return int(self.bits.nbytes)

    def blocks(self, block: int = 65536) -> Iterator[tuple[int, npt.NDArray[np.bool_]]]:
        """(first row, rows ``a:a+block`` unpacked) over the mask."""
        for a in range(0, self.n, block):
            yield a, self._unpack(a, min(self.n, a + block))


def as_packed(mask: PackedMask | npt.ArrayLike) -> PackedMask:
    """``mask`` as a :class:`PackedMask` (itself if it is one)."""
    return mask if isinstance(mask, PackedMask) else PackedMask.from_blocks([mask])


class MaskPacker:
    """Packs a mask that comes in blocks (:class:`PackedMask`): the last rows of a block
    that do not fill a byte wait for the next block. Past :data:`MEMORY` bytes the bits
    go to a temporary file (:class:`SpilledBytes`), so a mask of any length holds at
    most that much memory; where the file cannot be made or written they stay in memory
    (one warning line)."""

    #: bytes of bits kept in memory before they go to a temporary file (2**19 rows)
    MEMORY = 1 << 16

    def __init__(self) -> None:
        self._parts: list[npt.NDArray[np.uint8]] = []
        self._held = 0  # bytes in _parts
        self._file: SpilledBytes | None = None
        self._memory_only = False
        self._tail = np.zeros(0, np.bool_)
        self._n = 0
        self._done = False

    def append(self, block: npt.ArrayLike) -> None:
        """Add the rows of ``block`` at the end."""
        if self._done:
            raise ValueError("MaskPacker: the mask was taken with its file")
        b = np.asarray(block, dtype=np.bool_)
        m = np.concatenate([self._tail, b]) if len(self._tail) else b
        whole = len(m) - len(m) % 8
        part = np.packbits(m[:whole])
        self._parts.append(part)
        self._held += len(part)
        self._tail = m[whole:].copy()
        self._n += len(b)
        if self._held > self.MEMORY and not self._memory_only:
            self._flush()

    def _flush(self) -> None:
        i = 0  # parts written
        try:
            if self._file is None:
                self._file = SpilledBytes()
            for i, p in enumerate(self._parts):  # noqa: B007 - i read on failure
                self._file.append(p)
            i = len(self._parts)
        except OSError as e:
            global _mask_warned
            if not _mask_warned:  # once: a long diagnosis makes many masks
                _log.warning("cannot write a temporary file for a mask in %s (%s): masks "
                             "are kept in memory", tempfile.gettempdir(), e)
                _mask_warned = True
            self._memory_only = True
            if self._file is not None:
                # the bytes in the file back in memory, then the parts not written
                self._parts = [self._file[0:len(self._file)], *self._parts[i:]]
                self._file.close()
                self._file = None
            return
        self._parts = []
        self._held = 0

    def mask(self) -> PackedMask:
        """The rows appended so far, packed. A mask whose bits went to a temporary file
        takes the file: the packer cannot be used again (``ValueError``)."""
        if self._done:
            raise ValueError("MaskPacker: the mask was taken with its file")
        last = np.packbits(self._tail)
        if self._file is None:
            return PackedMask(np.concatenate([*self._parts, last]), self._n)
        self._parts.append(last)
        self._tail = np.zeros(0, np.bool_)
        self._flush()
        self._done = True
        if self._file is None:  # the file failed: in memory
            return PackedMask(np.concatenate(self._parts), self._n)
        return PackedMask(self._file, self._n)


def join_blocks(blocks: Iterable[Signals]) -> Signals:
    """:meth:`Signals.concat` of ``blocks`` (the same values), without keeping the larger
    arrays the blocks' columns are views of, one channel's blocks joined at a time and
    freed once joined: the peak is the samples and one channel more."""
    cols: dict[str, list[F64 | None]] = {r: [] for r in ("t", *ROLES)}
    for b in blocks:
        for r, parts in cols.items():
            v = getattr(b, r)
            # a copy: the block's columns are views of larger arrays, kept alive by them
            parts.append(None if v is None else np.array(v, dtype=np.float64))
    if not cols["t"]:
        return Signals.concat([])
    out: dict[str, F64 | None] = {}
    for r in list(cols):
        parts = cols.pop(r)
        whole = [v for v in parts if v is not None]
        out[r] = np.concatenate(whole) if len(whole) == len(parts) else None
        del parts, whole
    return Signals.from_roles(out)


def spill_blocks(blocks: Iterable[Signals]) -> Signals | SpilledSignals:
    """``blocks`` joined in a temporary file (:class:`SpilledSignals`), or in memory
    (:func:`join_blocks`) with one warning line when the file cannot be made or written (a
    read-only or full temporary directory): the rows written so far are read back,
    none is lost."""
    blocks = iter(blocks)
    try:
        rec = SpilledSignals()
    except OSError as e:
        _log.warning("cannot make a temporary file for the samples in %s (%s): they are "
                    "kept in memory", tempfile.gettempdir(), e)
        return join_blocks(blocks)
    try:
        for b in blocks:
            try:
                rec.append(b)
            except OSError as e:
                _log.warning("cannot write the temporary file of the samples in %s (%s): "
                            "they are kept in memory", tempfile.gettempdir(), e)
                kept = rec.in_memory()
                rec.close()
                return join_blocks(itertools.chain([kept, b], blocks))
    except BaseException:
        rec.close()  # a log that cannot be read: the file goes at once
        raise
    return rec
