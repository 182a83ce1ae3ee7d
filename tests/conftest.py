"""Shared fixtures: Warp devices (CPU always, CUDA when present) and small random primitive sets."""

from __future__ import annotations

import numpy as np
import pytest


def _devices() -> list[str]:
    from warpgauss.core.warp import warp

    wp = warp()
    names = {str(d) for d in wp.get_devices()}  # a CUDA-only Warp build has no "cpu"
    return [d for d in ("cpu", "cuda:0") if d in names]


@pytest.fixture(params=_devices())
def device(request) -> str:
    return request.param


@pytest.fixture
def cpu() -> str:
    """The Warp CPU device (bit-identical reruns are promised there); skips on a CUDA-only build."""
    if "cpu" not in _devices():
        pytest.skip("this Warp build has no CPU device")
    return "cpu"


def random_quaternions(rng: np.random.Generator, n: int) -> np.ndarray:
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def uniform_params(
    rng: np.random.Generator,
    n: int,
    centre: tuple[float, float],
    log_scale: tuple[float, float],
    value: tuple[float, float] = (0.0, 1.0),
    weight: tuple[float, float] = (0.05, 1.0),
) -> np.ndarray:
    """(n, 12) model parameters: centres and log-scales uniform per axis in the given ranges,
    random unit quaternions, a and w uniform (drawn in that order from ``rng``)."""
    p = np.zeros((n, 12), np.float32)
    p[:, 0:3] = rng.uniform(*centre, (n, 3))
    p[:, 3:6] = rng.uniform(*log_scale, (n, 3))
    p[:, 6:10] = random_quaternions(rng, n)
    p[:, 10] = rng.uniform(*value, n)
    p[:, 11] = rng.uniform(*weight, n)
    return p


def random_params(
    rng: np.random.Generator,
    n: int,
    shape_xyz: tuple[int, int, int],
    log_scale: tuple[float, float] = (-0.5, 1.0),
    aniso: float = 1.0,
) -> np.ndarray:
    """Rotated anisotropic primitives of mixed size with centres spread over (and a little past) the grid."""
    p = np.zeros((n, 12), np.float32)
    lo = -0.5 - 1.0
    p[:, 0:3] = rng.uniform(lo, np.asarray(shape_xyz) - 0.5 + 1.0, size=(n, 3))
    base = rng.uniform(*log_scale, size=(n, 1))
    p[:, 3:6] = base + rng.uniform(-np.log(aniso) / 2, np.log(aniso) / 2, size=(n, 3))
    p[:, 6:10] = random_quaternions(rng, n)
    p[:, 10] = rng.uniform(0.0, 1.0, n)
    p[:, 11] = rng.uniform(0.05, 1.0, n)
    return p


def assert_matches_atomic_scatter(r, grads: list, pairs: np.ndarray) -> None:
    """The refiner's pair gradients ``grads`` and pair counts ``pairs`` (from its own pass at the
    current points) equal the point-major atomic scatter's: the same pairs, the same sums to
    float32 rounding (another summation order)."""
    from warpgauss.kernels import backward as kb

    r.accumulate(kb.accumulate_pairs)
    np.testing.assert_array_equal(pairs, r.back_pairs.numpy())
    for x, y in zip(grads, (a.numpy() for a in r.pair_grads)):
        scale = float(np.abs(y).max())
        assert scale > 0
        np.testing.assert_allclose(x, y, rtol=0, atol=2e-5 * scale)
