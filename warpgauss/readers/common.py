"""What every reader shares: the :class:`Volume` it returns, the reader record, dtype and shape
parsing, the size checks against the machine, and the final validation (:func:`finish_read`).
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import WarpgaussError

# --------------------------------------------------------------------------------------------------
# The volume
# --------------------------------------------------------------------------------------------------


@dataclass
class Volume:
    """A 3D scalar volume as read from a file.

    Attributes:
        data: 3D array ``[z, y, x]`` in the source dtype (stride applied; possibly a memmap view).
        spacing: Voxel size ``(x, y, z)`` in the file's physical units, multiplied by the stride.
        origin: Position of the first voxel's centre ``(x, y, z)``.
        name: File name without its extension(s) and without a ``_XxYxZ_dtype`` tail.
        source_dtype: numpy dtype name of the stored values, e.g. ``"uint8"``, ``"float32"``.
        path: The file read, or None.
        fill_value: Value that the file marks as missing data (netCDF/HDF5 ``_FillValue`` or
            ``missing_value`` attribute), or None. The caller masks these voxels.
    """

    data: np.ndarray
    spacing: tuple[float, float, float] = (1.0, 1.0, 1.0)
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    name: str = "volume"
    source_dtype: str = ""
    path: str | None = None
    fill_value: float | None = None

    @property
    def shape_xyz(self) -> tuple[int, int, int]:
        """Grid size as ``(nx, ny, nz)``."""
        nz, ny, nx = self.data.shape
        return int(nx), int(ny), int(nz)

    @property
    def source_itemsize(self) -> int:
        """Bytes per voxel of the source dtype (1 for uint8, 2 for int16, 4 for float32...)."""
        try:
            return int(np.dtype(self.source_dtype).itemsize) if self.source_dtype else int(self.data.dtype.itemsize)
        except TypeError:
            return int(self.data.dtype.itemsize)

    @property
    def source_bytes(self) -> int:
        """Voxel count (after stride) times :attr:`source_itemsize` (SPEC section 4's S_src)."""
        return int(self.data.size) * self.source_itemsize


@dataclass
class ReadResult:
    """What a format reader found, before the common validation, stride and byte-order steps."""

    data: np.ndarray
    spacing: tuple[float, float, float] = (1.0, 1.0, 1.0)
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    fill_value: float | None = None
    strided: bool = False  # the reader already applied the stride (HDF5 reads only what is kept)


@dataclass(frozen=True)
class ReaderSpec:
    func: Callable[..., ReadResult]
    options: frozenset[str]  # keyword options of read_volume this format understands
    what: str


# --------------------------------------------------------------------------------------------------
# Raw file names and dtypes
# --------------------------------------------------------------------------------------------------

_RAW_DTYPES: dict[str, np.dtype] = {
    "uint8": np.dtype(np.uint8),
    "int8": np.dtype(np.int8),
    "uint16": np.dtype(np.uint16),
    "int16": np.dtype(np.int16),
    "uint32": np.dtype(np.uint32),
    "int32": np.dtype(np.int32),
    "float32": np.dtype(np.float32),
    "float64": np.dtype(np.float64),
    "float": np.dtype(np.float32),
    "double": np.dtype(np.float64),
}

_RAW_NAME = re.compile(
    r"(?:^|_)(\d+)x(\d+)x(\d+)_(" + "|".join(_RAW_DTYPES) + r")$",
    re.IGNORECASE,
)

_RAW_SUFFIXES = (".raw", ".bin")

MAX_READ_VOXELS = 2**31 - 1  # = warpgauss.field.analysis.MAX_VOXELS: the most an in-core encode indexes (the default limit)


def parse_raw_name(filename: str | os.PathLike) -> tuple[tuple[int, int, int], np.dtype] | None:
    """Shape and dtype from the open scientific-visualization naming ``name_XxYxZ_dtype.raw``.

    Args:
        filename: A file name or path, e.g. ``"bonsai_256x256x256_uint8.raw"``. A ``.raw`` or
            ``.bin`` extension is optional.

    Returns:
        ``((x, y, z), dtype)`` with a native-order dtype, or None if the name does not follow
        the convention (unknown dtype words such as ``float16`` included).
    """
    stem = Path(filename).name
    for suffix in _RAW_SUFFIXES:
        if stem.lower().endswith(suffix):
            stem = stem[: -len(suffix)]
            break
    m = _RAW_NAME.search(stem)
    if m is None:
        return None
    shape = (int(m.group(1)), int(m.group(2)), int(m.group(3)))
    return shape, _RAW_DTYPES[m.group(4).lower()]


def resolve_dtype(dtype) -> np.dtype:
    """A user's dtype (``"float32"``, ``"float"``, ``"double"``, ``np.int16``...) as a real numeric dtype."""
    if isinstance(dtype, str) and dtype.lower() in _RAW_DTYPES:
        return _RAW_DTYPES[dtype.lower()]
    try:
        dt = np.dtype(dtype)
    except (TypeError, ValueError, SyntaxError):  # numpy parses dtype strings: "0" and "01" raise these
        dt = None
    if dt is None or dt.kind not in "iuf":
        raise WarpgaussError(f"unknown dtype {dtype!r}; use one of {', '.join(_RAW_DTYPES)}")
    return dt


def resolve_shape(shape) -> tuple[int, int, int]:
    """Validate a user's ``(x, y, z)`` shape."""
    try:
        xyz = tuple(int(v) for v in shape)
    except (TypeError, ValueError):
        xyz = ()
    if len(xyz) != 3 or min(xyz) < 1:
        raise WarpgaussError(f"shape must be three positive integers (x, y, z), got {shape!r}")
    return xyz  # type: ignore[return-value]


def byte_order(endian: str | None) -> str:
    if endian is None or str(endian).lower() in ("little", "le", "<"):
        return "<"
    if str(endian).lower() in ("big", "be", ">"):
        return ">"
    raise WarpgaussError(f"endian must be 'little' or 'big', got {endian!r}")


def fmt_xyz(shape_xyz) -> str:
    return "x".join(str(int(v)) for v in shape_xyz)


def _physical_memory() -> int | None:
    try:
        return int(os.sysconf("SC_PHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (AttributeError, ValueError, OSError):
        return None


def check_declared(what: str, shape_zyx, itemsize: int, stride: int = 1, limit: int | None = None) -> int:
    """Refuse a declared grid before anything is allocated for it; returns the voxels to read.

    A header's dimensions are only a claim: compressed or sparse storage lets a few bytes declare
    terabytes. Beyond ``limit`` voxels (after the stride; default :data:`MAX_READ_VOXELS`, what
    an encode with the volume on the device indexes; ``field.analysis.MAX_HOST_VOXELS`` with the
    volume in host memory) or beyond this machine's physical memory the read is refused with the
    way out (a larger ``--stride``).
    """
    limit = MAX_READ_VOXELS if limit is None else int(limit)
    kept = [-(-int(n) // stride) for n in shape_zyx]
    voxels = math.prod(kept)
    shown = fmt_xyz(tuple(shape_zyx)[::-1])
    if voxels > limit:
        raise WarpgaussError(
            f"{what} declares {shown} voxels ({voxels} after --stride {stride}), more than the {limit} "
            "warpgauss can encode this way; use a larger --stride" + (" or --volume-on-host (a GPU)" if limit <= MAX_READ_VOXELS else "")
        )
    ram = _physical_memory()
    if ram is not None and voxels * int(itemsize) > ram:
        raise WarpgaussError(
            f"{what} declares {shown} voxels of {itemsize} bytes ({voxels * int(itemsize) / 2**30:.1f} GiB after "
            f"--stride {stride}), more than this machine's {ram / 2**30:.1f} GiB of memory; use a larger --stride"
        )
    return voxels


def finish_read(p: Path, suffix: str, got: ReadResult, stride: int, lazy: bool = False) -> Volume:
    """Common validation, stride and byte order (``lazy``: left to the reads); builds the :class:`Volume`."""
    data = got.data
    check_shape(data.shape, p.name)
    check_dtype(data.dtype, p.name)
    if stride > 1 and not got.strided:
        data = data[::stride, ::stride, ::stride]
    if not data.dtype.isnative and not lazy:
        data = data.astype(data.dtype.newbyteorder("="))
    # a header's inf/NaN geometry (metadata only) must not reach the model header, which is strict
    # JSON, nor a spacing of 0 (a model file refuses it) or below 0 (a flipped axis: its size kept)
    spacing = usable_spacing(got.spacing, stride)
    origin = tuple(float(v) if np.isfinite(v) else 0.0 for v in got.origin)
    return Volume(
        data=data,
        spacing=spacing,  # type: ignore[arg-type]
        origin=origin,  # type: ignore[arg-type]
        name=_volume_name(p.name, suffix),
        source_dtype=data.dtype.newbyteorder("=").name,
        path=str(p),
        fill_value=_fill_in_dtype(got.fill_value, data.dtype),
    )


def _fill_in_dtype(fill: float | None, dtype: np.dtype) -> float | None:
    """The fill value as the data stores it (a float64 attribute on float32 data is rounded to float32)."""
    if fill is None or dtype.kind != "f" or not np.isfinite(fill):
        return fill
    with np.errstate(over="ignore"):
        stored = dtype.type(fill)
    return float(stored) if np.isfinite(stored) else fill


def match_suffix(filename: str, table: dict, verb: str) -> str:
    lower = filename.lower()
    hits = [ext for ext in table if lower.endswith(ext)]
    if not hits:
        ext = "".join(Path(filename).suffixes[-2:]) or "no extension"
        raise WarpgaussError(f"cannot {verb} {filename}: unknown extension {ext!r}; supported: {' '.join(sorted(table))}")
    return max(hits, key=len)


def check_options(p: Path, reader: ReaderSpec, given: list[str]) -> None:
    extra = [o for o in given if o not in reader.options]
    if extra:
        opts = ", ".join(f"--{o}" for o in extra)
        verb, it = ("does", "it") if len(extra) == 1 else ("do", "them")
        raise WarpgaussError(f"{opts} {verb} not apply to {p.name} ({reader.what} file); leave {it} out")


def check_stride(stride) -> int:
    if isinstance(stride, bool) or not isinstance(stride, (int, np.integer)) or stride < 1:
        raise WarpgaussError(f"stride must be a positive integer, got {stride!r}")
    return int(stride)


def check_shape(shape: tuple, what: str) -> None:
    if len(shape) != 3:
        raise WarpgaussError(f"{what} is {len(shape)}D (shape {tuple(shape)}); warpgauss encodes 3D volumes")
    if min(shape) < 1:
        raise WarpgaussError(f"{what} has an empty axis (shape z,y,x = {tuple(shape)}); every axis needs at least 1 voxel")


def usable_spacing(spacing, stride: int = 1) -> tuple[float, float, float]:
    """A declared voxel size ``(x, y, z)`` as a model header takes it, times the stride: an
    infinite, NaN or 0 entry (unknown) becomes the stride, a negative one (a flipped axis) its size."""
    x, y, z = (abs(float(v)) * stride if np.isfinite(v) and v != 0 else float(stride) for v in spacing)
    return (x, y, z)


def check_dtype(dtype: np.dtype, what: str) -> None:
    if dtype.kind not in "iuf":
        raise WarpgaussError(f"{what} holds {dtype} values; warpgauss encodes real numbers (integer or float)")


def _volume_name(filename: str, suffix: str) -> str:
    stem = filename[: len(filename) - len(suffix)]
    stem = _RAW_NAME.sub("", stem)
    return stem or "volume"


def attr_xyz(attrs, key: str, default: tuple[float, float, float]) -> tuple[float, float, float]:
    """Three finite numbers from an attribute; the default for anything else (metadata only)."""
    value = attrs.get(key)
    if value is None:
        return default
    try:
        arr = np.asarray(value, dtype=np.float64).ravel()
    except (TypeError, ValueError):  # a string, a compound value...
        return default
    if arr.size != 3 or not np.isfinite(arr).all():
        return default
    return tuple(float(v) for v in arr)  # type: ignore[return-value]


def fill_attr(attrs) -> float | None:
    for key in ("_FillValue", "missing_value"):
        value = attrs.get(key)
        if value is not None:
            arr = np.asarray(value).ravel()
            if arr.size and arr.dtype.kind in "iuf":
                return float(arr[0])
    return None


def first_line(e: BaseException) -> str:
    text = str(e).strip()
    return text.splitlines()[0] if text else type(e).__name__


def list_datasets(found: list[tuple[str, tuple]], limit: int = 12) -> str:
    if not found:
        return "no datasets"
    items = [f"{n} {tuple(int(v) for v in s)}" for n, s in found[:limit]]
    more = f" and {len(found) - limit} more" if len(found) > limit else ""
    return ", ".join(items) + more


def pick_array(where: str, found: list[tuple[str, tuple]], wanted, has, noun: str, option: str, strip: str = "/") -> str:
    """The key of the array to read from a container (HDF5 datasets, netCDF variables, Zarr
    arrays): ``wanted`` (leading ``strip`` characters dropped) if ``has(key)``, else the first
    3D one of ``found`` ((name, shape) pairs); a one-line error listing them otherwise."""
    if wanted is not None:
        key = str(wanted).lstrip(strip)
        if not has(key):
            raise WarpgaussError(f"{where} has no {noun} {wanted!r}; it holds {list_datasets(found)}; pick one with {option}")
        return key
    first = next((n for n, s in found if len(s) == 3), None)
    if first is None:
        raise WarpgaussError(f"{where} has no 3D {noun}; it holds {list_datasets(found)}")
    return first


def parse_shape(text: str | None, what: str = "--shape") -> tuple[int, int, int] | None:
    """'128x128x64' or '128,128,64' -> (128, 128, 64) as (x, y, z)."""
    if text is None:
        return None
    parts = text.replace(",", "x").replace("X", "x").split("x")
    try:
        shape = tuple(int(p) for p in parts)
    except ValueError:
        shape = ()
    if len(shape) != 3 or min(shape) < 1:
        raise WarpgaussError(f"{what} must be three positive integers XxYxZ (e.g. 128x128x64), got {text!r}")
    return shape
