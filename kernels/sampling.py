"""Stratified training samples (SPEC section 3): 35 % from V > 0.4, 40 % from occupied mid-range
voxels, 25 % uniform, each at a voxel centre moved by up to ``jitter`` voxels along each axis, with
its target the trilinear interpolation there (the voxel's own value at jitter 0) and a partner
point about a voxel away for the smoothness term.

With ``importance`` each sample is weighted by 1 / (D q(v)), q(v) the probability that the draw
picks its voxel v (the three strata's shares over their sizes, summed over the strata v belongs
to) and D about the number of voxels the draw can reach: the weighted value loss is then, in
expectation, the mean squared error over every voxel, the full-grid MSE that EV reports, while
the strata still decide where the samples fall (more samples where the field is busy, each
counting for less). The mean weight is about 1.

When empty samples carry no loss (value-loss weight of empty samples 0, the paper's setting) the
uniform 25 % are drawn among the occupied voxels instead of the whole grid: a sample where
V <= 0.02 would add nothing to any loss term. Otherwise they are drawn over the model's support:
the 4^3 bricks that some primitive's 5-sigma box, widened by SUPPORT_MARGIN voxels, reaches
(:func:`warpgauss.kernels.support.mark_support`, redone at every re-bin). A point outside every 5-sigma box gets exactly 0
and no gradient, so a sample there would only dilute the batch.

A share of the samples may instead follow the error (:func:`accumulate_errors`,
:func:`update_errors`, :func:`error_quota`): each sample adds its weighted squared error to its
4^3 brick (fixed point, integer atomics: the sums do not depend on the order), every re-bin
decays the bricks' running sums and re-draws the quota of each brick in proportion to
sqrt(squared error x voxels) (its summed RMS error), and the error stratum picks a brick by
quota, then one of its voxels uniformly. Its probability joins q(v), so the weighted loss stays an
estimate of the full-grid MSE while more samples fall where the model is wrong.
"""

import warp as wp

from .analysis import OCCUPIED, in_grid, trilinear_axis, usable
from .indexing import (
    BRICK,
    block_voxels,
    brick_origin,
    brick_rank_voxel,
    brick_voxel,
    brick_voxels,
    find_brick,
    grid_voxel,
    grid_voxels,
    rank_below,
)

wp.set_module_options({"enable_backward": False})

HIGH_VALUE = wp.constant(0.4)  # the "high" stratum: normalised value above this


@wp.func
def stratum_value(v: float) -> int:
    """:func:`stratum_of` of a usable voxel whose value ``v`` the caller has read already."""
    if v > HIGH_VALUE:
        return 0
    if v > OCCUPIED:
        return 1
    return -1


@wp.func
def stratum_of(vol: wp.array3d(dtype=float), mask: wp.array3d(dtype=wp.uint8), has_mask: int, k: int, j: int, i: int) -> int:
    """0 high (V > 0.4), 1 occupied mid-range, -1 neither (empty or masked)."""
    if not usable(vol, mask, has_mask, k, j, i):
        return -1
    return stratum_value(vol[k, j, i])


@wp.func
def row_pair(vol: wp.array3d(dtype=float), flat4: wp.array2d(dtype=wp.vec4), wide: int, k: int, j: int, i0: int, i1: int) -> wp.vec2:
    """(V[k, j, i0], V[k, j, i1]) for i1 = i0 or i0 + 1. ``wide``: ``flat4`` views the volume as
    aligned groups of four values, row-major in rows of ``flat4.shape[1]`` groups (a Warp array
    holds fewer than 2^31 elements a dimension), and both are read in one 16-byte load where they
    lie in one group (a volume in host memory: each load over the bus is a transaction of its
    own); else, as without ``wide``, two loads. The linear index is int64: a volume in host
    memory may hold more than 2^31 voxels."""
    ll = (wp.int64(k) * wp.int64(vol.shape[1]) + wp.int64(j)) * wp.int64(vol.shape[2]) + wp.int64(i0)
    q = ll / wp.int64(4)
    r = int(ll - wp.int64(4) * q)
    cols = wp.int64(flat4.shape[1])
    if wide == 0 or q >= wp.int64(flat4.shape[0]) * cols or (i1 != i0 and r == 3):
        return wp.vec2(vol[k, j, i0], vol[k, j, i1])
    a = flat4[int(q / cols), int(q % cols)]
    if i1 == i0:
        return wp.vec2(a[r], a[r])
    return wp.vec2(a[r], a[r + 1])


@wp.func
def trilinear_rows(
    vol: wp.array3d(dtype=float), flat4: wp.array2d(dtype=wp.vec4), wide: int, p: wp.vec3, k: int, j: int, i: int
) -> wp.vec2:
    """(:func:`trilinear` at p bit for bit, V at voxel (k, j, i)): the corners read a row pair at
    a time (:func:`row_pair`), the voxel's own value taken from them where it is a corner (p within
    half a voxel of it), else read."""
    i0, i1, tx = trilinear_axis(p[0], vol.shape[2])
    j0, j1, ty = trilinear_axis(p[1], vol.shape[1])
    k0, k1, tz = trilinear_axis(p[2], vol.shape[0])
    r00 = row_pair(vol, flat4, wide, k0, j0, i0, i1)
    r01 = row_pair(vol, flat4, wide, k0, j1, i0, i1)
    r10 = row_pair(vol, flat4, wide, k1, j0, i0, i1)
    r11 = row_pair(vol, flat4, wide, k1, j1, i0, i1)
    c00 = wp.lerp(r00[0], r00[1], tx)
    c01 = wp.lerp(r01[0], r01[1], tx)
    c10 = wp.lerp(r10[0], r10[1], tx)
    c11 = wp.lerp(r11[0], r11[1], tx)
    value = wp.lerp(wp.lerp(c00, c01, ty), wp.lerp(c10, c11, ty), tz)
    own = float(0.0)
    if (i == i0 or i == i1) and (j == j0 or j == j1) and (k == k0 or k == k1):
        rr = r11
        if k == k0 and j == j0:
            rr = r00
        elif k == k0:
            rr = r01
        elif j == j0:
            rr = r10
        own = wp.where(i == i0, rr[0], rr[1])
    else:
        own = vol[k, j, i]
    return wp.vec2(value, own)


@wp.kernel
def brick_counts(
    vol: wp.array3d(dtype=float),
    mask: wp.array3d(dtype=wp.uint8),
    has_mask: int,
    high: wp.array3d(dtype=wp.int64),  # [bz, by, bx] out: high-stratum voxels in each 4^3 brick (int64: their prefix sums may pass 2^31)
    mid: wp.array3d(dtype=wp.int64),  # [bz, by, bx] out: mid-stratum voxels
    high_bits: wp.array3d(dtype=wp.uint64),  # [bz, by, bx] out: bit d set if the brick's d-th voxel is high
    mid_bits: wp.array3d(dtype=wp.uint64),  # [bz, by, bx] out: the same for the mid stratum
):
    """Per-brick stratum counts and membership bits (one thread per brick; voxel d of a brick is
    :func:`brick_voxel`'s). With their prefix sums the counts index the strata without listing
    voxels: a 1024^3 grid needs 64 MiB per stratum instead of 4 GiB, 192 MiB with the bits, which
    spare a draw reading the brick's voxels (:func:`stratum_voxel`)."""
    bk, bj, bi = wp.tid()
    nh = int(0)
    nm = int(0)
    bh = wp.uint64(0)
    bm = wp.uint64(0)
    for d in range(BRICK * BRICK * BRICK):
        v = brick_voxel(bk, bj, bi, d)
        if in_grid(vol, v[0], v[1], v[2]):
            st = stratum_of(vol, mask, has_mask, v[0], v[1], v[2])
            if st == 0:
                nh += 1
                bh = bh | (wp.uint64(1) << wp.uint64(d))
            elif st == 1:
                nm += 1
                bm = bm | (wp.uint64(1) << wp.uint64(d))
    high[bk, bj, bi] = wp.int64(nh)
    mid[bk, bj, bi] = wp.int64(nm)
    high_bits[bk, bj, bi] = bh
    mid_bits[bk, bj, bi] = bm


ERROR_FIXED = wp.constant(4294967296.0)  # 2^32: the fixed point of the per-brick error sums


@wp.kernel
def accumulate_errors(
    points: wp.array(dtype=wp.vec3),  # [2M] samples, then partners
    loss: wp.array(dtype=wp.vec3),  # [M] point_grads' per-sample loss terms (value first, 1/M x weight x r^2)
    m: int,
    acc: wp.array3d(dtype=wp.int64),  # [bz, by, bx] in/out: fixed-point sums of weight x r^2
):
    """Add each sample's weighted squared error to its 4^3 brick (one thread per sample)."""
    s = wp.tid()
    p = points[s]
    i = wp.clamp(int(wp.floor(p[0] + 0.5)), 0, acc.shape[2] * BRICK - 1)
    j = wp.clamp(int(wp.floor(p[1] + 0.5)), 0, acc.shape[1] * BRICK - 1)
    k = wp.clamp(int(wp.floor(p[2] + 0.5)), 0, acc.shape[0] * BRICK - 1)
    e = loss[s][0] * float(m)
    if e > 0.0 and wp.isfinite(e):  # weights stay below about 10 and errors below 1: the cap only stops a diverging run overflowing
        wp.atomic_add(acc, k / BRICK, j / BRICK, i / BRICK, wp.int64(wp.min(e, 1.0e4) * ERROR_FIXED))


@wp.func
def error_score(e: float, bk: int, bj: int, bi: int, nz: int, ny: int, nx: int) -> float:
    """sqrt(running sum x voxels): the brick's summed RMS error, what its quota follows."""
    return wp.sqrt(e * float(brick_voxels(bk, bj, bi, nz, ny, nx)))


@wp.kernel
def update_errors(
    acc: wp.array3d(dtype=wp.int64),  # [bz, by, bx] in, zeroed: the sums since the last update
    decay: float,  # weight of the running sums before them
    nz: int,
    ny: int,
    nx: int,
    err: wp.array3d(dtype=float),  # [bz, by, bx] in/out: running sums of weight x r^2
    top: wp.array(dtype=float),  # [1] in/out (zeroed before): the largest error_score (max: order-free)
):
    bk, bj, bi = wp.tid()
    e = decay * err[bk, bj, bi] + float(acc[bk, bj, bi]) / ERROR_FIXED
    err[bk, bj, bi] = e
    acc[bk, bj, bi] = wp.int64(0)
    wp.atomic_max(top, 0, error_score(e, bk, bj, bi, nz, ny, nx))


@wp.kernel
def error_quota(
    err: wp.array3d(dtype=float),  # [bz, by, bx] update_errors' running sums
    top: wp.array(dtype=float),  # [1] the largest score
    cap: int,  # the largest quota (the sum of every brick's must fit an int)
    nz: int,
    ny: int,
    nx: int,
    quota: wp.array3d(dtype=int),  # [bz, by, bx] out: the error stratum's draws of each brick, in proportion
):
    bk, bj, bi = wp.tid()
    q = int(0)
    if top[0] > 0.0:
        q = int(float(cap) * (error_score(err[bk, bj, bi], bk, bj, bi, nz, ny, nx) / top[0]))
    quota[bk, bj, bi] = q


@wp.kernel
def pool_errors(
    err: wp.array3d(dtype=float),  # [bz, by, bx] update_errors' running sums
    f: int,  # bricks per block edge
    pooled: wp.array3d(dtype=float),  # [ceil(bz / f), ceil(by / f), ceil(bx / f)] out: each block's sum
):
    """The running sums of each block of f^3 bricks (added in a fixed order)."""
    pk, pj, pi = wp.tid()
    s = float(0.0)
    for dk in range(f):
        for dj in range(f):
            for di in range(f):
                k = pk * f + dk
                j = pj * f + dj
                i = pi * f + di
                if k < err.shape[0] and j < err.shape[1] and i < err.shape[2]:
                    s += err[k, j, i]
    pooled[pk, pj, pi] = s


@wp.func
def pooled_score(pooled: wp.array3d(dtype=float), f: int, bk: int, bj: int, bi: int, nz: int, ny: int, nx: int) -> float:
    """A brick's share of its block's summed RMS error, sqrt(block sum x block voxels), by voxels."""
    pk = bk / f
    pj = bj / f
    pi = bi / f
    vb = float(block_voxels(pk, pj, pi, f, nz, ny, nx))
    return wp.sqrt(pooled[pk, pj, pi] * vb) * float(brick_voxels(bk, bj, bi, nz, ny, nx)) / vb


@wp.kernel
def pooled_top(
    pooled: wp.array3d(dtype=float),
    f: int,
    nz: int,
    ny: int,
    nx: int,
    top: wp.array(dtype=float),  # [1] in/out (zeroed before): the largest pooled_score (max: order-free)
):
    bk, bj, bi = wp.tid()
    wp.atomic_max(top, 0, pooled_score(pooled, f, bk, bj, bi, nz, ny, nx))


@wp.kernel
def pooled_quota(
    pooled: wp.array3d(dtype=float),  # pool_errors' block sums
    top: wp.array(dtype=float),  # [1] pooled_top's largest score
    cap: int,  # the largest quota (the sum of every brick's must fit an int)
    f: int,
    nz: int,
    ny: int,
    nx: int,
    quota: wp.array3d(dtype=int),  # [bz, by, bx] out: each brick's draws, its block's by voxels
):
    """error_quota with every brick scored by its block of f^3 (where bricks see too few samples for
    their own sums): a block's draws spread over its voxels alike."""
    bk, bj, bi = wp.tid()
    q = int(0)
    if top[0] > 0.0:
        q = int(float(cap) * (pooled_score(pooled, f, bk, bj, bi, nz, ny, nx) / top[0]))
    quota[bk, bj, bi] = q


@wp.func
def support_voxel(nz: int, ny: int, nx: int, cum: wp.array(dtype=wp.int64), r: wp.int64) -> wp.vec3i:
    """(k, j, i) of the r-th supported voxel (bricks in order, voxels in z, y, x order)."""
    br = find_brick(cum, r)
    return brick_rank_voxel(br[0], br[1], ny, nx)


@wp.func
def error_total(err_cum: wp.array(dtype=int), m_err: int) -> int:
    """The error stratum's quota over every brick; 0 when it draws nothing (off, or no error yet)."""
    if m_err <= 0:
        return 0
    return err_cum[err_cum.shape[0] - 1]


@wp.func
def error_probability(err_cum: wp.array(dtype=int), q_tot: int, k: int, j: int, i: int, nz: int, ny: int, nx: int) -> float:
    """Probability that one draw of the error stratum picks voxel (k, j, i): its brick's share of
    the quota over the brick's voxels."""
    nbx = (nx + BRICK - 1) / BRICK
    nby = (ny + BRICK - 1) / BRICK
    b = ((k / BRICK) * nby + j / BRICK) * nbx + i / BRICK
    qb = err_cum[b]
    if b > 0:
        qb -= err_cum[b - 1]
    return float(qb) / (float(q_tot) * float(brick_voxels(k / BRICK, j / BRICK, i / BRICK, nz, ny, nx)))


@wp.func
def error_voxel(err_cum: wp.array(dtype=int), r: int, d: int, nz: int, ny: int, nx: int) -> wp.vec3i:
    """(k, j, i) of the voxel the error stratum draws with quota rank r and in-brick draw d
    (0 <= d < 64, taken modulo the brick's voxels inside the grid). The quota's sum fits an int
    (``draw.Sampler``'s cap), and so does the brick index (fewer than 2^31 bricks)."""
    br = find_brick(err_cum, r)
    o = brick_origin(br[0], ny, nx)
    return brick_rank_voxel(br[0], d % brick_voxels(o[2] / BRICK, o[1] / BRICK, o[0] / BRICK, nz, ny, nx), ny, nx)


@wp.func
def stratum_voxel(
    bits: wp.array(dtype=wp.uint64),  # [B] the stratum's membership bits of each brick (brick_counts)
    cum: wp.array(dtype=wp.int64),  # [B] inclusive prefix sum of the stratum's brick counts
    ny: int,
    nx: int,
    r: wp.int64,  # 0 <= r < cum[B - 1]: rank of the wanted voxel in brick-then-scan order
) -> wp.vec3i:
    """(k, j, i) of the r-th voxel of a stratum (bricks in order, voxels in z, y, x order):
    the brick by its prefix sums, then the r-th set bit of its membership bits (no voxel read)."""
    br = find_brick(cum, r)
    t = br[1]
    b = bits[br[0]]
    o = brick_origin(br[0], ny, nx)
    for d in range(BRICK * BRICK * BRICK):
        if ((b >> wp.uint64(d)) & wp.uint64(1)) != wp.uint64(0):
            if t == 0:
                return brick_voxel(o[2] / BRICK, o[1] / BRICK, o[0] / BRICK, d)  # brick_counts' bit d
            t -= 1
    return wp.vec3i(0, 0, 0)  # unreachable when r is in range


@wp.func
def corners_usable(vol: wp.array3d(dtype=float), mask: wp.array3d(dtype=wp.uint8), has_mask: int, p: wp.vec3) -> float:
    """1 if every voxel the trilinear interpolation at p reads is unmasked, else 0."""
    if has_mask == 0:
        return 1.0
    x = wp.clamp(p[0], 0.0, float(vol.shape[2] - 1))
    y = wp.clamp(p[1], 0.0, float(vol.shape[1] - 1))
    z = wp.clamp(p[2], 0.0, float(vol.shape[0] - 1))
    i0 = int(wp.floor(x))
    j0 = int(wp.floor(y))
    k0 = int(wp.floor(z))
    for dk in range(2):
        for dj in range(2):
            for di in range(2):
                kk = wp.min(k0 + dk, vol.shape[0] - 1)
                jj = wp.min(j0 + dj, vol.shape[1] - 1)
                ii = wp.min(i0 + di, vol.shape[2] - 1)
                if mask[kk, jj, ii] == wp.uint8(0):
                    return 0.0
    return 1.0


UNIFORM_OCCUPIED = wp.constant(0)  # where the uniform stratum is drawn (uniform_domain)
UNIFORM_SUPPORT = wp.constant(1)
UNIFORM_GRID = wp.constant(2)


@wp.func
def uniform_domain(occ_total: wp.int64, use_support: int, support: wp.array(dtype=wp.int64)) -> int:
    """Where :func:`draw_samples` draws the uniform stratum: among the occupied voxels (when
    ``occ_total`` > 0), over the support bricks (when used and not empty), else the whole grid."""
    if occ_total > wp.int64(0):
        return UNIFORM_OCCUPIED
    if use_support != 0 and support[support.shape[0] - 1] > wp.int64(0):
        return UNIFORM_SUPPORT
    return UNIFORM_GRID


@wp.func
def sample_weight(
    vol: wp.array3d(dtype=float),
    st: int,  # the voxel's stratum (stratum_of)
    k: int,
    j: int,
    i: int,
    m: int,
    m_high: int,
    m_mid: int,
    n_high: wp.int64,
    n_mid: wp.int64,
    occ_total: wp.int64,
    use_support: int,
    support: wp.array(dtype=wp.int64),
    support_bricks: wp.array3d(dtype=wp.int64),
    support_everything: wp.array(dtype=int),
    m_err: int,
    err_cum: wp.array(dtype=int),
    q_tot: int,
) -> float:
    """1 / (D q(v)) for voxel v = (k, j, i): q(v) the probability that :func:`draw_samples` picks
    it, D about the number of voxels it can pick (the larger of the uniform domain and the two
    strata together), so that the mean weight is about 1. ``m_err`` samples follow the error
    (quota prefix sums ``err_cum``, total ``q_tot``); 0: none."""
    n_occ = float(n_high + n_mid)
    q = float(0.0)
    if st == 0:
        q += float(m_high) / (float(m) * float(n_high))
    elif st == 1:
        q += float(m_mid) / (float(m) * float(n_mid))
    if m_err > 0:
        nz = vol.shape[0]
        q += float(m_err) / float(m) * error_probability(err_cum, q_tot, k, j, i, nz, vol.shape[1], vol.shape[2])
    m_uni = float(m - m_high - m_mid - m_err)
    n_uni = float(grid_voxels(vol.shape[0], vol.shape[1], vol.shape[2]))
    in_uni = float(1.0)
    domain = uniform_domain(occ_total, use_support, support)
    if domain == UNIFORM_OCCUPIED:
        n_uni = float(occ_total)
        in_uni = wp.where(st >= 0, 1.0, 0.0)
    elif domain == UNIFORM_SUPPORT:
        n_uni = float(support[support.shape[0] - 1])
        if support_everything[0] == 0 and support_bricks[k / BRICK, j / BRICK, i / BRICK] == wp.int64(0):
            in_uni = 0.0
    q += in_uni * m_uni / (float(m) * n_uni)
    if q <= 0.0:
        return 1.0
    return 1.0 / (wp.max(n_uni, n_occ) * q)


@wp.kernel
def draw_samples(
    vol: wp.array3d(dtype=float),
    mask: wp.array3d(dtype=wp.uint8),
    has_mask: int,
    wide: int,  # 1: flat4 views vol as groups of four (row_pair; a volume in host memory)
    flat4: wp.array2d(dtype=wp.vec4),
    high: wp.array(dtype=wp.int64),  # [B] inclusive prefix sums of the high stratum's brick counts
    mid: wp.array(dtype=wp.int64),  # [B] the same for the mid stratum
    high_bits: wp.array(dtype=wp.uint64),  # [B] membership bits of the high stratum (brick_counts)
    mid_bits: wp.array(dtype=wp.uint64),  # [B] the same for the mid stratum
    n_high: wp.int64,  # voxels in the high stratum (>= 1)
    n_mid: wp.int64,
    m_high: int,  # samples drawn from the high stratum (the first m_high)
    m_mid: int,  # then this many from the mid stratum; the rest uniform over the grid
    occ_high: wp.int64,  # voxels in the high stratum (may be 0)
    occ_total: wp.int64,  # occupied voxels (high + mid); > 0: the uniform samples are drawn among them
    support: wp.array(dtype=wp.int64),  # [B] inclusive prefix sums of support_counts
    use_support: int,  # 1: the uniform samples are drawn over the support (when occ_total is 0)
    stream: wp.array(dtype=int),  # [1] RNG stream of this iteration
    partner_min: float,  # partner distance range in voxels
    partner_max: float,
    jitter: float,  # largest offset from the voxel centre along each axis, in voxels (0: the centre)
    importance: int,  # 1: weight each sample by 1 / (D q(v)) (see the module docstring)
    support_bricks: wp.array3d(dtype=wp.int64),  # [bz, by, bx] support_counts' output (use_support only)
    support_everything: wp.array(dtype=int),  # [1] mark_support's "everything" flag (use_support only)
    m_err: int,  # the last m_err samples follow the error (while its quota is not 0; else uniform)
    err_cum: wp.array(dtype=int),  # [B] inclusive prefix sums of error_quota's output (m_err > 0 only)
    threads: int,  # the launch size (the loop's stride)
    rank32_max: wp.int64,  # the largest count a rank is drawn from with one 32-bit draw (rank_below; 2^31 - 1)
    points: wp.array(dtype=wp.vec3),  # [2M] out: samples, then their partners
    target: wp.array(dtype=float),  # [M] out: trilinear V at the sample
    weight: wp.array(dtype=float),  # [M] out: the importance weight; 0 where the target reads a masked voxel
    occupied: wp.array(dtype=float),  # [M] out: 1 if target > 0.02
):
    """Training samples and their partners: thread t draws samples t, t + threads, ... (``threads``
    the launch size: one a sample where the volume is on the device, fewer where it is read over the
    bus, see ``draw.DRAW_THREADS_HOST``; each sample's random stream is its own, so the same samples
    either way)."""
    m = target.shape[0]
    nx = vol.shape[2]
    ny = vol.shape[1]
    domain = uniform_domain(occ_total, use_support, support)
    q_tot = error_total(err_cum, m_err)
    m_err_now = wp.where(q_tot > 0, m_err, 0)
    for s in range(wp.tid(), m, threads):
        state = wp.rand_init(stream[0], s)
        v = wp.vec3i(0, 0, 0)  # (k, j, i) of the drawn voxel
        if s >= m - m_err_now:  # the error stratum: a brick by its quota, then one of its voxels
            v = error_voxel(err_cum, wp.randi(state, 0, q_tot), wp.randi(state, 0, BRICK * BRICK * BRICK), vol.shape[0], ny, nx)
        elif s < m_high:
            v = stratum_voxel(high_bits, high, ny, nx, rank_below(wp.randu(state), n_high, rank32_max, stream[0], s))
        elif s < m_high + m_mid:
            v = stratum_voxel(mid_bits, mid, ny, nx, rank_below(wp.randu(state), n_mid, rank32_max, stream[0], s))
        elif domain == UNIFORM_OCCUPIED:  # among the occupied voxels (empty samples carry no gradient)
            rank = rank_below(wp.randu(state), occ_total, rank32_max, stream[0], s)
            if rank < occ_high:
                v = stratum_voxel(high_bits, high, ny, nx, rank)
            else:
                v = stratum_voxel(mid_bits, mid, ny, nx, rank - occ_high)
        elif domain == UNIFORM_SUPPORT:  # over the model's support
            v = support_voxel(
                vol.shape[0], ny, nx, support, rank_below(wp.randu(state), support[support.shape[0] - 1], rank32_max, stream[0], s)
            )
        else:
            v = grid_voxel(rank_below(wp.randu(state), grid_voxels(vol.shape[0], ny, nx), rank32_max, stream[0], s), ny, nx)
        k = v[0]
        j = v[1]
        i = v[2]
        # three draws whatever the jitter, so every setting consumes the same random numbers
        jx = (wp.randf(state) - 0.5) * (2.0 * jitter)
        jy = (wp.randf(state) - 0.5) * (2.0 * jitter)
        jz = (wp.randf(state) - 0.5) * (2.0 * jitter)
        p = wp.vec3(float(i) + jx, float(j) + jy, float(k) + jz)
        d = wp.vec3(wp.randn(state), wp.randn(state), wp.randn(state))
        dl = wp.length(d)
        if dl < 1.0e-6:
            d = wp.vec3(1.0, 0.0, 0.0)
            dl = 1.0
        r = partner_min + (partner_max - partner_min) * wp.randf(state)
        t = float(0.0)
        own = float(0.0)
        ok = float(1.0)
        if jitter > 0.0:
            tv = trilinear_rows(vol, flat4, wide, p, k, j, i)
            t = tv[0]
            own = tv[1]
            ok = corners_usable(vol, mask, has_mask, p)
        else:  # the voxel itself: no neighbour is read
            t = vol[k, j, i]
            own = t
        points[s] = p
        points[m + s] = p + d * (r / dl)
        target[s] = t
        if not usable(vol, mask, has_mask, k, j, i):
            ok = 0.0
        if importance != 0 and ok > 0.0:  # ok > 0: the voxel is usable
            ok = ok * sample_weight(
                vol,
                stratum_value(own),
                k,
                j,
                i,
                m,
                m_high,
                m_mid,
                n_high,
                n_mid,
                occ_total,
                use_support,
                support,
                support_bricks,
                support_everything,
                m_err_now,
                err_cum,
                q_tot,
            )
        weight[s] = ok
        occupied[s] = wp.where(t > OCCUPIED, 1.0, 0.0)
