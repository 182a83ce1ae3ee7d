"""The paper's pre-run check: the training path against the dense all-pairs reference."""

from __future__ import annotations

import numpy as np

from ...errors import WarpgaussError
from .refiner import Refiner


def self_test(refiner: Refiner, points: int = 64) -> dict:
    """The paper's pre-run check: binned vs dense values and gradients on a few samples.

    Draws samples, evaluates them through the training path (bins, split or point-major kernels)
    and against every primitive, and compares V~, rho, the contributing pairs (forward and
    backward) and every accumulated gradient, on the refiner's current primitives.

    Returns:
        The worst differences; raises :class:`WarpgaussError` if the two paths disagree.
    """
    from ...field.gaussians import GaussianField
    from ...kernels import backward as kb

    k = min(points, refiner.m)
    refiner.sample()  # the training state is left as it was (samples are redrawn by the next step)
    refiner.forward_backward()
    v = refiner.value.numpy()[:k].copy()
    d = refiner.density.numpy()[:k].copy()
    c = refiner.pairs.numpy()[:k].copy()
    refiner.accumulate(count=k)
    binned = [a.numpy().copy() for a in refiner.pair_grads]
    pairs_b = refiner.back_pairs.numpy()[:k].copy()
    refiner.accumulate(kb.accumulate_pairs_dense, count=k)
    dense = [a.numpy().copy() for a in refiner.pair_grads]
    pairs_d = refiner.back_pairs.numpy()[:k].copy()
    refiner.state.zero_grads()
    pts = refiner.points.numpy()[:k]
    vd, dd, cd = GaussianField(refiner.model_params(), refiner.dv.field.shape_xyz, refiner.device).evaluate_dense(pts)
    scale = max(float(np.abs(x).max()) for x in dense) or 1.0
    result = {
        "points": k,
        "value_max_abs_diff": float(np.abs(v - vd).max()),
        "density_max_rel_diff": float(np.abs(d - dd).max() / max(float(np.abs(dd).max()), 1.0)),
        "pairs_equal": bool(np.array_equal(c, cd) and np.array_equal(pairs_b, pairs_d) and np.array_equal(c, pairs_b)),
        "gradient_max_rel_diff": max(float(np.abs(b - x).max()) / scale for b, x in zip(binned, dense)),
    }
    result["passed"] = bool(
        result["pairs_equal"]
        and result["value_max_abs_diff"] < 1e-4
        and result["density_max_rel_diff"] < 1e-4
        and result["gradient_max_rel_diff"] < 1e-4
    )
    if not result["passed"]:
        raise WarpgaussError(f"self-test failed: binned and dense evaluation disagree ({result}); please report this")
    return result
