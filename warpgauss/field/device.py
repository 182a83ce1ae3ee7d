"""Volumes that already live on a device: a simulation's Warp, CuPy or PyTorch array is encoded
where it is, with no host copy of its voxels.

:func:`device_array` wraps an array handed over by DLPack (``__dlpack__``: PyTorch, CuPy, JAX) or
``__cuda_array_interface__`` (Numba, CuPy) as a Warp array without copying; :func:`normalise_on_device`
is stage P on the device (``kernels/ingest.py``): the min/max scan, the mask, the normalised
float32 values and the seed-candidate counts, bit-identical to :func:`warpgauss.field.analysis.normalise`
on the same voxels. The resulting :class:`~warpgauss.field.analysis.Field` holds :class:`DeviceValues`
(and :class:`DeviceMask`): they answer the shape, and copy to the host only what evaluation asks
for (sampled voxels, or z-slabs of a full-grid evaluation).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import WarpgaussError

F32_MAX = float(np.finfo(np.float32).max)


def is_device_array(x) -> bool:
    """Whether ``x`` is an array we take without a host copy (a Warp array, or anything with
    ``__cuda_array_interface__``, or a non-numpy ``__dlpack__`` producer)."""
    if isinstance(x, np.ndarray):
        return False
    if type(x).__module__.startswith("warp") and hasattr(x, "ptr") and hasattr(x, "device"):
        return True
    return hasattr(x, "__cuda_array_interface__") or hasattr(x, "__dlpack__")


def device_array(x, device: str | None = None):
    """``x`` as a Warp array on its own device, sharing its memory.

    Args:
        x: A Warp array, or a DLPack / ``__cuda_array_interface__`` producer (3D, z-y-x order).
        device: The device a ``__cuda_array_interface__`` pointer lives on (it does not say); by
            default ``cuda:0``.
    """
    from ..core.warp import warp

    wp = warp()
    if isinstance(x, wp.array):
        a = x
    elif hasattr(x, "__dlpack__"):
        try:
            a = wp.from_dlpack(x)
        except Exception as e:  # noqa: BLE001 - a producer's own refusal, said in one line
            raise WarpgaussError(
                f"the array could not be shared through DLPack ({e}); pass a Warp, CuPy or PyTorch array, or a numpy copy"
            ) from None
    else:
        a = _from_cuda_array_interface(wp, x.__cuda_array_interface__, x, device or "cuda:0")
    if a.ndim != 3:
        raise WarpgaussError(f"the array is {a.ndim}D (shape {tuple(a.shape)}); warpgauss encodes 3D volumes (z, y, x)")
    if not np.issubdtype(wp.dtype_to_numpy(a.dtype), np.number) or np.issubdtype(wp.dtype_to_numpy(a.dtype), np.complexfloating):
        raise WarpgaussError(f"the array's dtype {a.dtype.__name__} is not a real number type")
    return a


def _from_cuda_array_interface(wp, desc: dict, owner, device: str):
    """A Warp view of a ``__cuda_array_interface__`` (shape, typestr, data, strides), kept alive with its owner."""
    np_dtype = np.dtype(desc["typestr"])
    if np_dtype.byteorder not in ("=", "|") and np_dtype.byteorder != ("<" if np.little_endian else ">"):
        raise WarpgaussError(f"the array's byte order ({desc['typestr']}) is not this machine's; pass a native-order copy")
    shape = tuple(int(s) for s in desc["shape"])
    strides = desc.get("strides") or tuple(int(np_dtype.itemsize * np.prod(shape[i + 1 :], dtype=np.int64)) for i in range(len(shape)))
    try:
        dtype = wp.dtype_from_numpy(np_dtype.newbyteorder("="))
    except TypeError:
        raise WarpgaussError(f"the array's dtype {np_dtype} is not one warpgauss reads; pass float32") from None
    stream = desc.get("stream")
    if stream is not None and int(stream) == 0:
        raise WarpgaussError(
            "the array's __cuda_array_interface__ names stream 0, which the protocol disallows (ambiguous); its producer must say 1, 2 or a stream handle"
        )
    a = wp.array(ptr=int(desc["data"][0]), dtype=dtype, shape=shape, strides=tuple(int(s) for s in strides), device=device)
    a._ref = owner  # the producer's memory lives as long as this view
    if stream is not None and a.device.is_cuda:
        # the producer may still be writing on its stream: ours waits for it (no host synchronisation),
        # as DLPack's exchange does (protocol v3: 1 legacy default, 2 per-thread default, else a handle)
        wp.get_stream(a.device).wait_stream(wp.Stream(a.device, cuda_stream=int(stream)))
    return a


@dataclass(frozen=True)
class DeviceValues:
    """A Field's normalised values on the device: ``v[slices]`` and :meth:`take_flat` copy to the host."""

    array: Any  # wp.array3d(dtype=float32), contiguous

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(int(s) for s in self.array.shape)  # type: ignore[return-value]

    @property
    def size(self) -> int:
        return int(np.prod(self.shape, dtype=np.int64))

    ndim = 3
    dtype = np.dtype(np.float32)

    @property
    def nbytes(self) -> int:
        return 4 * self.size

    def __getitem__(self, key) -> np.ndarray:
        return np.ascontiguousarray(self.array[key].numpy())

    def take_flat(self, idx: np.ndarray) -> np.ndarray:
        """The values at linear voxel indices ``idx`` (gathered on the device)."""
        from ..kernels import ingest as ki

        return _gather(ki.gather_values, self.array, idx, float)


@dataclass(frozen=True)
class DeviceMask:
    """Validity on the device (1: usable); ``m[slices]`` and :meth:`take_flat` are host booleans."""

    array: Any  # wp.array3d(dtype=uint8)

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(int(s) for s in self.array.shape)  # type: ignore[return-value]

    ndim = 3

    def __getitem__(self, key) -> np.ndarray:
        return self.array[key].numpy() != 0

    def take_flat(self, idx: np.ndarray) -> np.ndarray:
        from ..kernels import ingest as ki

        return _gather(ki.gather_mask, self.array, idx, "uint8") != 0


def _gather(kernel, arr, idx: np.ndarray, dtype) -> np.ndarray:
    from ..core.warp import warp

    wp = warp()
    dev = arr.device
    ids = wp.array(np.asarray(idx, np.int64), dtype=wp.int64, device=dev)
    out = wp.empty(ids.shape[0], dtype=wp.uint8 if dtype == "uint8" else float, device=dev)
    if ids.shape[0]:
        wp.launch(kernel, dim=ids.shape[0], inputs=[arr, ids], outputs=[out], device=dev)
    return out.numpy()


class DeviceBuffers:
    """The normalised values and mask of one grid shape on one device, kept between encodes (an
    :class:`warpgauss.Encoder` normalises every timestep into the same memory)."""

    def __init__(self):
        self._key: tuple | None = None
        self.values = self.mask = None

    def get(self, shape: tuple[int, int, int], device: str):
        from ..core.warp import warp

        wp = warp()
        if self._key != (shape, str(device)):
            self.values = wp.empty(shape, dtype=float, device=device)
            self.mask = wp.empty(shape, dtype=wp.uint8, device=device)
            self._key = (shape, str(device))
        return self.values, self.mask


def normalise_on_device(
    src,
    *,
    fill_value: float | None = None,
    spacing=(1.0, 1.0, 1.0),
    origin=(0.0, 0.0, 0.0),
    name: str = "array",
    buffers: DeviceBuffers | None = None,
    count_candidates: bool = True,
):
    """Stage P of a device array (see the module docstring); returns a Field whose values stay there.

    Args:
        src: A Warp array (see :func:`device_array`), any real dtype, any strides.
        fill_value: Source value that marks missing data.
        buffers: Where to write the normalised values and mask (default: new arrays). The Field
            then shares that memory: the next normalisation into the same buffers overwrites it.
    """
    from ..core.warp import warp
    from ..kernels import ingest as ki
    from .analysis import MAX_VOXELS, NormPlan, new_field

    wp = warp()
    dev = src.device
    nz, ny, nx = (int(s) for s in src.shape)
    if nz * ny * nx > MAX_VOXELS:
        raise WarpgaussError(f"the array has {nz * ny * nx:,} voxels, more than the {MAX_VOXELS:,} warpgauss indexes; pass a strided view")
    np_dtype = np.dtype(wp.dtype_to_numpy(src.dtype))
    floating = np.issubdtype(np_dtype, np.floating)
    use_fill, fill = _fill(np_dtype, fill_value)
    check = [int(floating), int(use_fill), wp.float64(fill)]
    rows = (nz, ny)
    lo_r, hi_r = (wp.empty(rows, dtype=wp.float64, device=dev) for _ in range(2))
    bad_r = wp.empty(rows, dtype=int, device=dev)
    wp.launch(ki.row_range, dim=rows, inputs=[src, *check], outputs=[lo_r, hi_r, bad_r], device=dev)
    lo, hi = float(lo_r.numpy().min()), float(hi_r.numpy().max())
    n_invalid = int(bad_r.numpy().astype(np.int64).sum())
    if not np.isfinite(lo):
        raise WarpgaussError("the volume has no finite value (all NaN/Inf or fill); nothing to encode")
    if hi <= lo:
        raise WarpgaussError(f"the volume is constant ({lo:g} everywhere it is valid); there is no structure to encode")
    exact = np_dtype.itemsize > 4 or np_dtype in (np.int32, np.uint32)
    plan = NormPlan(lo, hi, lo, hi, exact, True)
    values, mask = (buffers or DeviceBuffers()).get((nz, ny, nx), dev)
    has_mask = int(n_invalid > 0)
    wp.launch(
        ki.normalise_values,
        dim=(nz, ny, nx),
        inputs=[
            src,
            *check,
            int(plan.f32),
            wp.float32(plan.lo),
            wp.float32(plan.scale),
            wp.float64(plan.lo),
            wp.float64(plan.span),
            wp.float64(plan.scale if np.isfinite(plan.scale) else 0.0),
            int(plan.halve),
            int(plan.divide),
            int(plan.clip),
            wp.float64(F32_MAX if plan.bound else 0.0),
        ],
        outputs=[values, mask, has_mask],
        device=dev,
    )
    f = new_field(DeviceValues(values), DeviceMask(mask) if has_mask else None, lo, hi, spacing, origin, name, np_dtype, n_invalid)
    if count_candidates:
        from .boxstats import box_counts

        c = box_counts(values, mask if has_mask else None)
        f.occupied, f.eligible = c.occupied, c.eligible
    return f


def _fill(dtype: np.dtype, fill_value: float | None) -> tuple[bool, float]:
    """(compare with a fill value, that value as the host compares it: in a floating source's own
    precision, as float64 for an integer one; see :func:`warpgauss.readers.lazy.valid_mask`)."""
    if fill_value is None:
        return False, 0.0
    if np.issubdtype(dtype, np.floating):
        if not abs(fill_value) <= float(np.finfo(dtype).max):
            return False, 0.0
        return True, float(np.asarray(fill_value, dtype=dtype))
    return True, float(fill_value)
