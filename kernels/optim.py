"""Adam on the raw primitive parameters, with the parameter constraints applied after each step.

Training keeps its state in *slot order*: primitives sorted by bin cell, re-sorted only every few
iterations (:func:`permute_slots`). Between re-bins :func:`refine_update` updates each touched slot
in place (chain rule, Adam, constraints, re-preparation), so an iteration costs nothing per
untouched primitive beyond one read, and :class:`SlotBounds` keeps the bins exact meanwhile.
"""

import warp as wp

from .analysis import trilinear
from .backward import anchor_target, raw_gradient, touched
from .field import BinnedPrimitives, bin_level, conic_of, level_cell, prepare_one, safe_unit_quat, vec12

wp.set_module_options({"enable_backward": False})

LOGIT_BOUND = wp.constant(12.0)  # |weight logit| <= 12: w in [6e-6, 1 - 6e-6]


@wp.func
def with_quaternion(p: vec12, q: wp.quat) -> vec12:
    """p with q (x, y, z, w) in its quaternion slots 6-9."""
    p[6] = q[0]
    p[7] = q[1]
    p[8] = q[2]
    p[9] = q[3]
    return p


@wp.func
def unit_quaternion(p: vec12) -> vec12:
    """p with its quaternion (slots 6-9) normalised, or the identity if it collapsed to zero."""
    return with_quaternion(p, safe_unit_quat(p[6], p[7], p[8], p[9]))


@wp.func
def all_finite(g: vec12) -> bool:
    for k in range(12):
        if not wp.isfinite(g[k]):
            return False
    return True


LIST_MARGIN = wp.constant(1.0e-4)  # voxels (and share of the coordinate) kept clear of a listed face


@wp.func
def fits_list(mu: wp.vec3, ext: wp.vec3, lo: wp.vec3, hi: wp.vec3) -> bool:
    """Whether a primitive's box stays inside the point cells it is listed in (see
    :mod:`warpgauss.kernels.lists`), with a margin against rounding in the cell lookup."""
    for k in range(3):
        m = LIST_MARGIN * (1.0 + wp.abs(mu[k]) + ext[k])
        if mu[k] - ext[k] < lo[k] + m or mu[k] + ext[k] > hi[k] - m:
            return False
    return True


@wp.func
def adam_update(
    p: vec12,
    g: vec12,
    a: vec12,
    b: vec12,
    lr: vec12,
    lr_scale: float,
    beta1: float,
    beta2: float,
    eps: float,
    bc1: float,
    bc2: float,
    log_lo: float,
    log_hi: float,
):
    """One Adam step of one primitive and its constraints; returns (parameters, m1, m2)."""
    for k in range(12):
        a[k] = beta1 * a[k] + (1.0 - beta1) * g[k]
        b[k] = beta2 * b[k] + (1.0 - beta2) * g[k] * g[k]
        p[k] = p[k] - lr_scale * lr[k] * (a[k] / bc1) / (wp.sqrt(b[k] / bc2) + eps)
    # constraints: unit quaternion (identity if it collapsed), bounded log-scales and logit
    p = unit_quaternion(p)
    for k in range(3, 6):
        p[k] = wp.clamp(p[k], log_lo, log_hi)
    p[11] = wp.clamp(p[11], -LOGIT_BOUND, LOGIT_BOUND)
    return p, a, b


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
    p, a, b = adam_update(params[i], g, m1[i], m2[i], lr, lr_scale, beta1, beta2, eps, bc1, bc2, log_lo, log_hi)
    if not (all_finite(p) and all_finite(a) and all_finite(b)):
        wp.atomic_add(skipped, 0, 1)  # a non-finite step (rate, bias correction) never lands
        return
    params[i] = p
    m1[i] = a
    m2[i] = b


@wp.struct
class SlotBounds:
    """Where each training slot's primitive may go before it must be re-binned.

    A primitive binned into cell c (edge S) of its level is found by every point whose 3^3
    neighbourhood includes c. That stays true after it moves and reshapes as long as, per axis,
    its half-extent plus its centre's distance outside the cell is at most S (edge cells extend
    to infinity outwards, because cell lookups clamp there).
    """

    lo: wp.array(dtype=wp.vec3)  # [N] lower cell faces (-BIG on the grid's first cell)
    hi: wp.array(dtype=wp.vec3)  # [N] upper cell faces (+BIG on the last)
    cell: wp.array(dtype=float)  # [N] cell edge S of the slot's level
    # the region of the point cells the slot is listed in (kernels.lists; +-BIG without lists):
    # the forward pass through the lists stays exact while the box stays inside it
    box_lo: wp.array(dtype=wp.vec3)  # [N]
    box_hi: wp.array(dtype=wp.vec3)  # [N]


BIG = wp.constant(1.0e30)
REACH_SLACK = wp.constant(1.1)  # headroom on a deferred step's reach: the next gradient differs a little


@wp.func
def cell_faces(first: wp.vec3i, last: wp.vec3i, size: float, dims: wp.vec3i):
    """(lower, upper) faces of the cells ``first`` .. ``last`` (per axis) of a grid of ``dims``
    cells of edge ``size`` starting at -0.5; a face on the grid's boundary is +-BIG, since cell
    lookups clamp there (edge cells reach to infinity outwards)."""
    lo = wp.vec3()
    hi = wp.vec3()
    for k in range(3):
        lo[k] = wp.where(first[k] == 0, -BIG, float(first[k]) * size - 0.5)
        hi[k] = wp.where(last[k] == dims[k] - 1, BIG, float(last[k] + 1) * size - 0.5)
    return lo, hi


@wp.kernel
def effective_radius(radius: wp.array(dtype=float), reach: wp.array(dtype=float)):
    """Binning radius = max(extent, the reach a deferred step asked for)."""
    i = wp.tid()
    radius[i] = wp.max(radius[i], reach[i])


@wp.kernel
def permute_slots(
    perm: wp.array(dtype=int),  # [>=N] old slot of each new slot (cell order)
    raw: wp.array(dtype=vec12),  # [N] old slot order
    m1: wp.array(dtype=vec12),
    m2: wp.array(dtype=vec12),
    ids: wp.array(dtype=int),  # [N] primitive id of each old slot
    mu: wp.array(dtype=wp.vec3),  # [N] prepared, old slot order
    radius: wp.array(dtype=float),
    level_size: wp.array(dtype=float),
    level_dims: wp.array(dtype=wp.vec3i),
    raw_out: wp.array(dtype=vec12),  # [N] out: new slot order
    m1_out: wp.array(dtype=vec12),
    m2_out: wp.array(dtype=vec12),
    ids_out: wp.array(dtype=int),
    bounds: SlotBounds,  # out
):
    """Move the training state into cell order and record each slot's cell (one thread per slot)."""
    i = wp.tid()
    o = perm[i]
    raw_out[i] = raw[o]
    m1_out[i] = m1[o]
    m2_out[i] = m2[o]
    ids_out[i] = ids[o]
    lev = bin_level(radius[o], level_size)
    size = level_size[lev]
    dims = level_dims[lev]
    c = level_cell(mu[o], size, dims)
    lo, hi = cell_faces(c, c, size, dims)
    bounds.lo[i] = lo
    bounds.hi[i] = hi
    bounds.cell[i] = size
    bounds.box_lo[i] = wp.vec3(-BIG, -BIG, -BIG)  # the cell lists, when built, narrow these
    bounds.box_hi[i] = wp.vec3(BIG, BIG, BIG)


@wp.func
def fits_slot(mu: wp.vec3, ext: wp.vec3, lo: wp.vec3, hi: wp.vec3, size: float) -> bool:
    """Whether a primitive of centre mu and half-extents ext is still found from its slot's cell."""
    for k in range(3):
        outside = wp.max(wp.max(lo[k] - mu[k], mu[k] - hi[k]), 0.0)
        if ext[k] + outside > size:
            return False
    return True


@wp.kernel
def begin_iteration(
    counter: wp.array(dtype=int),  # [1] iteration index
    schedule: wp.array(dtype=wp.vec4),  # [T] (learning-rate factor, smoothness weight, bc1, bc2)
    streams: wp.array(dtype=int),  # [T] sampler RNG stream of each iteration
    touch: wp.array(dtype=float),  # [1] learning-rate factor from the contact density
    now: wp.array(dtype=wp.vec4),  # [1] out: this iteration's (lr factor x touch, smoothness, bc1, bc2)
    stream: wp.array(dtype=int),  # [2] out: this iteration's stream, then the next one's
):
    """Pick this iteration's schedule values on the device, so that a captured graph can replay."""
    t = wp.min(counter[0], schedule.shape[0] - 1)
    s = schedule[t]
    now[0] = wp.vec4(s[0] * touch[0], s[1], s[2], s[3])
    stream[0] = streams[t]
    stream[1] = streams[wp.min(counter[0] + 1, schedule.shape[0] - 1)]


@wp.kernel
def end_iteration(counter: wp.array(dtype=int)):
    counter[0] = counter[0] + 1


@wp.func
def on_grid(x: float, bits: int) -> float:
    """x rounded to the nearest multiple of 2^-bits (the coded format's absolute grids)."""
    s = float(1 << bits)
    return wp.round(x * s) / s


@wp.struct
class QuantGrid:
    """Bit depths of the coded format's grids (:mod:`warpgauss.format.coded`); on = 0: no projection."""

    on: int
    mu: int
    s: int
    q: int
    a: int
    w: int
    geometry_only: int  # 1: leave a and w as they are (refitted after the geometry is fixed)


_R2 = 0.7071067811865476  # 1 / sqrt 2
_mat24x4 = wp.types.matrix(shape=(24, 4), dtype=float)
_mat24x3i = wp.types.matrix(shape=(24, 3), dtype=int)
# the 24 turns of a box's axes onto themselves, (x, y, z, w), the identity first, and the old axis
# each new axis is: as warpgauss.format.coded.OCTAHEDRAL_Q and OCTAHEDRAL_AXES (a test holds them equal)
OCTAHEDRAL_Q = wp.constant(
    _mat24x4(
        *(0.0, 0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0),
        *(_R2, 0.0, 0.0, _R2, -_R2, 0.0, 0.0, _R2, 0.0, _R2, 0.0, _R2, 0.0, -_R2, 0.0, _R2),
        *(0.0, 0.0, _R2, _R2, 0.0, 0.0, -_R2, _R2, _R2, _R2, 0.0, 0.0, _R2, -_R2, 0.0, 0.0),
        *(_R2, 0.0, _R2, 0.0, _R2, 0.0, -_R2, 0.0, 0.0, _R2, _R2, 0.0, 0.0, _R2, -_R2, 0.0),
        *(0.5, 0.5, 0.5, 0.5, 0.5, 0.5, -0.5, 0.5, 0.5, -0.5, 0.5, 0.5, 0.5, -0.5, -0.5, 0.5),
        *(-0.5, 0.5, 0.5, 0.5, -0.5, 0.5, -0.5, 0.5, -0.5, -0.5, 0.5, 0.5, -0.5, -0.5, -0.5, 0.5),
    )
)
OCTAHEDRAL_AXES = wp.constant(
    _mat24x3i(
        *(0, 1, 2, 0, 1, 2, 0, 1, 2, 0, 1, 2, 0, 2, 1, 0, 2, 1, 2, 1, 0, 2, 1, 0),
        *(1, 0, 2, 1, 0, 2, 1, 0, 2, 1, 0, 2, 2, 1, 0, 2, 1, 0, 0, 2, 1, 0, 2, 1),
        *(1, 2, 0, 2, 0, 1, 2, 0, 1, 1, 2, 0, 2, 0, 1, 1, 2, 0, 1, 2, 0, 2, 0, 1),
    )
)
CANONICAL_MARGIN = wp.constant(1.0e-5)  # as warpgauss.format.coded.CANONICAL_MARGIN
TAN_EIGHTH = wp.constant(0.41421356237309503)  # tan(pi / 8)


@wp.func
def quat_product(a: wp.vec4, b: wp.vec4) -> wp.vec4:
    """The quaternion product a b, (x, y, z, w) order."""
    return wp.vec4(
        a[3] * b[0] + b[3] * a[0] + a[1] * b[2] - a[2] * b[1],
        a[3] * b[1] + b[3] * a[1] + a[2] * b[0] - a[0] * b[2],
        a[3] * b[2] + b[3] * a[2] + a[0] * b[1] - a[1] * b[0],
        a[3] * b[3] - a[0] * b[0] - a[1] * b[1] - a[2] * b[2],
    )


@wp.func
def nearest_turn(q: wp.vec4) -> int:
    """The turn k of :data:`OCTAHEDRAL_Q` that brings unit q nearest the identity (largest |w| of
    q g_k; the first of ties), as :func:`warpgauss.format.coded.canonical` chooses it."""
    best = int(0)
    top = wp.abs(q[3])
    for k in range(1, 24):
        wk = wp.abs(q[3] * OCTAHEDRAL_Q[k, 3] - q[0] * OCTAHEDRAL_Q[k, 0] - q[1] * OCTAHEDRAL_Q[k, 1] - q[2] * OCTAHEDRAL_Q[k, 2])
        if wk > top:
            top = wk
            best = k
    return best


@wp.func
def turned(p: vec12, q: wp.vec4, k: int) -> vec12:
    """The same Gaussian with its axes turned by g_k: quaternion q g_k (w >= 0), log-scales moved
    with the axes (q: p's unit quaternion)."""
    r = quat_product(q, wp.vec4(OCTAHEDRAL_Q[k, 0], OCTAHEDRAL_Q[k, 1], OCTAHEDRAL_Q[k, 2], OCTAHEDRAL_Q[k, 3]))
    if r[3] < 0.0:
        r = -r
    out = p
    for i in range(3):
        out[3 + i] = p[3 + OCTAHEDRAL_AXES[k, i]]
    return with_quaternion(out, wp.quat(r[0], r[1], r[2], r[3]))


@wp.func
def turned_back(t: vec12, k: int, like: wp.vec4) -> vec12:
    """Undo :func:`turned`: quaternion t's times g_k's conjugate, signed as ``like``, log-scales
    back on their axes."""
    qt = wp.vec4(t[6], t[7], t[8], t[9])
    r = quat_product(qt, wp.vec4(-OCTAHEDRAL_Q[k, 0], -OCTAHEDRAL_Q[k, 1], -OCTAHEDRAL_Q[k, 2], OCTAHEDRAL_Q[k, 3]))
    if wp.dot(r, like) < 0.0:
        r = -r
    out = t
    for i in range(3):
        out[3 + OCTAHEDRAL_AXES[k, i]] = t[3 + i]
    return with_quaternion(out, wp.quat(r[0], r[1], r[2], r[3]))


@wp.func
def project_turned(p: vec12, g: QuantGrid) -> vec12:
    """A primitive already turned nearest the identity (:func:`turned`) on the coded format's
    grids: centres, log-scales and values to multiples of 2^-bits, the weight to a multiple of
    2^-w in [2^-w, 1 - 2^-w] (as a logit), the rotation to its smallest-three levels with the
    implied component the largest and the rounded rotation still nearest the identity by
    :data:`CANONICAL_MARGIN` (as :func:`warpgauss.format.coded.quantise` codes it)."""
    for k in range(3):
        p[k] = on_grid(p[k], g.mu)
        p[3 + k] = on_grid(p[3 + k], g.s)
    if g.geometry_only == 0:
        p[10] = on_grid(p[10], g.a)
        sw = float(1 << g.w)
        w = 1.0 / (1.0 + wp.exp(-p[11]))
        wq = wp.clamp(wp.round(w * sw), 1.0, sw - 1.0) / sw
        p[11] = wp.log(wq / (1.0 - wq))
    q = wp.vec4(p[6], p[7], p[8], p[9])
    big = int(0)
    for k in range(1, 4):
        if wp.abs(q[k]) > wp.abs(q[big]):
            big = k
    if q[big] < 0.0:
        q = -q
    r = _R2
    lev = float((1 << g.q) - 2)
    c = wp.vec4(0.0)
    for k in range(4):
        if k != big:
            c[k] = wp.clamp(wp.round((q[k] + r) / (2.0 * r) * lev), 0.0, lev)
    mid = float((1 << g.q) / 2 - 1)
    keep = 1.0 - CANONICAL_MARGIN
    for _ in range(64):  # the implied component the largest, the rotation nearest the identity
        s2 = float(0.0)
        top = int(-1)
        for k in range(4):
            if k != big:
                v = c[k] * (2.0 * r / lev) - r
                s2 += v * v
                if top < 0:
                    top = k
                elif wp.abs(c[k] - mid) > wp.abs(c[top] - mid):
                    top = k
        largest = wp.sqrt(wp.max(0.0, 1.0 - s2))
        vt = wp.abs(c[top] * (2.0 * r / lev) - r)
        inside = vt < largest * (1.0 - 1.0e-6)
        if big == 3:
            total = float(0.0)
            for k in range(3):
                total += wp.abs(c[k] * (2.0 * r / lev) - r)
            inside = inside and vt <= TAN_EIGHTH * largest * keep and total <= largest * keep
        if inside:
            break
        if c[top] > mid:
            c[top] = c[top] - 1.0
        else:
            c[top] = c[top] + 1.0
    s2 = float(0.0)
    for k in range(4):
        if k != big:
            q[k] = c[k] * (2.0 * r / lev) - r
            s2 += q[k] * q[k]
    q[big] = wp.sqrt(wp.max(0.0, 1.0 - s2))
    q = q / wp.length(q)
    return with_quaternion(p, wp.quat(q[0], q[1], q[2], q[3]))


@wp.func
def project_one(p: vec12, g: QuantGrid) -> vec12:
    """One primitive's training parameters as the coded format stores them: turned nearest the
    identity (:func:`nearest_turn`), then on its grids (:func:`project_turned`)."""
    uq = safe_unit_quat(p[6], p[7], p[8], p[9])
    q = wp.vec4(uq[0], uq[1], uq[2], uq[3])
    return project_turned(turned(p, q, nearest_turn(q)), g)


@wp.func
def evaluated(p: vec12, g: QuantGrid) -> vec12:
    """The parameters evaluation sees: while quantisation-aware, the Gaussian the coded format
    stores, in p's own axes and quaternion sign (so that its gradients step p straight through);
    else p."""
    if g.on != 0:
        uq = safe_unit_quat(p[6], p[7], p[8], p[9])
        q = wp.vec4(uq[0], uq[1], uq[2], uq[3])
        k = nearest_turn(q)
        return turned_back(project_turned(turned(p, q, k), g), k, q)
    return p


@wp.kernel
def refine_update(
    raw: wp.array(dtype=vec12),  # [N] training parameters, slot order (updated)
    m1: wp.array(dtype=vec12),  # [N] Adam moments (updated)
    m2: wp.array(dtype=vec12),
    d_mu: wp.array(dtype=wp.vec3),  # [N] pair gradients of this iteration (read, then zeroed)
    d_ls: wp.array(dtype=wp.vec3),
    d_rot: wp.array(dtype=wp.mat33),
    d_a: wp.array(dtype=float),
    d_w: wp.array(dtype=float),
    vol: wp.array3d(dtype=float),
    anchors: wp.array(dtype=float),  # [N] anchor targets stored at the last re-bin (cached only)
    cached: int,  # 1: the anchor targets from anchors (a volume in host memory; anchor_target)
    l_anchor: float,
    l_aniso: float,
    l_cap: float,
    log_aniso: float,
    log_cap: float,
    log_min: float,
    lr: vec12,
    now: wp.array(dtype=wp.vec4),  # [1] (lr factor, smoothness, bc1, bc2) of this iteration
    beta1: float,
    beta2: float,
    eps: float,
    log_lo: float,
    log_hi: float,
    bounds: SlotBounds,
    prims: BinnedPrimitives,  # prepared primitives, slot order (updated)
    quant: QuantGrid,  # on: evaluation sees the parameters on the coded grids (straight-through)
    ids: wp.array(dtype=int),  # [N] primitive of each slot
    n_train: int,  # primitives 0 .. n_train - 1 are stepped; the rest are frozen (seen, never moved)
    counts: wp.array(dtype=int),  # [2] out: (non-finite steps skipped, updates deferred to the next re-bin)
    reach: wp.array(dtype=float),  # [N] out: binning radius a deferred slot needs at the next re-bin
):
    """Chain rule, sparse Adam, constraints and re-preparation of one slot, fused (one thread per slot).

    A frozen primitive (a finished neighbour brick's, see :mod:`warpgauss.encoding.scale.bricks`) takes part in
    evaluation and its gradients are cleared, but it never steps.

    An untouched slot costs one read of its pair gradients. A step that would carry a primitive
    beyond what its cell's neighbourhood covers (:class:`SlotBounds`) is deferred: parameters and
    moments stay, and the slot records the reach the step needs (extent plus move), which the
    next re-bin uses to choose its level, so that the step fits then and evaluation stays exact.
    A step whose result is not finite (a bad rate or bias correction) is skipped and counted.
    """
    j = wp.tid()
    if not touched(j, d_mu, d_a, d_w):
        return
    if ids[j] >= n_train:
        d_mu[j] = wp.vec3()
        d_ls[j] = wp.vec3()
        d_rot[j] = wp.mat33()
        d_a[j] = 0.0
        d_w[j] = 0.0
        return
    pe0 = evaluated(raw[j], quant)
    g, reg = raw_gradient(
        pe0,
        d_mu[j],
        d_ls[j],
        d_rot[j],
        d_a[j],
        d_w[j],
        anchor_target(vol, anchors, cached, j, pe0),
        l_anchor,
        l_aniso,
        l_cap,
        log_aniso,
        log_cap,
        log_min,
        1.0 / float(raw.shape[0]),
    )
    d_mu[j] = wp.vec3()
    d_ls[j] = wp.vec3()
    d_rot[j] = wp.mat33()
    d_a[j] = 0.0
    d_w[j] = 0.0
    if not all_finite(g):
        wp.atomic_add(counts, 0, 1)
        return
    s = now[0]
    p, a, b = adam_update(raw[j], g, m1[j], m2[j], lr, s[0], beta1, beta2, eps, s[2], s[3], log_lo, log_hi)
    if not (all_finite(p) and all_finite(a) and all_finite(b)):
        wp.atomic_add(counts, 0, 1)  # a non-finite step (rate, bias correction) never lands
        return
    pe = evaluated(p, quant)  # straight-through: the step lands on p, evaluation reads pe
    R, inv, e, wt = prepare_one(pe, 1)
    mu = wp.vec3(pe[0], pe[1], pe[2])
    if not (fits_slot(mu, e, bounds.lo[j], bounds.hi[j], bounds.cell[j]) and fits_list(mu, e, bounds.box_lo[j], bounds.box_hi[j])):
        # the next re-bin gives this slot a level whose cells cover the step it wanted
        old = prims.mu[j]  # where evaluation has the primitive now
        need = float(0.0)
        for k in range(3):
            need = wp.max(need, e[k] + wp.abs(mu[k] - old[k]))
        reach[j] = REACH_SLACK * need
        wp.atomic_add(counts, 1, 1)
        return
    raw[j] = p
    m1[j] = a
    m2[j] = b
    prims.mu[j] = mu
    prims.rot[j] = R
    prims.inv_s2[j] = inv
    prims.conic[j] = conic_of(R, inv)
    prims.ext[j] = e
    prims.a[j] = pe[10]
    prims.w[j] = wt


@wp.kernel
def anchor_targets(raw: wp.array(dtype=vec12), quant: QuantGrid, vol: wp.array3d(dtype=float), anchors: wp.array(dtype=float)):
    """anchors[j] = V at slot j's centre as evaluation sees it: refine_update's cached anchor targets."""
    p = evaluated(raw[wp.tid()], quant)
    anchors[wp.tid()] = trilinear(vol, wp.vec3(p[0], p[1], p[2]))


@wp.func
def model_of(p: vec12) -> vec12:
    """Training parameters -> model parameters (unit quaternion, weight = sigmoid(logit))."""
    p = unit_quaternion(p)
    p[11] = 1.0 / (1.0 + wp.exp(-p[11]))
    return p


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
    out[i] = model_of(params[i])


@wp.kernel
def to_model_slots(raw: wp.array(dtype=vec12), ids: wp.array(dtype=int), out: wp.array(dtype=vec12)):
    """:func:`to_model` from slot order back to primitive order (out[ids[j]] = model of slot j)."""
    j = wp.tid()
    out[ids[j]] = model_of(raw[j])


@wp.kernel
def slots_from_ids(src: wp.array(dtype=vec12), ids: wp.array(dtype=int), out: wp.array(dtype=vec12)):
    """out[j] = src[ids[j]]: primitive order into slot order."""
    j = wp.tid()
    out[j] = src[ids[j]]


@wp.kernel
def ids_from_slots(src: wp.array(dtype=vec12), ids: wp.array(dtype=int), out: wp.array(dtype=vec12)):
    """out[ids[j]] = src[j]: slot order back to primitive order."""
    j = wp.tid()
    out[ids[j]] = src[j]


@wp.kernel
def project_coded(raw: wp.array(dtype=vec12), g: QuantGrid):
    """Move training parameters onto the coded grids in place (the end of a quantisation-aware run)."""
    i = wp.tid()
    raw[i] = project_one(raw[i], g)


@wp.kernel
def project_copy(raw: wp.array(dtype=vec12), g: QuantGrid, out: wp.array(dtype=vec12)):
    """out = the parameters evaluation sees (see :func:`evaluated`)."""
    i = wp.tid()
    out[i] = evaluated(raw[i], g)
