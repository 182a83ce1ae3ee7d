"""Zarr stores (a ``.zarr`` directory): an array, or a named array of a group; read by chunks."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ..errors import WarpgaussError
from .common import ReadResult, attr_xyz, check_declared, check_dtype, check_shape, fill_attr, first_line, pick_array


def read_zarr(path: Path, *, dataset=None, stride: int = 1, lazy: bool = False, max_voxels: int | None = None, **_) -> ReadResult:
    """The store's array, or the group's ``dataset`` (default: the first 3D array, by name);
    ``[z, y, x]`` order assumed. ``lazy``: left unread, each brick reads its box."""
    try:
        import zarr
    except ImportError:
        raise WarpgaussError("reading a .zarr store needs the 'zarr' package: pip install zarr") from None
    if path.is_dir() and not any(path.iterdir()):
        raise WarpgaussError(f"{path.name} is an empty folder, not a Zarr store; give a store that holds a 3D array")
    try:
        root: Any = zarr.open(str(path), mode="r")
    except Exception as e:  # zarr raises several types for a store it cannot read
        why = first_line(e)
        if "StorePath(" in why:  # zarr names its own objects: say what was looked for instead
            why = "no Zarr array or group metadata (.zarray, .zgroup or zarr.json) at its top"
        raise WarpgaussError(f"cannot open {path.name} as a Zarr store: {why}") from None
    key = None
    arr: Any
    if isinstance(root, zarr.Array):
        arr = root
    else:
        names = sorted(array_names(root))
        found = [(n, tuple(root[n].shape)) for n in names]
        key = pick_array(path.name, found, dataset, lambda k: k in names, "array", "--dataset")
        arr = root[key]
    shape = tuple(int(v) for v in arr.shape)
    check_shape(shape, path.name)
    check_dtype(np.dtype(arr.dtype), path.name)
    attrs = dict(arr.attrs)
    meta = dict(
        spacing=attr_xyz(attrs, "spacing", (1.0, 1.0, 1.0)),
        origin=attr_xyz(attrs, "origin", (0.0, 0.0, 0.0)),
        fill_value=fill_attr(attrs),
    )
    if lazy:
        from .lazy import ArraySource, Lazy3D

        src = ArraySource("zarr", str(path), shape, np.dtype(arr.dtype).str, key=key)  # type: ignore[arg-type]
        return ReadResult(Lazy3D(src), **meta)  # type: ignore[arg-type]
    voxels = check_declared(f"{path.name}", shape, np.dtype(arr.dtype).itemsize, stride, max_voxels)
    s = slice(None, None, stride)
    try:
        return ReadResult(np.asarray(arr[s, s, s]), strided=True, **meta)  # type: ignore[arg-type]
    except MemoryError:
        raise WarpgaussError(f"not enough memory to read {path.name} ({voxels} voxels); use a larger --stride") from None


def array_names(group, prefix: str = "") -> list[str]:
    """Every array's path in a group, nested groups included."""
    out = [prefix + n for n, _ in group.arrays()]
    for n, sub in group.groups():
        out += array_names(sub, prefix + n + "/")
    return out
