"""A region of a model at any resolution: the box's checks, where its output voxels sample the
model, and what a bounded residual can do for it.

A box is ``((x0, x1), (y0, y1), (z0, z1))`` in voxel coordinates of the encoded grid (the
header's ``grid.shape_xyz``: the source's voxels, or the strided grid's after ``--stride``),
bounds on voxel faces: the box runs from the lower face of voxel x0 to the lower face of voxel
x1, so integer bounds hold the source voxels ``x0 <= x < x1``, as the slice
``volume[z0:z1, y0:y1, x0:x1]`` does. Bounds may be fractional; ``0 <= x0 < x1 <= nx``.

Sampling (the whole decode's, over the box): ``n`` output voxels along an axis split the box's
extent ``[x0 - 0.5, x1 - 0.5]`` (model coordinates, voxel centres at integers) into ``n`` equal
cells, output voxel ``i`` at its cell's centre::

    x(i) = x0 - 0.5 + (i + 0.5) (x1 - x0) / n  =  ((i + x0 / s) + 0.5) s - 0.5,   s = (x1 - x0) / n

The whole extent is the box ``((0, nx), (0, ny), (0, nz))``: a whole decode at ``S`` voxels
samples ``(i + 0.5) nx / S - 0.5``. A box whose bounds are faces of that grid
(``x0 = I0 nx / S``, ``x1 = I1 nx / S``, ``n = I1 - I0``) samples its voxels ``I0 .. I1 - 1``
at the same float32 coordinates (the kernels add the integer offset ``I0`` exactly, and a scale or
offset within 1e-9 of ``nx / S`` or of an integer is taken as exactly that, so bounds written in
decimal do not drift): its decode is that crop of the whole decode, bit for bit.

A box costs what its output voxels and the Gaussians reaching them cost: each 8^3 brick of output
voxels lists the Gaussians whose 5-sigma box meets it (:mod:`warpgauss.kernels.decode`), plus one
pass over all N to prepare and bin them.
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import WarpgaussError

SNAP = 1e-9  # relative: a scale or offset this close to a whole grid's is taken as that grid's
Box = tuple[tuple[float, float], tuple[float, float], tuple[float, float]]
BOX_FORM = "((x0, x1), (y0, y1), (z0, z1)) voxel bounds of the encoded grid"


def _number(v) -> float | None:
    if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
        return None
    x = float(v)
    return x if math.isfinite(x) else None


def check_box(box, shape_xyz) -> Box:
    """The box as three (lo, hi) float pairs, or a one-line refusal of what is wrong with it: not
    three pairs of finite numbers, an empty range, a range reaching outside the model's extent
    ``[0, n]`` on an axis of ``shape_xyz`` (x, y, z)."""
    try:
        pairs = [tuple(p) for p in box]
    except TypeError:
        pairs = []
    bounds = [[_number(v) for v in p] for p in pairs]
    if len(bounds) != 3 or any(len(p) != 2 or None in p for p in bounds):
        raise WarpgaussError(f"a box must be {BOX_FORM}: three pairs of finite numbers, got {box!r}")
    out = []
    for axis, (lo, hi), n in zip("xyz", bounds, shape_xyz):
        assert lo is not None and hi is not None  # checked above
        if not lo < hi:
            raise WarpgaussError(f"the box's {axis} range {lo:g}:{hi:g} is empty; give {axis}0 < {axis}1")
        if lo < 0 or hi > int(n):
            raise WarpgaussError(
                f"the box's {axis} range {lo:g}:{hi:g} reaches outside the model's extent 0:{int(n)} "
                f"(voxel bounds of the encoded grid {'x'.join(str(int(s)) for s in shape_xyz)}); give bounds within it"
            )
        out.append((lo, hi))
    return (out[0], out[1], out[2])


def parse_box(text: str) -> Box:
    """``"x0:x1,y0:y1,z0:z1"`` (the command line's ``--box``) as three (lo, hi) pairs (not yet
    checked against a model: :func:`check_box`)."""
    parts = text.replace(" ", "").split(",")
    pairs = []
    for part in parts:
        ends = part.split(":")
        try:
            pair = tuple(float(v) for v in ends)
        except ValueError:
            pair = ()
        if len(pair) != 2 or not all(math.isfinite(v) for v in pair):
            break
        pairs.append(pair)
    if len(parts) != 3 or len(pairs) != 3:
        raise WarpgaussError(f"--box must be x0:x1,y0:y1,z0:z1, voxel bounds of the encoded grid (e.g. 0:32,0:32,16:48), got {text!r}")
    return (pairs[0], pairs[1], pairs[2])  # type: ignore[return-value]


def whole_voxels(box: Box) -> bool:
    """Whether every bound of a (checked) box is a voxel face of the encoded grid (an integer)."""
    return all(float(v).is_integer() for pair in box for v in pair)


def box_shape(box: Box) -> tuple[int, int, int]:
    """The output grid (x, y, z) of a box at the encoded resolution: its size in voxels. A box
    with a fractional bound has none: it needs a shape."""
    if not whole_voxels(box):
        raise WarpgaussError(
            f"the box {format_box(box)} does not lie on the encoded grid's voxels (a bound is fractional); give its output shape"
        )
    return (int(box[0][1] - box[0][0]), int(box[1][1] - box[1][0]), int(box[2][1] - box[2][0]))


def format_box(box: Box) -> str:
    """The box as the command line writes it, ``x0:x1,y0:y1,z0:z1``."""
    return ",".join(f"{lo:g}:{hi:g}" for lo, hi in box)


def on_encoded_grid(box: Box | None, shape_xyz, model_shape) -> bool:
    """Whether a decode of ``box`` (None: the whole extent) at ``shape_xyz`` (None: the encoded
    resolution) samples exactly voxels of the encoded grid: where a bounded residual applies."""
    if box is None:
        return shape_xyz is None or tuple(int(s) for s in shape_xyz) == tuple(int(s) for s in model_shape)
    return whole_voxels(box) and (shape_xyz is None or tuple(int(s) for s in shape_xyz) == box_shape(box))


def sampling(box: Box | None, out_shape, model_shape) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """(scale, offset) per axis (x, y, z) of ``out_shape`` output voxels over ``box`` (None: the
    whole extent): output voxel i sits at ``((i + offset) + 0.5) scale - 0.5`` model voxels
    (:func:`warpgauss.kernels.decode.voxel_coord`). Snapped to a whole grid's scale and an integer
    offset within :data:`SNAP` (see the module docstring)."""
    scale, offset = [], []
    for a in range(3):
        n, size = int(out_shape[a]), int(model_shape[a])
        if box is None:
            scale.append(size / n)
            offset.append(0.0)
            continue
        lo, hi = float(box[a][0]), float(box[a][1])
        s = (hi - lo) / n
        whole = round(size / s)
        if whole >= 1 and abs(size / s - whole) <= SNAP * (size / s):
            s = size / whole  # as the whole decode at `whole` voxels computes its scale
        o = lo / s
        if abs(o - round(o)) <= SNAP * max(1.0, abs(o)):
            o = float(round(o))
        scale.append(s)
        offset.append(o)
    return tuple(scale), tuple(offset)


def spacing_origin(header: dict, box: Box | None, out_shape) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """Physical voxel spacing and position of the first voxel centre of a decode of ``box`` (None:
    the whole extent) at ``out_shape`` (x, y, z); the header's spacing and origin place voxel
    (0, 0, 0) of the encoded grid."""
    g = header["grid"]
    full = [int(v) for v in g["shape_xyz"]]
    lows = [0.0, 0.0, 0.0] if box is None else [float(p[0]) for p in box]
    highs = full if box is None else [float(p[1]) for p in box]
    sp, org = [], []
    for a in range(3):
        s = (float(highs[a]) - lows[a]) / int(out_shape[a])  # model voxels per output voxel
        sp.append(float(g["spacing"][a]) * s)
        org.append(float(g["origin"][a]) + float(g["spacing"][a]) * (lows[a] - 0.5 + 0.5 * s))
    return tuple(sp), tuple(org)


def crop(grid: np.ndarray, box: Box) -> np.ndarray:
    """The (z, y, x) sub-array of a grid of the encoded resolution that a whole-voxel box holds."""
    (x0, x1), (y0, y1), (z0, z1) = ((int(lo), int(hi)) for lo, hi in box)
    return np.ascontiguousarray(grid[z0:z1, y0:y1, x0:x1])
