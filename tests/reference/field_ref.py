"""float64 numpy reference of the truncated, density-normalised Gaussian mixture (SPEC section 2)."""

from __future__ import annotations

import numpy as np

RHO0 = 0.05
TRUNC_M2 = 25.0


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """(N,4) quaternions in (x, y, z, w) order -> (N,3,3) rotation matrices (normalised first)."""
    q = np.asarray(q, np.float64)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    x, y, z, w = q.T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=1,
    )


def covariances(params: np.ndarray) -> np.ndarray:
    """(N,3,3) Sigma = R diag(exp(2 s)) R^T."""
    p = np.asarray(params, np.float64)
    R = quat_to_matrix(p[:, 6:10])
    s2 = np.exp(2.0 * p[:, 3:6])
    return np.einsum("nij,nj,nkj->nik", R, s2, R)


def field(params: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(V~, rho, contributing pairs) at points (M,3), dense, float64."""
    p = np.asarray(params, np.float64)
    pts = np.asarray(points, np.float64)
    prec = np.linalg.inv(covariances(p))
    d = pts[:, None, :] - p[None, :, :3]  # (M, N, 3)
    m = np.einsum("mni,nij,mnj->mn", d, prec, d)
    g = np.where(m < TRUNC_M2, np.exp(-0.5 * m), 0.0)
    w, a = p[:, 11], p[:, 10]
    num = g @ (w * a)
    den = g @ w
    return num / np.maximum(den, RHO0), den, (m < TRUNC_M2).sum(1)
