"""Windows of an uncompressed zarr v3 array read and written as its chunk files.

zarr decodes every chunk a window touches, whole, through its event loop: a
tile task's halo needs a tenth of the chunks above and below its own (4 MB
each) and pays for all of them, and each chunk costs milliseconds of Python
beside the tasks' own.  The run's scratch arrays (the ingested inputs, the labels, the per-tile
tables) are uncompressed, so their chunk files hold the values themselves:
:class:`ChunkFiles` reads only the rows of each chunk file that a window
needs and writes whole chunk files, in the layout zarr reads and writes (the
raw values in C order, little-endian, edge chunks padded to the full chunk
shape, a chunk of the fill value not written, a missing chunk read as the
fill value).  Any other array (compressed,
sharded, not on the local file system) is left to zarr: see
:func:`chunk_files`.
"""

import itertools
import os
import uuid
from pathlib import Path

import numpy as np

__all__ = ["ChunkFiles", "chunk_files"]


def chunk_files(array):
    """:class:`ChunkFiles` over the zarr array ``array`` when its chunk files
    are its raw values (zarr v3, local store, regular chunks, no filter,
    compressor or sharding); else ``array`` itself."""
    from zarr.codecs import BytesCodec
    from zarr.core.chunk_grids import RegularChunkGrid
    from zarr.storage import LocalStore

    metadata = array.metadata
    codecs = getattr(metadata, "codecs", ())  # zarr v3 only; one codec: no filter, compressor or sharding
    plain = (getattr(metadata, "zarr_format", None) == 3 and isinstance(array.store, LocalStore)
             and len(codecs) == 1 and isinstance(codecs[0], BytesCodec)
             and (codecs[0].endian is None or codecs[0].endian.value == "little")
             and isinstance(metadata.chunk_grid, RegularChunkGrid))
    return ChunkFiles(array) if plain else array


class ChunkFiles:
    """Basic indexing (integers and slices of step 1) of an uncompressed
    zarr v3 array through its chunk files; see the module's docstring.

    As with zarr, concurrent writes must not share a chunk: a write that
    covers part of a chunk reads the chunk, changes it and writes it back.
    """

    def __init__(self, array):
        self.shape = tuple(array.shape)
        self.chunks = tuple(array.chunks)
        self.ndim = len(self.shape)
        self.dtype = np.dtype(array.dtype)
        self._stored = self.dtype.newbyteorder("<")
        self.fill_value = np.asarray(array.fill_value, self.dtype)
        self._root = Path(array.store.root, array.path)
        self._key = array.metadata.chunk_key_encoding.encode_chunk_key

    def _bounds(self, key):
        """``key`` as (start, stop) per axis and the axes an integer drops."""
        key = key if isinstance(key, tuple) else (key,)
        if any(k is Ellipsis for k in key):
            at = key.index(Ellipsis)
            key = key[:at] + (slice(None),) * (self.ndim - len(key) + 1) + key[at + 1:]
        if len(key) > self.ndim:
            raise IndexError(f"too many indices for an array of {self.ndim} dimensions: {key}")
        key = key + (slice(None),) * (self.ndim - len(key))
        bounds, dropped = [], []
        for axis, (k, n) in enumerate(zip(key, self.shape)):
            if isinstance(k, slice):
                start, stop, step = k.indices(n)
                if step != 1:
                    raise IndexError(f"only slices of step 1 are supported, got {k}")
                bounds.append((start, max(start, stop)))
            elif isinstance(k, (int, np.integer)) and not isinstance(k, (bool, np.bool_)):
                i = int(k) + n if k < 0 else int(k)
                if not 0 <= i < n:
                    raise IndexError(f"index {k} is out of bounds for axis {axis} of size {n}")
                bounds.append((i, i + 1))
                dropped.append(axis)
            else:
                raise IndexError(f"only integers and slices are supported, got {k!r}")
        return bounds, tuple(dropped)

    def _parts(self, bounds):
        """Each chunk a window touches: (chunk index, the window's part of it
        in chunk coordinates, the same part in window coordinates)."""
        ranges = [range(a // c, -(-b // c)) for (a, b), c in zip(bounds, self.chunks)]
        for index in itertools.product(*ranges):
            inside, window = [], []
            for i, (a, b), c in zip(index, bounds, self.chunks):
                lo, hi = max(a, i * c), min(b, (i + 1) * c)
                inside.append(slice(lo - i * c, hi - i * c))
                window.append(slice(lo - a, hi - a))
            yield index, tuple(inside), tuple(window)

    def _path(self, index):
        return self._root / self._key(index)

    def _read_rows(self, index, rows):
        """Rows ``rows`` (a slice of the first axis) of a chunk, or None when
        the chunk was never written."""
        per_row = int(np.prod(self.chunks[1:], dtype=np.int64))
        path, count = self._path(index), (rows.stop - rows.start) * per_row
        try:
            values = np.fromfile(path, self._stored, count=count, offset=rows.start * per_row * self._stored.itemsize)
        except FileNotFoundError:
            return None
        if values.size != count:
            raise OSError(f"{path}: chunk file cut short (rows {rows.start}-{rows.stop} of a chunk of "
                          f"{self.chunks[0]} rows asked, {values.size} of {count} values there)")
        return values.reshape((rows.stop - rows.start,) + self.chunks[1:])

    def __getitem__(self, key):
        bounds, dropped = self._bounds(key)
        out = np.empty([b - a for a, b in bounds], self.dtype)
        if out.size:
            for index, inside, window in self._parts(bounds):
                rows = self._read_rows(index, inside[0])
                out[window] = self.fill_value if rows is None else rows[(slice(None),) + inside[1:]]
        return out[tuple(0 if axis in dropped else slice(None) for axis in range(self.ndim))]

    def __setitem__(self, key, value):
        bounds, dropped = self._bounds(key)
        shape = [b - a for a, b in bounds]
        value = np.asarray(value, self.dtype)
        if dropped and value.ndim == self.ndim - len(dropped):
            value = np.expand_dims(value, dropped)
        value = np.broadcast_to(value, shape)
        if not value.size:
            return
        for index, inside, window in self._parts(bounds):
            whole = all(s.start == 0 and s.stop == min(c, n - i * c)
                        for s, i, c, n in zip(inside, index, self.chunks, self.shape))
            chunk = None if whole else self._read_rows(index, slice(0, self.chunks[0]))
            chunk = np.full(self.chunks, self.fill_value, self._stored) if chunk is None else chunk
            chunk[inside] = value[window]
            if self._empty(chunk):  # as zarr: a chunk of the fill value is no file
                self._path(index).unlink(missing_ok=True)
            else:
                self._write(index, chunk)

    def _empty(self, chunk):
        """Whether ``chunk`` is the fill value throughout, as zarr tells: any NaN
        for a NaN fill, else bit for bit (-0.0 is not 0.0)."""
        if self.dtype.kind in "fc" and np.isnan(self.fill_value):
            return bool(np.isnan(chunk).all())
        bits = f"V{self._stored.itemsize}"
        return bool((chunk.view(bits) == np.asarray(self.fill_value, self._stored).view(bits)).all())

    def _write(self, index, chunk):
        """Replace a chunk's file at once: a reader sees the old chunk or the new."""
        path = self._path(index)
        path.parent.mkdir(parents=True, exist_ok=True)
        partial = path.with_name(f".{path.name}.{uuid.uuid4().hex}.partial")
        try:  # created as zarr creates its files: mode 0666 less the umask
            with os.fdopen(os.open(partial, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666), "wb") as file:
                file.write(np.ascontiguousarray(chunk, self._stored).data)
            os.replace(partial, path)
        except BaseException:
            partial.unlink(missing_ok=True)
            raise
