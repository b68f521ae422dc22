"""Whole views of a per-view array read straight from its shard files (docs/spec.md §9.1).

Training reads a few per-view arrays of every view of every batch. zarr reads one inner
chunk of a sharded array in about a millisecond whatever its size (the call crosses to
zarr's event-loop thread, and the shard index read, the chunk read and the decode each hop
to a thread pool): 20 times the file reads and the decode themselves for an 80×60 view's
depth. :class:`ShardReader` reads the same bytes as zarr's sharding codec lays them out
(zarr v3 ``sharding_indexed``): each shard file holds its inner chunks' encoded bytes, then
the index, per inner chunk in C order its byte offset and length (uint64 little-endian;
both 2⁶⁴ − 1 for a chunk never written, which reads as the fill value) followed by the
index's CRC32C; a shard file that is not there holds fill values only. Each shard's index is
read once and kept (a store being read is complete: its files no longer change).

Only the layout the store writer makes is read so (:meth:`ShardReader.of`): one view per
inner chunk, the index at the end, a ``bytes`` serialiser and at most one Blosc or zstd
compressor; for any other array (strings, another codec chain) it gives None and the
caller reads through zarr. A file that cannot be decoded raises :class:`ShardDamage`; whether
a missing one holds fill values or is damage too is the caller's to tell (``missing``).
"""

from __future__ import annotations

import os
from typing import TYPE_CHECKING, Callable, Sequence

import numpy as np

if TYPE_CHECKING:
    import zarr

#: the offset and length of an inner chunk that was never written
_EMPTY = 2**64 - 1
_CRC_BYTES = 4


class ShardDamage(Exception):
    """A shard file that is not as its array's codecs wrote it; ``shard`` is its number."""

    def __init__(self, shard: int, reason: str):
        super().__init__(reason)
        self.shard = shard


def local_ranges(path: str, ranges: Sequence[tuple[int, int]]) -> list[bytes]:
    """Byte ranges ``(start, length)`` of a local file (a negative start counts from its end);
    FileNotFoundError when there is no file."""
    fd = os.open(path, os.O_RDONLY)
    try:
        size = None
        out = []
        for start, length in ranges:
            if start < 0:
                size = os.fstat(fd).st_size if size is None else size
                start = max(size + start, 0)
            out.append(os.pread(fd, length, start))
        return out
    finally:
        os.close(fd)


def fsspec_ranges(fs) -> Callable[[str, Sequence[tuple[int, int]]], list[bytes]]:
    """:func:`local_ranges` on an fsspec filesystem (one request per range)."""

    def read(path: str, ranges: Sequence[tuple[int, int]]) -> list[bytes]:
        return [fs.cat_file(path, start=start, end=None if start < 0 else start + length)
                for start, length in ranges]

    return read


def _endian(codec) -> str | None:
    """A ``bytes`` codec's byte order: ``little``, ``big`` or None (one-byte values)."""
    return getattr(codec.endian, "value", codec.endian)


class ShardReader:
    """Reads whole views (rows along the first axis) of one sharded per-view array.

    array   : the zarr array, for its metadata only
    path    : the shard file of shard ``k``: ``path(k)``
    read    : the byte ranges of a file (:func:`local_ranges`, :func:`fsspec_ranges`)
    missing : called with the number of a shard whose file is not there: it raises when
              that is damage, and the shard's views read as the fill value when it returns
    """

    def __init__(self, array: "zarr.Array", path: Callable[[int], str], read: Callable, missing: Callable,
                 decode, checksum: bool, dtype: np.dtype):
        self.shape, self.per = tuple(array.shape), int(array.shards[0])
        self.dtype, self.fill = dtype, np.asarray(array.fill_value, dtype=dtype)
        self.path, self.read, self.missing = path, read, missing
        self.decode, self.checksum = decode, checksum
        self.view_bytes = int(np.prod(self.shape[1:], dtype=np.int64)) * dtype.itemsize
        self._index: dict[int, np.ndarray | None] = {}

    @classmethod
    def of(cls, array: "zarr.Array", path: Callable[[int], str],
           read: Callable[[str, Sequence[tuple[int, int]]], list[bytes]],
           missing: Callable[[int], None]) -> "ShardReader | None":
        """A reader of ``array`` when it has the store writer's layout (module docstring), else None."""
        from zarr.codecs import BloscCodec, BytesCodec, Crc32cCodec, ShardingCodec, ZstdCodec
        from zarr.codecs.sharding import ShardingCodecIndexLocation

        meta = array.metadata
        if getattr(meta, "zarr_format", None) != 3 or len(meta.codecs) != 1 or not array.shards:
            return None
        sharding = meta.codecs[0]
        if not isinstance(sharding, ShardingCodec) or sharding.index_location != ShardingCodecIndexLocation.end:
            return None
        if tuple(array.chunks) != (1, *array.shape[1:]) or tuple(array.shards[1:]) != tuple(array.shape[1:]):
            return None
        index = tuple(sharding.index_codecs)
        if not index or not isinstance(index[0], BytesCodec) or _endian(index[0]) not in ("little", None):
            return None
        if index[1:] not in ((), (Crc32cCodec(),)):
            return None
        serialiser, *compressors = sharding.codecs
        try:
            dtype = np.dtype(array.dtype)
        except TypeError:
            return None
        if not isinstance(serialiser, BytesCodec) or dtype.kind not in "biuf" or len(compressors) > 1:
            return None
        dtype = dtype.newbyteorder({"little": "<", "big": ">"}.get(_endian(serialiser), "="))
        decode = None
        if compressors:
            import numcodecs

            if isinstance(compressors[0], BloscCodec):
                decode = numcodecs.Blosc().decode
            elif isinstance(compressors[0], ZstdCodec):
                decode = numcodecs.Zstd().decode
            else:
                return None
        return cls(array, path, read, missing, decode, bool(index[1:]), dtype)

    def __call__(self, rows: Sequence[int], out: np.ndarray | None = None) -> np.ndarray:
        """Rows ``rows`` (in bounds, any order, repeats allowed) as an array
        ``(len(rows), *shape[1:])`` of the array's dtype, native byte order (written into
        ``out`` when given). Raises :class:`ShardDamage`, or what ``missing`` raises."""
        rows = np.asarray(rows, dtype=np.int64)
        if out is None:
            out = np.empty((len(rows), *self.shape[1:]), dtype=self.dtype.newbyteorder("="))
        shards = rows // self.per
        for shard in np.unique(shards):
            at = np.flatnonzero(shards == shard)
            self._read_shard(int(shard), rows[at] % self.per, at, out)
        return out

    def _read_shard(self, shard: int, chunks: np.ndarray, at: np.ndarray, out: np.ndarray) -> None:
        path = self.path(shard)
        index = self._shard_index(shard, path)
        if index is None:  # a shard of fill values only: never written
            out[at] = self.fill
            return
        starts, lengths = index[chunks, 0], index[chunks, 1]
        written = starts != _EMPTY
        out[at[~written]] = self.fill
        if not written.any():
            return
        ranges = [(int(s), int(n)) for s, n in zip(starts[written], lengths[written])]
        for data, row in zip(self.read(path, ranges), at[written]):
            out[row] = self._decode(shard, data)

    def _decode(self, shard: int, data: bytes) -> np.ndarray:
        """One view from its chunk's bytes."""
        if self.decode is None:
            raw = data
        else:
            try:
                raw = self.decode(data)
            except Exception as e:  # numcodecs raises RuntimeError, ValueError, ... for torn bytes
                raise ShardDamage(shard, str(e).split(". ")[0] or type(e).__name__) from None
        if len(raw) != self.view_bytes:
            raise ShardDamage(shard, f"a chunk of {len(raw)} bytes where a view has {self.view_bytes}")
        return np.frombuffer(raw, dtype=self.dtype).reshape(self.shape[1:])

    def _shard_index(self, shard: int, path: str) -> np.ndarray | None:
        """(per, 2) uint64 offsets and lengths of the shard's chunks; None: no file, a shard
        of fill values only (``missing`` let it be)."""
        if shard not in self._index:
            size = self.per * 16 + (_CRC_BYTES if self.checksum else 0)
            try:
                (data,) = self.read(path, [(-size, size)])
            except FileNotFoundError:
                self.missing(shard)
                self._index[shard] = None
                return None
            if len(data) != size:
                raise ShardDamage(shard, f"{len(data)} bytes, fewer than its index's {size}")
            if self.checksum:
                import google_crc32c

                body, crc = data[:-_CRC_BYTES], data[-_CRC_BYTES:]
                if np.uint32(google_crc32c.value(body)).tobytes() != crc:
                    raise ShardDamage(shard, "its index does not match its checksum")
                data = body
            index = np.frombuffer(data, dtype="<u8").reshape(self.per, 2)
            self._index[shard] = index
        return self._index[shard]
