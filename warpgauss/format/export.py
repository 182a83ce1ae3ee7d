"""Export the primitives for other tools: a ``.vtp`` point cloud ParaView opens directly.

One point per Gaussian at its centre, with point-data arrays

* ``scale`` (3): the sigma along each local axis,
* ``orientation`` (4): the unit quaternion of the local frame, in (x, y, z, w) order,
* ``rotation`` (9): the same frame as a row-major 3x3 matrix whose columns are the local axes,
* ``value``: the primitive's value a in the source's units, ``value_normalised`` in [0, 1],
* ``weight``: w,

so that the covariance is ``rotation diag(scale^2) rotation^T``. By default positions and sizes
are physical (origin + index x spacing, as the decoded ``.vti``); with anisotropic spacing the
covariance is transformed and re-factored, so the local axes are the physical ones.
``voxel_units=True`` writes the model's own voxel coordinates and parameters unchanged.
"""

from __future__ import annotations

import os

import numpy as np

from ..errors import WarpgaussError


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """(N, 4) unit quaternions (x, y, z, w) -> (N, 3, 3) rotation matrices (as Warp's quat_to_matrix)."""
    q = np.asarray(q, np.float64)
    q = q / np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-300)
    x, y, z, w = q.T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=1,
    )


def matrix_to_quat(r: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotation matrices -> (N, 4) unit quaternions (x, y, z, w), w >= 0 (Shepperd's method)."""
    r = np.asarray(r, np.float64)
    n = r.shape[0]
    q = np.empty((n, 4))
    tr = r[:, 0, 0] + r[:, 1, 1] + r[:, 2, 2]
    diag = np.stack([r[:, 0, 0], r[:, 1, 1], r[:, 2, 2]], 1)
    case = np.where(tr > diag.max(axis=1), 3, diag.argmax(axis=1))
    for c in range(4):
        m = case == c
        if not m.any():
            continue
        R = r[m]
        if c == 3:
            s = 2.0 * np.sqrt(1.0 + tr[m])
            q[m] = np.stack([(R[:, 2, 1] - R[:, 1, 2]) / s, (R[:, 0, 2] - R[:, 2, 0]) / s, (R[:, 1, 0] - R[:, 0, 1]) / s, 0.25 * s], 1)
        else:
            i, j, k = c, (c + 1) % 3, (c + 2) % 3
            s = 2.0 * np.sqrt(np.maximum(1.0 + R[:, i, i] - R[:, j, j] - R[:, k, k], 1e-300))
            v = np.empty((R.shape[0], 4))
            v[:, i] = 0.25 * s
            v[:, j] = (R[:, j, i] + R[:, i, j]) / s
            v[:, k] = (R[:, k, i] + R[:, i, k]) / s
            v[:, 3] = (R[:, k, j] - R[:, j, k]) / s
            q[m] = v
    q *= np.where(q[:, 3:4] < 0, -1.0, 1.0)
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def primitive_arrays(model, *, voxel_units: bool = False) -> dict[str, np.ndarray]:
    """Centres and per-primitive attributes as float arrays (see the module docstring).

    Returns:
        dict with ``points`` (N, 3), ``scale`` (N, 3), ``orientation`` (N, 4), ``rotation`` (N, 9),
        ``value``, ``value_normalised``, ``weight`` (N,).
    """
    p = model.params.astype(np.float64)
    mu, log_s, q = p[:, 0:3], p[:, 3:6], p[:, 6:10]
    rot = quat_to_matrix(q)
    scale = np.exp(np.clip(log_s, -9.0, 12.0))  # as the field kernels clamp them
    g = model.header["grid"]
    spacing = np.asarray(g.get("spacing", (1.0, 1.0, 1.0)), np.float64)
    origin = np.asarray(g.get("origin", (0.0, 0.0, 0.0)), np.float64)
    if voxel_units:
        points = mu
    else:
        points = origin + mu * spacing
        if np.allclose(np.abs(spacing), abs(spacing[0])) and np.all(spacing > 0):
            scale = scale * spacing[0]
        else:  # Sigma_phys = D R diag(s^2) R^T D, re-factored per primitive
            d = np.diag(spacing)
            cov = d @ (rot * (scale**2)[:, None, :]) @ np.swapaxes(rot, 1, 2) @ d
            lam, vec = np.linalg.eigh(cov)
            vec *= np.where(np.linalg.det(vec) < 0, -1.0, 1.0)[:, None, None]
            rot, scale = vec, np.sqrt(np.maximum(lam, 0.0))
    lo, hi = model.value_range
    a = p[:, 10]
    return {
        "points": points,
        "scale": scale,
        "orientation": matrix_to_quat(rot),
        "rotation": rot.reshape(-1, 9),
        "value": lo + a * (hi - lo),
        "value_normalised": a,
        "weight": p[:, 11],
    }


def write_vtp(model, path: str | os.PathLike, *, voxel_units: bool = False, force: bool = False) -> int:
    """Write the primitives as a ``.vtp`` point cloud (atomic); returns the number of points."""
    from ..core.files import atomic_path, check_writable

    if not str(path).lower().endswith(".vtp"):
        raise WarpgaussError(f"{path}: primitives are exported as VTK PolyData; give a .vtp file name")
    check_writable(path, force=force)
    cloud = primitives_polydata(model, voxel_units=voxel_units)
    with atomic_path(path) as tmp:
        cloud.save(str(tmp), binary=True)
    return int(cloud.n_points)


def primitives_polydata(model, *, voxel_units: bool = False):
    """The primitives as a VTK point cloud (pyvista PolyData, one vertex a point) with the arrays of
    :func:`primitive_arrays` (float32), ``value`` active; what :func:`write_vtp` writes."""
    import pyvista as pv

    arr = primitive_arrays(model, voxel_units=voxel_units)
    cloud = pv.PolyData(arr["points"].astype(np.float32))
    for key in ("scale", "orientation", "rotation", "value", "value_normalised", "weight"):
        cloud.point_data[key] = arr[key].astype(np.float32)
    cloud.set_active_scalars("value")
    cloud.field_data["warpgauss_units"] = np.array(["voxel" if voxel_units else "physical"])
    cloud.field_data["orientation_order"] = np.array(["x y z w"])
    cloud.field_data["value_range"] = np.asarray(model.value_range, np.float64)
    return cloud
