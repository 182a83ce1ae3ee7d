"""Volumes read on demand (out of core): a bricked encode reads each brick's box when it runs, so
that no process holds the whole volume.

:class:`ArraySource` names where the voxels are (a memory-mapped raw/``.npy``/contiguous HDF5
file, a chunked HDF5 or netCDF-4 dataset, a Zarr array) as plain, picklable data: a Dask worker
reopens it itself. :class:`LazyValues` and :class:`LazyMask` are a :class:`~warpgauss.field.analysis.Field`'s
``values`` and ``mask`` read that way, normalised by the min/max of one streaming pass
(:func:`warpgauss.field.analysis.normalise` with ``lazy=True``).
"""

from __future__ import annotations

import math
import os
import shutil
import tempfile
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import WarpgaussError

_OPEN: dict[tuple, Any] = {}  # this process's open handles, by source
TAKE_SLAB = 128  # z-planes per read when gathering sampled voxels
GATHER_GAP = 1024  # sampled voxels of a raw file this close read together (4 KiB of float32)


def valid_mask(s: np.ndarray, fill_value: float | None) -> np.ndarray:
    ok = np.isfinite(s) if np.issubdtype(s.dtype, np.floating) else np.ones(s.shape, bool)
    if fill_value is not None:
        if np.issubdtype(s.dtype, np.floating) and not abs(fill_value) <= float(np.finfo(s.dtype).max):
            return ok  # no finite value of this dtype equals it (and casting it would overflow)
        ok &= s != fill_value
    return ok


@dataclass(frozen=True)
class ArraySource:
    """Where a 3D array's voxels are: ``kind`` "memmap" (``path``, ``offset``, ``dtype`` with its
    byte order), "hdf5" (``path``, dataset ``key``, leading length-1 axes dropped) or "zarr"
    (``path``, array ``key`` or None); ``shape`` is ``(z, y, x)``."""

    kind: str
    path: str
    shape: tuple[int, int, int]
    dtype: str
    offset: int = 0
    key: str | None = None

    def open(self):
        h = _OPEN.get(self._id())
        if h is None:
            h = _OPEN[self._id()] = self._open()
        return h

    def _id(self) -> tuple:
        return (self.kind, self.path, self.key, self.offset)

    def _open(self):
        if self.kind == "hdf5":
            import h5py

            ds = h5py.File(self.path, "r")[self.key]
            return _Lead(ds, ds.ndim - 3)
        if self.kind == "zarr":
            import zarr

            z: Any = zarr.open(self.path, mode="r")  # a group (indexed by name) or an array
            return z if self.key is None else z[self.key]
        raise ValueError(f"unknown array source kind {self.kind!r}")

    def read(self, key) -> np.ndarray:
        """A copy of the voxels at ``key`` (slices), in native byte order. A memory-mapped file is
        mapped for this read only: pages left mapped would count in the process's resident memory
        until the whole file had been."""
        if self.kind == "memmap":
            m = np.memmap(self.path, dtype=np.dtype(self.dtype), mode="r", offset=self.offset, shape=self.shape)
            a = np.array(m[key], dtype=m.dtype.newbyteorder("="))
            del m
            return a
        a = np.asarray(self.open()[key])
        return a if a.dtype.isnative else a.astype(a.dtype.newbyteorder("="))

    def gather(self, idx: np.ndarray) -> np.ndarray | None:
        """The voxels at linear indices ``idx`` (in that order, native byte order) where the source
        can read them one by one: a raw file by positioned reads, in file order, neighbours within
        :data:`GATHER_GAP` voxels in one read (500,000 voxels of a 512^3 file: 0.13 s against
        0.93 s by z-slabs, on two cores; the evaluation of a 2048^3 file: 2.4 s against 34 s).
        Not through a mapping: the kernel's read-ahead mapped the whole 32 GiB file into this
        process's resident memory against a 16 GiB host limit. None for chunked formats."""
        if self.kind != "memmap":
            return None
        dt = np.dtype(self.dtype)
        flat = np.asarray(idx, np.int64).reshape(-1)
        order = np.argsort(flat, kind="stable")  # in file order
        pos = flat[order]
        out = np.empty(flat.size, dt.newbyteorder("="))
        if pos.size == 0:
            return out
        total = math.prod(self.shape)
        if pos[0] < 0 or pos[-1] >= total:
            raise IndexError(f"voxel index out of range 0..{total - 1}")
        starts = np.concatenate([[0], np.flatnonzero(np.diff(pos) > GATHER_GAP) + 1])
        ends = np.append(starts[1:], pos.size)
        with open(self.path, "rb", buffering=0) as fh:
            fd = fh.fileno()
            for a, b in zip(starts.tolist(), ends.tolist()):
                lo, hi = int(pos[a]), int(pos[b - 1]) + 1
                span = np.frombuffer(os.pread(fd, (hi - lo) * dt.itemsize, self.offset + lo * dt.itemsize), dt)
                out[order[a:b]] = span[pos[a:b] - lo]
        return out


class _Lead:
    """An HDF5 dataset with ``lead`` leading length-1 axes, indexed as 3D."""

    def __init__(self, ds, lead: int):
        self.ds, self.lead = ds, lead

    def __getitem__(self, key):
        key = key if isinstance(key, tuple) else (key,)
        return self.ds[(0,) * self.lead + key]


def source_of(data) -> ArraySource | None:
    """The :class:`ArraySource` of an array a reader returned (None: an array in memory)."""
    if isinstance(data, np.memmap) and data.base is not None and getattr(data, "filename", None) is not None:
        if data.ndim == 3 and data.flags.c_contiguous:
            return ArraySource("memmap", str(data.filename), tuple(int(s) for s in data.shape), data.dtype.str, int(data.offset))  # type: ignore[arg-type]
    if isinstance(data, Lazy3D):
        return data.source
    return None


class Lazy3D:
    """A reader's unread array (chunked HDF5, Zarr): shape, dtype and slicing only."""

    def __init__(self, source: ArraySource):
        self.source = source
        self.shape = source.shape
        self.dtype = np.dtype(source.dtype)
        self.ndim = 3
        self.size = int(np.prod(self.shape, dtype=np.int64))

    def __getitem__(self, key):
        return self.source.read(key)


def _key(key) -> tuple:
    return key if isinstance(key, tuple) else (key,)


@dataclass(frozen=True)
class LazyValues:
    """Normalised values read on demand: ``v[slices]`` is float32 with invalid voxels 0."""

    source: ArraySource
    plan: Any  # analysis.NormPlan (plain numbers)
    fill_value: float | None
    check_valid: bool

    @property
    def shape(self) -> tuple[int, int, int]:
        return self.source.shape

    @property
    def size(self) -> int:
        return int(np.prod(self.shape, dtype=np.int64))

    ndim = 3
    dtype = np.dtype(np.float32)

    def __getitem__(self, key) -> np.ndarray:
        s = self.source.read(_key(key))
        v = self.plan.apply(s)
        if self.check_valid:
            v[~valid_mask(s, self.fill_value)] = 0.0
        return v

    def take_flat(self, idx: np.ndarray) -> np.ndarray:
        """The values at linear voxel indices ``idx``: gathered where the source can
        (:meth:`ArraySource.gather`), else read z-slab by z-slab."""
        s = self.source.gather(idx)
        if s is None:
            return _take(self, idx, np.float32)
        v = self.plan.apply(s)
        if self.check_valid:
            v[~valid_mask(s, self.fill_value)] = 0.0
        return v


@dataclass(frozen=True)
class LazyMask:
    """Validity read on demand (True: usable)."""

    source: ArraySource
    fill_value: float | None

    @property
    def shape(self) -> tuple[int, int, int]:
        return self.source.shape

    ndim = 3

    def __getitem__(self, key) -> np.ndarray:
        return valid_mask(self.source.read(_key(key)), self.fill_value)

    def take_flat(self, idx: np.ndarray) -> np.ndarray:
        s = self.source.gather(idx)
        return _take(self, idx, bool) if s is None else valid_mask(s, self.fill_value)


def _take(arr, idx: np.ndarray, dtype) -> np.ndarray:
    nz, ny, nx = arr.shape
    plane = ny * nx
    out = np.empty(idx.size, dtype)
    z = idx // plane
    order = np.argsort(z, kind="stable")
    zs = z[order]
    for z0 in range(0, nz, TAKE_SLAB):
        lo, hi = np.searchsorted(zs, [z0, z0 + TAKE_SLAB])
        if lo == hi:
            continue
        slab = arr[z0 : min(nz, z0 + TAKE_SLAB)].reshape(-1)
        sel = order[lo:hi]
        out[sel] = slab[idx[sel] - z0 * plane]
    return out


def is_lazy(values) -> bool:
    return isinstance(values, LazyValues)


def require_source(data, what: str) -> ArraySource:
    src = source_of(data)
    if src is None:
        raise WarpgaussError(f"{what} cannot be read lazily (it is in memory); it must fit this machine's memory as a whole")
    return src


class Shared(Lazy3D):
    """An in-memory array written once to a temporary ``.npy`` file (:func:`shared`), so that the
    Dask workers of this machine read it box by box instead of receiving it through the task
    graph; picklable as its :class:`ArraySource` alone. ``array()``: the whole, memory-mapped."""

    def array(self) -> np.memmap:
        s = self.source
        return np.memmap(s.path, dtype=np.dtype(s.dtype), mode="r", offset=s.offset, shape=s.shape)

    def __reduce__(self):
        return (Shared, (self.source,))


@contextmanager
def shared(arrays: Sequence[np.ndarray | None]) -> Iterator[list[Shared | None]]:
    """Each 3D array of ``arrays`` (None stays None) written to a ``.npy`` file in a temporary
    folder (``$TMPDIR``: the page cache keeps it in memory while there is room), offered as a
    :class:`Shared`; the folder is deleted on exit. For the workers of a local cluster, which can
    open the files this process writes (see :func:`warpgauss.encoding.scale.cluster.is_local`)."""
    with shared_folder() as folder:
        out: list[Shared | None] = []
        for i, a in enumerate(arrays):
            if a is None:
                out.append(None)
                continue
            path = os.path.join(folder, f"{i}.npy")
            np.save(path, np.ascontiguousarray(a))
            m = np.load(path, mmap_mode="r")
            src = source_of(m)
            assert src is not None, "np.load(mmap_mode='r') gives a memmap"
            del m
            out.append(Shared(src))
        yield out


@contextmanager
def shared_folder() -> Iterator[str]:
    """A temporary folder (in ``$TMPDIR``) for files this machine's processes share, deleted on exit."""
    folder = tempfile.mkdtemp(prefix="warpgauss-shared-")
    try:
        yield folder
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def opened(item):
    """A series item as :func:`warpgauss.encode` takes it: a :class:`Shared` array memory-mapped,
    anything else as it is."""
    return item.array() if isinstance(item, Shared) else item
