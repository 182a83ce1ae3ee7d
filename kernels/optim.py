"""Adam on the raw primitive parameters, with the parameter constraints applied after each step."""

import warp as wp

from .field import safe_unit_quat, vec12

wp.set_module_options({"enable_backward": False})

LOGIT_BOUND = wp.constant(12.0)  # |weight logit| <= 12: w in [6e-6, 1 - 6e-6]


@wp.func
def unit_quaternion(p: vec12) -> vec12:
    """p with its quaternion (slots 6-9) normalised, or the identity if it collapsed to zero."""
    q = safe_unit_quat(p[6], p[7], p[8], p[9])
    p[6] = q[0]
    p[7] = q[1]
    p[8] = q[2]
    p[9] = q[3]
    return p


@wp.func
def all_finite(g: vec12) -> bool:
    for k in range(12):
        if not wp.isfinite(g[k]):
            return False
    return True


@wp.kernel
def adam_step(
    params: wp.array(dtype=vec12),  # [N] raw parameters, updated in place
    grad: wp.array(dtype=vec12),  # [N]
    m1: wp.array(dtype=vec12),  # [N] first moments
    m2: wp.array(dtype=vec12),  # [N] second moments
    lr: vec12,  # learning rate of each parameter slot (one per group: mu, scale, rotation, a, w)
    lr_scale: float,  # schedule factor of this step (decay)
    beta1: float,
    beta2: float,
    eps: float,
    bc1: float,  # 1 - beta1^t
    bc2: float,  # 1 - beta2^t
    log_lo: float,  # hard bounds on log-sigma after the step
    log_hi: float,
    skipped: wp.array(dtype=int),  # [1] out: primitives whose gradient was not finite this step
):
    """torch.optim.Adam (no weight decay) per primitive, then the constraints (one thread each).

    A primitive whose gradient is all zero (no sample touched it) is left unchanged, moments too,
    as in gsplat's sparse/visible Adam: with thousands of samples and up to millions of
    primitives most are untouched in a step, and dense Adam would keep moving them on stale
    momentum. A primitive whose gradient has a non-finite entry is left unchanged and counted.
    """
    i = wp.tid()
    g = grad[i]
    if not all_finite(g):
        wp.atomic_add(skipped, 0, 1)
        return
    if wp.length_sq(g) == 0.0:
        return  # not visible this iteration: parameters and moments stay (sparse Adam)
    p = params[i]
    a = m1[i]
    b = m2[i]
    for k in range(12):
        a[k] = beta1 * a[k] + (1.0 - beta1) * g[k]
        b[k] = beta2 * b[k] + (1.0 - beta2) * g[k] * g[k]
        p[k] = p[k] - lr_scale * lr[k] * (a[k] / bc1) / (wp.sqrt(b[k] / bc2) + eps)
    # constraints: unit quaternion (identity if it collapsed), bounded log-scales and logit
    p = unit_quaternion(p)
    for k in range(3, 6):
        p[k] = wp.clamp(p[k], log_lo, log_hi)
    p[11] = wp.clamp(p[11], -LOGIT_BOUND, LOGIT_BOUND)
    params[i] = p
    m1[i] = a
    m2[i] = b


@wp.kernel
def to_raw(params: wp.array(dtype=vec12), out: wp.array(dtype=vec12)):
    """Model parameters (weight w) -> training parameters (weight logit)."""
    i = wp.tid()
    p = params[i]
    w = wp.clamp(p[11], 1.0e-6, 1.0 - 1.0e-6)
    p[11] = wp.clamp(wp.log(w / (1.0 - w)), -LOGIT_BOUND, LOGIT_BOUND)
    out[i] = p


@wp.kernel
def to_model(params: wp.array(dtype=vec12), out: wp.array(dtype=vec12)):
    """Training parameters -> model parameters (unit quaternion, weight = sigmoid(logit))."""
    i = wp.tid()
    p = unit_quaternion(params[i])
    p[11] = 1.0 / (1.0 + wp.exp(-p[11]))
    out[i] = p
