"""Scratch arrays read and written as their chunk files agree with zarr, both ways."""

import os
import stat

import numpy as np
import pytest
import zarr
import zarr.codecs

from rsmb import tiles


def _array(path, shape, chunks, dtype, fill, **kw):
    return zarr.create_array(store=str(path), shape=shape, chunks=chunks, dtype=dtype, fill_value=fill,
                             zarr_format=3, **kw)


def _key(rng, shape):
    key = []
    for n in shape:
        if rng.random() < 0.2:
            key.append(int(rng.integers(-n, n)))
        else:
            a, b = sorted(int(v) for v in rng.integers(0, n + 1, 2))
            key.append(slice(a, b))
    return tuple(key)


@pytest.mark.parametrize("shape, chunks, dtype, fill", [
    ((37, 53), (8, 16), "float32", np.nan),  # edge chunks in both axes
    ((37, 5, 3), (10, 1, 3), "float32", np.nan),  # a per-tile table of rows
    ((3, 4, 6, 2), (1, 1, 6, 2), "float64", np.nan),
    ((50, 40), (16, 16), "int32", 0),
    ((29, 31), (7, 9), "uint8", 255),
    ((50, 3), (50, 3), "float32", np.nan),  # one chunk
])
def test_chunk_files_read_and_write_what_zarr_does(tmp_path, shape, chunks, dtype, fill):
    rng = np.random.default_rng(1)
    array = _array(tmp_path / "a.zarr", shape, chunks, dtype, fill, compressors=None)
    files = tiles.chunk_files(array)
    assert isinstance(files, tiles.ChunkFiles) and files.shape == shape
    truth = np.full(shape, fill, dtype)
    for k in range(40):
        key = _key(rng, shape)
        values = (rng.random(truth[key].shape) * 100).astype(dtype)
        (files if k % 2 else array)[key] = values  # each written by the other in turn
        truth[key] = values
        window = tuple(slice(*sorted(int(v) for v in rng.integers(0, n + 1, 2))) for n in shape)
        assert np.array_equal(files[window], truth[window], equal_nan=True)
        assert np.array_equal(array[window], truth[window], equal_nan=True)
        assert np.array_equal(files[key], truth[key], equal_nan=True)
    assert np.array_equal(files[...], truth, equal_nan=True)
    assert np.array_equal(files[2:-3, ...], truth[2:-3, ...], equal_nan=True)
    files[:] = fill  # chunks of the fill value are removed, as zarr does
    assert np.array_equal(array[:], np.full(shape, fill, dtype), equal_nan=True)
    assert not [p for p in (tmp_path / "a.zarr").rglob("*") if p.is_file() and p.name != "zarr.json"]


def test_chunk_files_read_only_the_rows_a_window_needs_and_write_whole_files(tmp_path):
    array = _array(tmp_path / "a.zarr", (64, 64), (32, 32), "float32", np.nan, compressors=None)
    files = tiles.chunk_files(array)
    files[:32, :32] = 1.0
    chunk = tmp_path / "a.zarr" / "c" / "0" / "0"
    assert chunk.stat().st_size == 32 * 32 * 4
    assert not (tmp_path / "a.zarr" / "c" / "0" / "1").exists()  # never written: the fill value
    assert np.isnan(files[30:34, 30:34][2:, :]).all() and (files[30:32, 30:32] == 1).all()
    chunk.write_bytes(chunk.read_bytes()[:4 * 32 * 4])  # a chunk cut short: its first rows still read
    assert (files[0:4, :32] == 1).all()
    with pytest.raises(OSError, match="cut short"):
        files[0:8, :32]


def test_chunk_files_index_as_numpy_does(tmp_path):
    array = _array(tmp_path / "a.zarr", (6, 7, 2), (4, 4, 2), "float32", np.nan, compressors=None)
    files = tiles.chunk_files(array)
    values = np.arange(84, dtype=np.float32).reshape(6, 7, 2)
    files[...] = values
    for key in [(1,), (-1, 2), (slice(1, 5), -7), (Ellipsis, 0), (2, Ellipsis, 1), (slice(5, 2),)]:
        assert np.array_equal(files[key], values[key]), key
    files[3, 2] = [-1, -2]
    values[3, 2] = [-1, -2]
    files[:, 0, 1] = 5
    values[:, 0, 1] = 5
    assert np.array_equal(files[...], values)
    for key in [(slice(0, 4, 2),), (6,), (0, 0, 0, 0), ([1, 2],), (True,)]:
        with pytest.raises(IndexError):
            files[key]


def test_chunk_files_keep_what_zarr_keeps(tmp_path):
    """A chunk of -0.0 under a fill of 0.0 is written (zarr compares bits),
    and chunk files are created as zarr creates its files (the umask's mode)."""
    array = _array(tmp_path / "a.zarr", (4, 4), (2, 2), "float32", 0.0, compressors=None)
    files = tiles.chunk_files(array)
    files[:2, :2] = -0.0
    files[2:, 2:] = 0.0
    assert np.signbit(array[:2, :2]).all() and not np.signbit(array[2:, 2:]).any()
    written = sorted(p for p in (tmp_path / "a.zarr").rglob("*") if p.is_file() and p.name != "zarr.json")
    assert [p.relative_to(tmp_path / "a.zarr").as_posix() for p in written] == ["c/0/0"]
    umask = os.umask(0)
    os.umask(umask)
    assert stat.S_IMODE(written[0].stat().st_mode) == 0o666 & ~umask


@pytest.mark.parametrize("kw", [{}, {"compressors": None, "shards": (4, 4)},
                                {"compressors": None, "filters": [zarr.codecs.TransposeCodec(order=(1, 0))]}])
def test_other_arrays_are_left_to_zarr(tmp_path, kw):
    """Compressed, sharded or filtered arrays: their chunk files are not their values."""
    array = _array(tmp_path / "a.zarr", (8, 8), (2, 2) if "shards" in kw else (4, 4), "float32", 0.0, **kw)
    assert tiles.chunk_files(array) is array
