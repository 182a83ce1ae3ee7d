"""VTK ImageData, legacy VTK, NIfTI, MetaImage and NRRD through pyvista, with their declared sizes
checked before VTK allocates (VTK trusts a header's sizes).
"""

from __future__ import annotations

import gzip
import math
import re
import struct
from pathlib import Path

import numpy as np

from ..errors import WarpgaussError
from .common import ReadResult, check_declared, first_line


def read_pyvista(path: Path, max_voxels: int | None = None, **_) -> ReadResult:
    """VTK ImageData, legacy structured points, NIfTI, MetaImage, NRRD via ``pyvista.read``.

    The active point-data scalars (else the first point-data array) are used; a file with cell data
    only uses its first cell array on the cell-centre grid. Multi-component arrays are refused
    (no magnitude is taken). The NIfTI affine / VTK direction matrix is not applied.
    """
    import pyvista as pv

    _precheck_vtk(path, max_voxels)
    mesh, vtk_error = _quiet_pyvista_read(pv, path)
    if vtk_error is not None:  # whatever VTK returned after an error is not the file's data
        raise WarpgaussError(f"cannot read {path.name}: VTK reports: {vtk_error}")
    if not isinstance(mesh, pv.ImageData):
        raise WarpgaussError(
            f"{path.name} holds a {type(mesh).__name__}, not image data on a regular grid; "
            f"warpgauss reads VTK ImageData (structured points)"
        )
    dims = tuple(int(d) for d in mesh.dimensions)
    spacing = tuple(float(v) for v in mesh.spacing)
    origin = tuple(float(v) for v in mesh.origin)
    arrays = mesh.point_data
    if len(arrays.keys()) == 0 and len(mesh.cell_data.keys()) > 0:
        arrays = mesh.cell_data
        dims = tuple(max(d - 1, 1) for d in dims)
        origin = tuple(o + s / 2 for o, s in zip(origin, spacing))
    if len(arrays.keys()) == 0:
        raise WarpgaussError(f"{path.name} has no data arrays; nothing to encode")
    name = arrays.active_scalars_name or arrays.keys()[0]
    arr = np.asarray(arrays[name])
    if arr.ndim > 1 and path.name.lower().endswith((".nrrd", ".nhdr")):
        fixed = _nrrd_undo_vtk_components(path, arr, spacing)
        if fixed is not None:
            return ReadResult(fixed[0], spacing=fixed[1], origin=origin)  # type: ignore[arg-type]
    if arr.ndim > 1 and int(np.prod(arr.shape[1:])) != 1:
        raise WarpgaussError(
            f"{path.name}: array {name!r} has {int(np.prod(arr.shape[1:]))} components per voxel; "
            f"warpgauss encodes scalar volumes, so extract one component (or the magnitude) first"
        )
    xyz = arr.reshape(dims, order="F")  # [x, y, z]
    return ReadResult(np.ascontiguousarray(xyz.transpose(2, 1, 0)), spacing=spacing, origin=origin)  # type: ignore[arg-type]


_NRRD_SIZES = {
    1: ("uchar", "unsigned char", "uint8", "uint8_t", "signed char", "int8", "int8_t", "char"),
    2: (
        "short",
        "short int",
        "signed short",
        "signed short int",
        "int16",
        "int16_t",
        "ushort",
        "unsigned short",
        "unsigned short int",
        "uint16",
        "uint16_t",
    ),
    4: ("int", "signed int", "int32", "int32_t", "uint", "unsigned int", "uint32", "uint32_t", "float"),
}
_META_SIZES = {
    "MET_UCHAR": 1,
    "MET_CHAR": 1,
    "MET_SHORT": 2,
    "MET_USHORT": 2,
    "MET_INT": 4,
    "MET_UINT": 4,
    "MET_FLOAT": 4,
    "MET_LONG": 4,
    "MET_ULONG": 4,
}


def _quiet_pyvista_read(pv, path: Path):
    """``pv.read`` with VTK's own error output (its logger, pyvista's warnings and log records)
    held back: a damaged file must end in one line, not thirty. Returns (mesh, first VTK error)."""
    import contextlib
    import logging
    import warnings

    verbosity = getattr(pv, "vtk_verbosity", None)
    quiet = verbosity("off") if verbosity is not None else contextlib.nullcontext()
    previous = logging.root.manager.disable
    with warnings.catch_warnings(), quiet, pv.VtkErrorCatcher() as catcher:
        warnings.simplefilter("ignore")
        logging.disable(logging.CRITICAL)
        try:
            mesh = pv.read(path)
        except Exception as e:  # VTK and pyvista raise a mix of types for unreadable files
            raise WarpgaussError(f"cannot read {path.name} with pyvista ({first_line(e)})") from e
        finally:
            logging.disable(previous)
    errors = [ev for ev in catcher.events if str(getattr(ev, "kind", "ERROR")) == "ERROR"]
    if not errors:
        return mesh, None
    text = str(getattr(errors[0], "alert", "") or errors[0]).strip()
    return mesh, (text.splitlines() or ["unknown error"])[0]


def _precheck_vtk(path: Path, max_voxels: int | None = None) -> None:
    """Check the dimensions a VTK/NRRD/MetaImage/NIfTI header declares before VTK allocates for them.

    VTK trusts a header's sizes: a 90-byte NRRD declaring 99999^3 voxels makes it throw
    ``std::bad_alloc`` and abort the process. The declared grid is refused here if it is empty,
    larger than warpgauss can encode or than this machine's memory, or (uncompressed data in the
    same file) larger than the bytes the file holds. Headers this cannot parse are left to VTK.
    """
    name = path.name.lower()
    if name.endswith((".nrrd", ".nhdr")):
        found = _nrrd_declared(path)
    elif name.endswith((".mha", ".mhd")):
        found = _meta_declared(path)
    elif name.endswith((".nii", ".nii.gz")):
        found = _nifti_declared(path)
    else:
        found = _vtk_xml_or_legacy_declared(path)
    if found is None:
        return
    dims, itemsize, need_after = found
    if not dims or min(dims) < 1:
        raise WarpgaussError(f"{path.name} declares an empty grid (sizes {dims}); the header is damaged")
    check_declared(path.name, tuple(dims)[::-1], itemsize, limit=max_voxels)
    if need_after is not None:
        offset, amount, mode = need_after
        have = _gzip_bytes(path, offset, amount) if mode == "gzip" else path.stat().st_size - offset
        if have < amount:
            raise WarpgaussError(
                f"{path.name} declares {'x'.join(map(str, dims))} voxels ({amount} bytes of data) but holds "
                f"{max(have, 0)}; the file is truncated or its header is damaged"
            )


def _gzip_bytes(path: Path, offset: int, enough: int) -> int:
    """Bytes a gzip stream starting at ``offset`` (of the file, or of its gunzipped content for a
    ``.gz`` file) decompresses to, counted in 1 MiB pieces up to ``enough``; memory stays bounded."""
    import zlib

    outer_gz = path.name.lower().endswith(".gz")
    total = 0
    try:
        with gzip.open(path, "rb") if outer_gz else open(path, "rb") as fh:
            fh.seek(offset) if not outer_gz else fh.read(offset)
            if outer_gz:  # the file itself is gzip: count what follows the header
                while total < enough:
                    piece = fh.read(1 << 20)
                    if not piece:
                        break
                    total += len(piece)
                return total
            z = zlib.decompressobj(16 + zlib.MAX_WBITS)
            while total < enough:
                piece = fh.read(1 << 20)
                if not piece:
                    break
                total += len(z.decompress(piece, enough - total + 1))
                while z.unconsumed_tail and total < enough:
                    total += len(z.decompress(z.unconsumed_tail, enough - total + 1))
    except (OSError, EOFError, zlib.error):
        pass
    return total


def _head_text(path: Path, limit: int = 65536) -> bytes:
    with open(path, "rb") as fh:
        return fh.read(limit)


def _ints(text: str) -> list[int] | None:
    try:
        return [int(float(v)) for v in text.replace(",", " ").split()]
    except (ValueError, OverflowError):
        return None


def _nrrd_declared(path: Path):
    head = _head_text(path)
    if not head.startswith(b"NRRD"):
        raise WarpgaussError(f"{path.name} does not start with the NRRD magic; it is not a NRRD file")
    fields = _nrrd_fields(path)
    sizes = _ints(fields.get("sizes", ""))
    if not sizes:
        raise WarpgaussError(f"{path.name} has no valid 'sizes:' field; the NRRD header is damaged")
    kind = fields.get("type", "").strip().lower()
    itemsize = next((k for k, names in _NRRD_SIZES.items() if kind in names), 8)
    need = None
    end = head.find(b"\n\n")
    detached = "data file" in fields or "datafile" in fields
    encoding = fields.get("encoding", "").strip().lower()
    if not detached and end >= 0:
        if encoding == "raw":
            need = (end + 2, math.prod(sizes) * itemsize, "raw")
        elif encoding in ("gzip", "gz"):
            need = (end + 2, math.prod(sizes) * itemsize, "gzip")
        elif encoding in ("ascii", "text", "txt"):
            # vtkNrrdReader returns zeros and noise for ASCII data instead of failing (VTK 9.x)
            raise WarpgaussError(
                f"{path.name} stores its values as ASCII text, which the NRRD reader (VTK) reads as garbage; "
                "convert it to raw or gzip encoding (e.g. unu save -e raw) and retry"
            )
    return sizes, itemsize, need


def _meta_declared(path: Path):
    head = _head_text(path)
    fields: dict[str, str] = {}
    offset = None
    pos = 0
    for line in head.split(b"\n"):
        pos += len(line) + 1
        key, sep, value = line.decode("latin-1").partition("=")
        if sep:
            fields[key.strip()] = value.strip()
        if key.strip() == "ElementDataFile":
            offset = pos
            break
    sizes = _ints(fields.get("DimSize", ""))
    if not sizes:
        raise WarpgaussError(f"{path.name} has no valid 'DimSize =' line; it is not a MetaImage header")
    channels = _ints(fields.get("ElementNumberOfChannels", "1")) or [1]
    itemsize = _META_SIZES.get(fields.get("ElementType", ""), 8) * max(channels[0], 1)
    need = None
    compressed = fields.get("CompressedData", "False").strip().lower() == "true"
    if fields.get("ElementDataFile", "").strip().upper() == "LOCAL" and not compressed and offset is not None:
        need = (offset, math.prod(sizes) * itemsize, "raw")
    return sizes, itemsize, need


def _nifti_declared(path: Path):
    if path.name.lower().endswith(".gz"):
        try:
            with gzip.open(path, "rb") as fh:
                head = fh.read(544)
        except (OSError, EOFError) as e:
            raise WarpgaussError(f"cannot decompress {path.name} ({first_line(e)})") from None
        size = None
    else:
        head = _head_text(path, 544)
        size = path.stat().st_size
    for order in ("<", ">"):
        if len(head) >= 348 and struct.unpack(order + "i", head[:4])[0] == 348:
            dim = struct.unpack(order + "8h", head[40:56])
            bitpix = struct.unpack(order + "h", head[72:74])[0]
            offset = struct.unpack(order + "f", head[108:112])[0]
            break
        if len(head) >= 540 and struct.unpack(order + "i", head[:4])[0] == 540:
            dim = struct.unpack(order + "8q", head[16:80])
            bitpix = struct.unpack(order + "h", head[14:16])[0]
            offset = struct.unpack(order + "q", head[168:176])[0]
            break
    else:
        raise WarpgaussError(f"{path.name} has no NIfTI-1 or NIfTI-2 header (sizeof_hdr is not 348 or 540)")
    ndim = int(dim[0])
    if not 1 <= ndim <= 7:
        raise WarpgaussError(f"{path.name} declares {ndim} dimensions; the NIfTI header is damaged")
    sizes = [int(v) for v in dim[1 : ndim + 1]]
    itemsize = max(int(bitpix) // 8, 1) if 0 < bitpix <= 256 else 8
    need = None
    if np.isfinite(offset) and 0 <= offset < 2**40 and min(sizes) >= 1:
        need = (int(offset), math.prod(sizes) * itemsize, "gzip" if size is None else "raw")
    return sizes, itemsize, need


_VTK_EXTENT = re.compile(rb'WholeExtent\s*=\s*"([^"]*)"')
_VTK_DIMS = re.compile(rb"DIMENSIONS\s+(-?\d+)\s+(-?\d+)\s+(-?\d+)")


def _vtk_xml_or_legacy_declared(path: Path):
    head = _head_text(path)
    m = _VTK_EXTENT.search(head)
    if m:
        ext = _ints(m.group(1).decode("latin-1"))
        if not ext or len(ext) != 6:
            raise WarpgaussError(f"{path.name} has a WholeExtent that is not six integers; the file is damaged")
        return [ext[1] - ext[0] + 1, ext[3] - ext[2] + 1, ext[5] - ext[4] + 1], 8, None
    m = _VTK_DIMS.search(head)
    if m:
        return [int(v) for v in m.groups()], 8, None
    return None


def _nrrd_undo_vtk_components(path: Path, arr: np.ndarray, spacing) -> tuple[np.ndarray, tuple] | None:
    """Undo VTK's guess that a fastest NRRD axis of 9 samples or fewer holds vector components.

    vtkNrrdReader turns such an axis into components and shifts the grid axes down by one. When
    the header says ``dimension: 3`` and the first axis is not marked as a non-spatial kind, the
    file is a scalar volume: rebuild ``[z, y, x]`` and take the x spacing from the header.

    Returns:
        (data, spacing) or None if the file really holds vectors.
    """
    fields = _nrrd_fields(path)
    try:
        ndim = int(fields.get("dimension", "0"))
        sizes = [int(v) for v in fields.get("sizes", "").split()]
    except ValueError:
        return None
    kinds = fields.get("kinds", "").lower().split()
    directions = fields.get("space directions", "").split()
    if ndim != 3 or len(sizes) != 3 or arr.ndim != 2 or arr.shape[1] != sizes[0]:
        return None
    if (kinds and kinds[0] not in ("domain", "space")) or (directions and directions[0] == "none"):
        return None
    sx = 1.0
    try:
        if "spacings" in fields:
            sx = float(fields["spacings"].split()[0])
        elif directions:
            sx = float(np.linalg.norm([float(v) for v in directions[0].strip("()").split(",")]))
    except ValueError:
        pass
    sx = sx if np.isfinite(sx) and sx > 0 else 1.0
    data = np.ascontiguousarray(arr.reshape(sizes[2], sizes[1], sizes[0]))
    return data, (sx, float(spacing[0]), float(spacing[1]))


def _nrrd_fields(path: Path) -> dict[str, str]:
    """``field: value`` lines of a NRRD header (up to the blank line that ends it)."""
    with open(path, "rb") as fh:
        text = fh.read(65536).split(b"\n\n", 1)[0].decode("latin-1")
    fields = {}
    for line in text.splitlines()[1:]:
        key, sep, value = line.partition(": ")
        if sep and not line.startswith("#"):
            fields[key.strip().lower()] = value.strip()
    return fields
