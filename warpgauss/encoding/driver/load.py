"""Stage P: read a source (file, array, device array or example) and normalise it to a :class:`Field`."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ...core.limits import available_memory
from ...errors import WarpgaussError
from ...field.analysis import Field, normalise
from ...field.device import device_array, is_device_array, normalise_on_device
from ...readers import ReadOptions
from ...readers.common import usable_spacing
from ...readers.timesteps import TimeStep

LAZY_SUFFIXES = (
    ".raw",
    ".bin",
    ".npy",
    ".h5",
    ".hdf5",
    ".hdf",
    ".nc",
    ".cdf",
    ".zarr",
)  # formats read on demand: their header gives the shape


def read_on_demand(source, example) -> bool:
    """Whether ``source`` is a file in a format whose header gives its shape before any reading."""
    return example is None and isinstance(source, (str, os.PathLike)) and str(source).lower().endswith(LAZY_SUFFIXES)


def header_shape(source, read) -> tuple[int, ...]:
    """The (x, y, z) shape of such a file, from its header: nothing is read yet."""
    vol = (read or ReadOptions()).read(source, lazy=True)
    return tuple(int(v) for v in vol.data.shape[::-1])


def load_field(
    source,
    read: ReadOptions | None = None,
    *,
    example: str | None = None,
    example_size: int | tuple[int, int, int] = 64,
    lazy: bool = False,
    buffers=None,
    count: bool = True,
    max_voxels: int | None = None,
    pinned: bool = False,
) -> tuple[Field, dict]:
    """Stage P: read (or generate) the volume, apply the stride, mask and normalise it (``lazy``:
    a file the format lets us leave where it is is read on demand, see :mod:`warpgauss.readers.lazy`).

    Args:
        source: A path, a 3D numpy array (nz, ny, nx), a device array (Warp, or DLPack /
            ``__cuda_array_interface__``: normalised where it is, see :mod:`warpgauss.field.device`),
            or None with ``example``.
        read: Reader options for a path (and stride / fill value for any source).
        example: Name of a built-in example volume (see :mod:`warpgauss.readers.synthetic`).
        buffers: A device array's normalised values go there (:class:`warpgauss.field.device.DeviceBuffers`).
        count: Count the seed candidates of a volume read on demand now (False: a bricked encode
            counts them with its bricks' statistics, one pass over the file fewer).
        max_voxels: The most voxels the encode indexes (None: ``field.analysis.MAX_VOXELS``, the
            volume on the device; ``MAX_HOST_VOXELS`` with the volume in host memory).
        pinned: Normalise into page-locked host memory that the encode's device volume then
            reads as it is (the volume in host memory, ``--volume-on-host``; see
            :func:`warpgauss.field.analysis.normalise`).

    Returns:
        (normalised field, description of the input for the report)
    """
    from ...field import limits as field_limits

    limit = field_limits.MAX_VOXELS if max_voxels is None else int(max_voxels)
    read = read or ReadOptions()
    if read.stride < 1:
        raise WarpgaussError(f"--stride must be a positive integer, got {read.stride}")
    s = read.stride
    fill = read.fill_value
    if example is not None:
        from ...readers.synthetic import generate

        dims = (example_size,) * 3 if isinstance(example_size, (int, np.integer)) else tuple(example_size)
        voxels = int(np.prod([int(d) for d in dims], dtype=object))
        if voxels > limit:
            largest = int(round(limit ** (1 / 3))) - 1
            raise WarpgaussError(
                f"--size {example_size} gives {voxels:,} voxels, more than the {limit:,} warpgauss indexes; use --size {largest} or less"
            )
        free = available_memory()
        if free is not None and 3 * 4 * voxels > free:  # the float32 field and generation temporaries
            raise WarpgaussError(
                f"--size {example_size} needs about {3 * 4 * voxels / 2**30:.1f} GiB to generate, more than the "
                f"{free / 2**30:.1f} GiB available; use a smaller --size"
            )
        data = generate(example, example_size, seed=0)[::s, ::s, ::s]
        name, spacing, origin, dtype, path = example, (float(s),) * 3, (0.0, 0.0, 0.0), "float32", None
    elif is_device_array(source):  # stays where it is: stage P runs on its device
        arr = device_array(source)
        f = normalise_on_device(arr[::s, ::s, ::s] if s > 1 else arr, fill_value=fill, spacing=(float(s),) * 3, buffers=buffers)
        info = {"read_lazily": False, "name": "array", "path": None, "example": None, "on_device": str(arr.device)}
        return f, {**info, **field_facts(f, s, fill)}
    elif isinstance(source, TimeStep):  # one timestep of a file with a time axis, with its attributes
        data = source.read()[::s, ::s, ::s]
        declared, origin, declared_fill = source.meta()
        spacing = usable_spacing(declared, s)
        name, dtype, path = f"{Path(source.path).name}:{source.key}[{source.t}]", str(data.dtype), str(source)
        if fill is None:
            fill = declared_fill
    elif isinstance(source, np.ndarray):
        if source.ndim != 3:
            raise WarpgaussError(f"the array is {source.ndim}D (shape {source.shape}); warpgauss encodes 3D volumes")
        data = source[::s, ::s, ::s]
        name, spacing, origin, dtype, path = "array", (float(s),) * 3, (0.0, 0.0, 0.0), str(source.dtype), None
    elif isinstance(source, (str, os.PathLike)):
        vol = read.read(source, lazy=lazy, max_voxels=limit)
        data, name, spacing, origin = vol.data, vol.name, vol.spacing, vol.origin
        dtype, path = vol.source_dtype or str(vol.data.dtype), str(source)
        if fill is None and getattr(vol, "fill_value", None) is not None:
            fill = vol.fill_value
    else:
        raise WarpgaussError("give a file path, a 3D numpy or device array (Warp, CuPy, PyTorch), or example=NAME as the source")
    from ...readers.lazy import source_of

    lazy = lazy and source_of(data) is not None
    f = normalise(
        data,
        fill_value=fill,
        spacing=spacing,
        origin=origin,
        name=name,
        source_dtype=dtype,
        lazy=lazy,
        count_candidates=count or not lazy,
        max_voxels=limit,
        pinned=pinned and not lazy,
    )
    info = {"read_lazily": lazy, "name": name, "path": path, "example": example}
    return f, {**info, **field_facts(f, s, fill)}


def field_facts(f: Field, stride: int, fill) -> dict:
    """The input description of a normalised field (the report's ``input``)."""
    return {
        "shape_xyz": list(f.shape_xyz),
        "source_dtype": f.source_dtype,
        "source_bytes": f.source_bytes,
        "stride": stride,
        "fill_value": fill,
        "value_min": f.vmin,
        "value_max": f.vmax,
        "masked_voxels": f.n_voxels - f.n_valid,
        "notes": list(f.notes),
    }
