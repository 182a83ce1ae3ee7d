"""Analysis and analytic allocation kernels (paper stages S1a-S1e, SPEC sections 3 and 5).

The volume lives on the device as normalised float32 values ``vol[z, y, x]`` with an optional
validity mask (0 = NaN/Inf/fill voxel, treated as empty space). Gradients are central differences,
one-sided next to the grid border or a masked voxel, zero with no valid neighbour on an axis.

Seeds are drawn without replacement by exponential race keys ``-log(u) / weight`` (Efraimidis and
Spirakis): the k smallest keys are a weighted sample of k distinct voxels. Keys are histogrammed
by log2 so that only the voxels in the lowest bins are compacted and sorted.
"""

from typing import Any

import warp as wp

wp.set_module_options({"enable_backward": False})

OCCUPIED = wp.constant(0.02)  # normalised value above which a voxel is occupied (SPEC section 2)
KEY_BINS = wp.constant(2048)  # histogram bins of log2(key)
KEY_BINS_PER_OCTAVE = wp.constant(16.0)
KEY_LOG2_MIN = wp.constant(-64.0)
TINY_WEIGHT = wp.constant(1.0e-30)  # weight of a gradient that is non-zero but underflows
ST_RADIUS = wp.constant(3)  # 7^3 structure-tensor window


@wp.func
def valid_at(mask: wp.array3d(dtype=wp.uint8), has_mask: int, k: int, j: int, i: int) -> bool:
    """Not masked (the caller has checked that (k, j, i) is inside the grid)."""
    if has_mask == 0:
        return True
    return mask[k, j, i] != wp.uint8(0)


@wp.func
def in_grid(vol: wp.array3d(dtype=float), k: int, j: int, i: int) -> bool:
    return k >= 0 and j >= 0 and i >= 0 and k < vol.shape[0] and j < vol.shape[1] and i < vol.shape[2]


@wp.func
def usable(vol: wp.array3d(dtype=float), mask: wp.array3d(dtype=wp.uint8), has_mask: int, k: int, j: int, i: int) -> bool:
    """Voxel inside the grid and not masked."""
    if not in_grid(vol, k, j, i):
        return False
    return valid_at(mask, has_mask, k, j, i)


@wp.func
def axis_gradient(
    vol: wp.array3d(dtype=float),
    mask: wp.array3d(dtype=wp.uint8),
    has_mask: int,
    k: int,
    j: int,
    i: int,
    dk: int,
    dj: int,
    di: int,
) -> wp.vec2:
    """(derivative along one axis, 1 if the differenced values differ else 0)."""
    fwd = usable(vol, mask, has_mask, k + dk, j + dj, i + di)
    bwd = usable(vol, mask, has_mask, k - dk, j - dj, i - di)
    if fwd and bwd:
        a = vol[k + dk, j + dj, i + di]
        b = vol[k - dk, j - dj, i - di]
        return wp.vec2(0.5 * (a - b), wp.where(a != b, 1.0, 0.0))
    if fwd:
        a = vol[k + dk, j + dj, i + di]
        b = vol[k, j, i]
        return wp.vec2(a - b, wp.where(a != b, 1.0, 0.0))
    if bwd:
        a = vol[k, j, i]
        b = vol[k - dk, j - dj, i - di]
        return wp.vec2(a - b, wp.where(a != b, 1.0, 0.0))
    return wp.vec2(0.0, 0.0)


@wp.func
def gradient_at(vol: wp.array3d(dtype=float), mask: wp.array3d(dtype=wp.uint8), has_mask: int, k: int, j: int, i: int) -> wp.vec4:
    """(gx, gy, gz, 1 if any axis difference is non-zero) at voxel (k, j, i)."""
    gx = axis_gradient(vol, mask, has_mask, k, j, i, 0, 0, 1)
    gy = axis_gradient(vol, mask, has_mask, k, j, i, 0, 1, 0)
    gz = axis_gradient(vol, mask, has_mask, k, j, i, 1, 0, 0)
    nz = wp.max(gx[1], wp.max(gy[1], gz[1]))
    return wp.vec4(gx[0], gy[0], gz[0], nz)


@wp.func
def seed_weight(vol: wp.array3d(dtype=float), mask: wp.array3d(dtype=wp.uint8), has_mask: int, k: int, j: int, i: int, mode: int) -> float:
    """Draw weight of a voxel: 0 if not eligible; 1 for coverage (mode 1); |grad V| for detail (mode 0)."""
    if not valid_at(mask, has_mask, k, j, i):
        return 0.0
    if vol[k, j, i] <= OCCUPIED:
        return 0.0
    if mode == 1:
        return 1.0
    g = gradient_at(vol, mask, has_mask, k, j, i)
    if g[3] == 0.0:
        return 0.0
    return wp.max(wp.length(wp.vec3(g[0], g[1], g[2])), TINY_WEIGHT)


@wp.func
def race_key(stream: int, idx: wp.int64, weight: float) -> float:
    """The exponential race key of linear voxel index ``idx``: its uniform from the stream at
    offset idx where idx < 2^32 (as when indices were int32), else at offset idx mod 2^32 of a
    stream mixed with idx's high word, so that voxels 2^32 apart do not share a key."""
    seed = stream
    hi = int(idx >> wp.int64(32))
    if hi != 0:
        seed = int(wp.rand_init(stream, hi))
    state = wp.rand_init(seed, int(idx & wp.int64(0xFFFFFFFF)))
    u = 1.0 - wp.randf(state)  # (0, 1]
    return -wp.log(u) / weight


@wp.func
def linear_index(k: int, j: int, i: int, ny: int, nx: int) -> wp.int64:
    """(k * ny + j) * nx + i in int64 (a volume in host memory may hold more than 2^31 voxels)."""
    return (wp.int64(k) * wp.int64(ny) + wp.int64(j)) * wp.int64(nx) + wp.int64(i)


@wp.func
def key_bin(key: float) -> int:
    if key <= 0.0:
        return 0
    b = int(wp.floor((wp.log2(key) - KEY_LOG2_MIN) * KEY_BINS_PER_OCTAVE))
    return wp.clamp(b, 0, KEY_BINS - 1)


@wp.kernel
def seed_key_histogram(
    vol: wp.array3d(dtype=float),  # [nz, ny, nx] normalised values
    mask: wp.array3d(dtype=wp.uint8),  # [nz, ny, nx] or [1, 1, 1] when has_mask == 0
    has_mask: int,
    mode: int,  # 0 detail (|grad V|-weighted), 1 coverage (uniform)
    stream: int,  # RNG stream of this draw
    hist: wp.array(dtype=wp.int64),  # [KEY_BINS] out, zeroed before
    eligible: wp.array(dtype=wp.int64),  # [1] out: number of eligible voxels, zeroed before
):
    """Histogram of log2 race keys over the eligible voxels (one thread per voxel)."""
    k, j, i = wp.tid()
    weight = seed_weight(vol, mask, has_mask, k, j, i, mode)
    if weight <= 0.0:
        return
    idx = linear_index(k, j, i, vol.shape[1], vol.shape[2])
    wp.atomic_add(hist, key_bin(race_key(stream, idx, weight)), wp.int64(1))
    wp.atomic_add(eligible, 0, wp.int64(1))


@wp.kernel
def seed_key_compact(
    vol: wp.array3d(dtype=float),
    mask: wp.array3d(dtype=wp.uint8),
    has_mask: int,
    mode: int,
    stream: int,
    max_bin: int,  # keep keys whose bin is <= max_bin
    counter: wp.array(dtype=int),  # [1] zeroed before
    keys: wp.array(dtype=float),  # [>= 2 * candidates] out
    idx_out: wp.array(dtype=wp.int64),  # [>= 2 * candidates] out: linear voxel index
):
    """Write the race keys of the lowest bins (the candidates of the draw) with their voxel index."""
    k, j, i = wp.tid()
    weight = seed_weight(vol, mask, has_mask, k, j, i, mode)
    if weight <= 0.0:
        return
    idx = linear_index(k, j, i, vol.shape[1], vol.shape[2])
    key = race_key(stream, idx, weight)
    if key_bin(key) <= max_bin:
        slot = wp.atomic_add(counter, 0, 1)
        keys[slot] = key
        idx_out[slot] = idx


@wp.func
def trilinear_axis(x: float, n: int):
    """Along one axis of n samples: the two samples around x (clamped to the grid) and the weight
    of the second."""
    c = wp.clamp(x, 0.0, float(n - 1))
    i0 = wp.min(int(wp.floor(c)), n - 1)
    return i0, wp.min(i0 + 1, n - 1), c - float(i0)


@wp.func
def trilinear_slab(vol: wp.array3d(dtype=Any), p: wp.vec3, kz0: int, nz: int):
    """:func:`trilinear` at p, in the coordinates of a volume of ``nz`` slices of which ``vol``
    holds the slices from ``kz0`` on (the clamp and weights are the whole volume's, so a slab that
    holds every slice read gives the same value bit for bit)."""
    i0, i1, tx = trilinear_axis(p[0], vol.shape[2])
    j0, j1, ty = trilinear_axis(p[1], vol.shape[1])
    k0, k1, tz = trilinear_axis(p[2], nz)
    k0 -= kz0
    k1 -= kz0
    c00 = wp.lerp(vol[k0, j0, i0], vol[k0, j0, i1], tx)
    c01 = wp.lerp(vol[k0, j1, i0], vol[k0, j1, i1], tx)
    c10 = wp.lerp(vol[k1, j0, i0], vol[k1, j0, i1], tx)
    c11 = wp.lerp(vol[k1, j1, i0], vol[k1, j1, i1], tx)
    return wp.lerp(wp.lerp(c00, c01, ty), wp.lerp(c10, c11, ty), tz)


@wp.func
def trilinear(vol: wp.array3d(dtype=Any), p: wp.vec3):
    """Trilinear interpolation at p = (x, y, z) voxel units, clamped to the grid (a scalar volume,
    or a grid of vectors such as the motion's block displacements)."""
    return trilinear_slab(vol, p, 0, vol.shape[0])


@wp.func
def sort3(d: wp.vec3) -> wp.vec3i:
    """Indices of d in ascending order."""
    a = int(0)
    b = int(1)
    c = int(2)
    if d[a] > d[b]:
        t = a
        a = b
        b = t
    if d[b] > d[c]:
        t = b
        b = c
        c = t
    if d[a] > d[b]:
        t = a
        a = b
        b = t
    return wp.vec3i(a, b, c)


SEED_FRAME_REACH = wp.constant(ST_RADIUS + 2)  # slices a seed's frame reads beyond its own (window, gradient, trilinear)


@wp.func
def seed_frame(
    vol: wp.array3d(dtype=float),  # the volume, or a slab of it from slice kz0 on
    mask: wp.array3d(dtype=wp.uint8),  # the same slices of the mask (has_mask only)
    has_mask: int,
    kz0: int,
    nz: int,  # slices of the whole volume
    s: int,  # the seed's index (its jitter's random stream)
    idx: wp.int64,  # its linear voxel index in the whole volume
    stream: int,
    mu: wp.array(dtype=wp.vec3),
    quat: wp.array(dtype=wp.quat),
    shape_info: wp.array(dtype=wp.vec3),
):
    """S1c + S1e at one seed: 7^3 structure tensor, tangent frame, gradient, value.

    The principal (first) axis is the eigenvector of the smallest eigenvalue of the structure tensor
    (the local tangent); the third axis is the dominant gradient direction (the normal). Planarity
    (l_max - l_mid) / l_max is 1 on a plane (both tangents free) and 0 on a tube. A slab must hold
    every slice within :data:`SEED_FRAME_REACH` of the seed's (or reach the volume's end there).
    """
    nx = wp.int64(vol.shape[2])
    ny = wp.int64(vol.shape[1])
    i = int(idx % nx)
    j = int((idx / nx) % ny)
    k = int(idx / (nx * ny))
    kl = k - kz0
    T = wp.mat33(0.0)
    for dz in range(-ST_RADIUS, ST_RADIUS + 1):
        for dy in range(-ST_RADIUS, ST_RADIUS + 1):
            for dx in range(-ST_RADIUS, ST_RADIUS + 1):
                if usable(vol, mask, has_mask, kl + dz, j + dy, i + dx):
                    g4 = gradient_at(vol, mask, has_mask, kl + dz, j + dy, i + dx)
                    g = wp.vec3(g4[0], g4[1], g4[2])
                    T += wp.outer(g, g)
    Q, d = wp.eig3(T)
    order = sort3(d)
    e_t = wp.normalize(wp.vec3(Q[0, order[0]], Q[1, order[0]], Q[2, order[0]]))
    e_m = wp.normalize(wp.vec3(Q[0, order[1]], Q[1, order[1]], Q[2, order[1]]))
    e_n = wp.cross(e_t, e_m)  # right-handed frame
    R = wp.matrix_from_cols(e_t, e_m, e_n)
    lmax = d[order[2]]
    planarity = float(0.0)
    if lmax > 0.0:
        planarity = wp.clamp((lmax - d[order[1]]) / lmax, 0.0, 1.0)
    state = wp.rand_init(stream, s)
    jit = wp.vec3(wp.randf(state) - 0.5, wp.randf(state) - 0.5, wp.randf(state) - 0.5)
    p = wp.vec3(float(i), float(j), float(k)) + jit
    g0 = gradient_at(vol, mask, has_mask, kl, j, i)
    mu[s] = p
    quat[s] = wp.quat_from_matrix(R)
    shape_info[s] = wp.vec3(wp.length(wp.vec3(g0[0], g0[1], g0[2])), planarity, trilinear_slab(vol, p, kz0, nz))


@wp.kernel
def seed_frames(
    vol: wp.array3d(dtype=float),
    mask: wp.array3d(dtype=wp.uint8),
    has_mask: int,
    voxel: wp.array(dtype=wp.int64),  # [S] linear voxel index of each seed
    stream: int,  # RNG stream for the half-voxel jitter
    mu: wp.array(dtype=wp.vec3),  # [S] out: jittered centre
    quat: wp.array(dtype=wp.quat),  # [S] out: local axes (tangent, middle, normal) as a rotation
    shape_info: wp.array(dtype=wp.vec3),  # [S] out: (|grad V| at the seed, planarity, value at mu)
):
    """S1c + S1e at each seed (:func:`seed_frame`; one thread per seed)."""
    s = wp.tid()
    seed_frame(vol, mask, has_mask, 0, vol.shape[0], s, voxel[s], stream, mu, quat, shape_info)


@wp.kernel
def seed_frames_slab(
    vol: wp.array3d(dtype=float),  # slices kz0.. of the volume (see seed_frame)
    mask: wp.array3d(dtype=wp.uint8),
    has_mask: int,
    kz0: int,
    nz: int,
    voxel: wp.array(dtype=wp.int64),  # [S] linear voxel index of each seed
    which: wp.array(dtype=int),  # [T] the seeds whose voxels lie in this slab's own slices
    stream: int,
    mu: wp.array(dtype=wp.vec3),  # [S] out, as seed_frames'
    quat: wp.array(dtype=wp.quat),
    shape_info: wp.array(dtype=wp.vec3),
):
    """:func:`seed_frames` for the seeds of one slab (a volume in host memory, a slab at a time on
    the device): the same outputs bit for bit."""
    s = which[wp.tid()]
    seed_frame(vol, mask, has_mask, kz0, nz, s, voxel[s], stream, mu, quat, shape_info)


@wp.kernel
def nearest_neighbour_distance(
    probe: wp.array(dtype=wp.vec3),  # [S] subsample of the group (the first S points of pts)
    pts: wp.array(dtype=wp.vec3),  # [n] the whole group
    out: wp.array(dtype=float),  # [S] out: distance to the nearest other point of the group
):
    """Brute-force nearest-neighbour distance of a probe subsample (one thread per probe)."""
    s = wp.tid()
    p = probe[s]
    best = float(1.0e30)
    for j in range(pts.shape[0]):
        if j != s:
            best = wp.min(best, wp.length_sq(pts[j] - p))
    out[s] = wp.sqrt(best)


@wp.kernel
def assemble_primitives(
    mu: wp.array(dtype=wp.vec3),  # [S]
    quat: wp.array(dtype=wp.quat),  # [S]
    shape_info: wp.array(dtype=wp.vec3),  # [S] (|grad|, planarity, value)
    sigma: float,  # group base scale in voxels
    grad_ref: float,  # |grad V| at which elongation saturates
    max_aniso: float,  # longest / shortest axis bound (3)
    scale_min: float,
    scale_cap: float,
    weight: float,  # initial weight
    first: int,  # row offset of this group in params
    params: wp.array2d(dtype=float),  # [N, 12] out
):
    """S1d + S1e: scales from the group spacing, elongated along the tangent with |grad V|."""
    s = wp.tid()
    info = shape_info[s]
    e = 1.0
    if grad_ref > 0.0:
        e = 1.0 + (max_aniso - 1.0) * wp.min(info[0] / grad_ref, 1.0)
    st = wp.clamp(sigma * e, scale_min, scale_cap)
    sm = wp.clamp(sigma * (1.0 + (e - 1.0) * info[1]), scale_min, scale_cap)
    sn = wp.clamp(sigma, scale_min, scale_cap)
    # the bound holds after clamping too: clamping only brings scales closer together
    st = wp.min(st, max_aniso * sn)
    sm = wp.min(sm, max_aniso * sn)
    r = first + s
    p = mu[s]
    q = quat[s]
    params[r, 0] = p[0]
    params[r, 1] = p[1]
    params[r, 2] = p[2]
    params[r, 3] = wp.log(st)
    params[r, 4] = wp.log(sm)
    params[r, 5] = wp.log(sn)
    params[r, 6] = q[0]
    params[r, 7] = q[1]
    params[r, 8] = q[2]
    params[r, 9] = q[3]
    params[r, 10] = info[2]
    params[r, 11] = weight


@wp.kernel
def structure_samples(
    vol: wp.array3d(dtype=float),
    mask: wp.array3d(dtype=wp.uint8),
    has_mask: int,
    voxel: wp.array(dtype=wp.int64),  # [S] linear voxel indices to analyse
    lag: int,  # the long lag of the structure function (16)
    out: wp.array2d(dtype=float),  # [S, 6] out: occupied, |grad|, S(1) sum, S(1) pairs, S(lag) sum, S(lag) pairs
):
    """Per-voxel terms of the structure statistics (SPEC section 5), for occupied voxels."""
    s = wp.tid()
    idx = voxel[s]
    nx = wp.int64(vol.shape[2])
    ny = wp.int64(vol.shape[1])
    i = int(idx % nx)
    j = int((idx / nx) % ny)
    k = int(idx / (nx * ny))
    for c in range(6):
        out[s, c] = 0.0
    if not valid_at(mask, has_mask, k, j, i):
        return
    v = vol[k, j, i]
    if v <= OCCUPIED:
        return
    g = gradient_at(vol, mask, has_mask, k, j, i)
    out[s, 0] = 1.0
    out[s, 1] = wp.length(wp.vec3(g[0], g[1], g[2]))
    for axis in range(3):
        for which in range(2):
            l = 1
            if which == 1:
                l = lag
            kk = k
            jj = j
            ii = i
            if axis == 0:
                ii = i + l
            elif axis == 1:
                jj = j + l
            else:
                kk = k + l
            if usable(vol, mask, has_mask, kk, jj, ii):
                out[s, 2 + 2 * which] += wp.abs(vol[kk, jj, ii] - v)
                out[s, 3 + 2 * which] += 1.0


@wp.kernel
def region_mask(
    valid: wp.array3d(dtype=wp.uint8),  # [nz, ny, nx] or [1, 1, 1] when has_valid == 0
    has_valid: int,
    regions: wp.array2d(dtype=int),  # [r, 6] boxes (z0, z1, y0, y1, x0, x1), half-open
    exclude: wp.array(dtype=int),  # [6] a box left out (z0 >= z1: none)
    out: wp.array3d(dtype=wp.uint8),  # [nz, ny, nx]
):
    """1 where a voxel is valid, inside one of ``regions`` and outside ``exclude`` (a brick's
    interior, or the part of its halo where its pending neighbours lie)."""
    k, j, i = wp.tid()
    inside = bool(False)
    for r in range(regions.shape[0]):
        if k >= regions[r, 0] and k < regions[r, 1] and j >= regions[r, 2] and j < regions[r, 3]:
            if i >= regions[r, 4] and i < regions[r, 5]:
                inside = True
    if inside and exclude[0] < exclude[1]:
        if k >= exclude[0] and k < exclude[1] and j >= exclude[2] and j < exclude[3] and i >= exclude[4] and i < exclude[5]:
            inside = False
    if inside and not valid_at(valid, has_valid, k, j, i):
        inside = False
    out[k, j, i] = wp.where(inside, wp.uint8(1), wp.uint8(0))


@wp.func
def box_difference(vol: wp.array3d(dtype=float), k: int, j: int, i: int, dk: int, dj: int, di: int, at: int, n: int) -> float:
    """numpy.gradient along one axis at index ``at`` of ``n``: central differences, one-sided at
    the box's faces, 0 on an axis of one voxel (no mask)."""
    if n < 2:
        return 0.0
    if at == 0:
        return vol[k + dk, j + dj, i + di] - vol[k, j, i]
    if at == n - 1:
        return vol[k, j, i] - vol[k - dk, j - dj, i - di]
    return (vol[k + dk, j + dj, i + di] - vol[k - dk, j - dj, i - di]) * 0.5


@wp.kernel
def row_box_counts(
    vol: wp.array3d(dtype=float),
    mask: wp.array3d(dtype=wp.uint8),
    has_mask: int,
    row_valid: wp.array2d(dtype=int),
    row_occupied: wp.array2d(dtype=int),
    row_eligible: wp.array2d(dtype=int),
    row_grad: wp.array2d(dtype=wp.float64),
):
    """Per (z, y) row of a box: its valid voxels, the occupied ones, those with a non-zero gradient
    (``analysis.count_seed_candidates``) and the float64 sum of |grad V| over the occupied ones
    (``brickplan.grad_sum``: float32 differences that ignore the mask, one-sided at the box's faces)."""
    k, j = wp.tid()
    nz = vol.shape[0]
    ny = vol.shape[1]
    nx = vol.shape[2]
    n_ok = int(0)
    occ = int(0)
    elig = int(0)
    total = wp.float64(0.0)
    for i in range(nx):
        if valid_at(mask, has_mask, k, j, i):
            n_ok += 1
            if vol[k, j, i] > OCCUPIED:
                occ += 1
                if gradient_at(vol, mask, has_mask, k, j, i)[3] != 0.0:
                    elig += 1
                dz = box_difference(vol, k, j, i, 1, 0, 0, k, nz)
                dy = box_difference(vol, k, j, i, 0, 1, 0, j, ny)
                dx = box_difference(vol, k, j, i, 0, 0, 1, i, nx)
                g = dz * dz
                g = g + dy * dy
                g = g + dx * dx
                total += wp.float64(wp.sqrt(g))
    row_valid[k, j] = n_ok
    row_occupied[k, j] = occ
    row_eligible[k, j] = elig
    row_grad[k, j] = total


@wp.kernel
def loss_partials(
    point_loss: wp.array(dtype=wp.vec3),  # [M] (value, density, smooth) loss terms of each sample
    value: wp.array(dtype=float),  # [>= M] V~ at the samples
    target: wp.array(dtype=float),  # [M]
    weight: wp.array(dtype=float),  # [M] importance weight om (0: excluded)
    reg_loss: wp.array(dtype=wp.vec3),  # [N] (anchor, aniso, cap) loss terms of each primitive
    per: int,  # samples (and primitives) a thread sums
    sample_slices: int,  # the first this many threads sum samples, the others primitives
    out: wp.array2d(dtype=wp.float64),  # [slices, 6] out: partial sums of one slice
):
    """Float64 partial sums of one slice of the samples, in order: the three loss terms,
    om (v - t)^2, om, om (clamp(v, 0, 1) - t)^2; or of one slice of the primitives: their three
    regulariser terms (one thread per slice; the slices are summed on the host in order, so a loss
    record is the same on every rerun)."""
    s = wp.tid()
    a0 = wp.float64(0.0)
    a1 = wp.float64(0.0)
    a2 = wp.float64(0.0)
    a3 = wp.float64(0.0)
    a4 = wp.float64(0.0)
    a5 = wp.float64(0.0)
    if s < sample_slices:
        for i in range(s * per, wp.min(target.shape[0], (s + 1) * per)):
            pl = point_loss[i]
            om = wp.float64(weight[i])
            t = wp.float64(target[i])
            v = value[i]
            e = wp.float64(v) - t
            c = wp.float64(wp.clamp(v, 0.0, 1.0)) - t
            a0 += wp.float64(pl[0])
            a1 += wp.float64(pl[1])
            a2 += wp.float64(pl[2])
            a3 += om * e * e
            a4 += om
            a5 += om * c * c
    else:
        r = s - sample_slices
        for i in range(r * per, wp.min(reg_loss.shape[0], (r + 1) * per)):
            rl = reg_loss[i]
            a0 += wp.float64(rl[0])
            a1 += wp.float64(rl[1])
            a2 += wp.float64(rl[2])
    out[s, 0] = a0
    out[s, 1] = a1
    out[s, 2] = a2
    out[s, 3] = a3
    out[s, 4] = a4
    out[s, 5] = a5
