"""Forward evaluation of the Gaussian mixture field (SPEC section 2, paper Eq. 1).

    V~(p) = sum_i w_i a_i G_i(p) / max(sum_i w_i G_i(p), RHO0),   G_i(p) = exp(-m/2) if m < 25 else 0,
    m = d^T Sigma_i^-1 d,  d = p - mu_i,  Sigma_i = R(q_i) diag(exp(2 s_i)) R(q_i)^T.

Evaluation is truncation-aware: primitives are prepared once (rotation, inverse squared scales, per-axis
half-extents of the 5-sigma ellipsoid), binned by truncation radius into levels of cubic cells
whose size is at least the radius of every member, sorted by cell, and each query point visits
the 3^3 neighbouring cells of every level with a per-axis bounding test before the exact
Mahalanobis cut. A dense all-pairs kernel with the identical cut serves as the reference.

Parameter layout of one primitive (``vec12``): mu_x, mu_y, mu_z, log_sx, log_sy, log_sz,
q_x, q_y, q_z, q_w (Warp order), a, w.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})

vec12 = wp.types.vector(length=12, dtype=wp.float32)
# Sigma^-1 of one primitive, symmetric: (xx, yy, zz, xy, xz, yz)
vec6 = wp.types.vector(length=6, dtype=wp.float32)

TRUNC_M2 = wp.constant(25.0)  # squared Mahalanobis distance of the 5-sigma cut
TRUNC_SIGMA = wp.constant(5.0)
RHO0 = wp.constant(0.05)  # density floor of the normalisation
LOG_SCALE_MIN = wp.constant(-9.0)  # exp(-9) = 1.2e-4 voxel: keeps 1/s^2 finite in float32
LOG_SCALE_MAX = wp.constant(12.0)  # exp(12) = 1.6e5 voxels: keeps s^2 finite in float32
# |a| and |w| as evaluation reads them: w a G <= 1e30, so sums over up to 3e8 primitives stay finite
# (models hold a near [0, 1] and w in (0, 1]; only a crafted file reaches the bound)
VALUE_BOUND = wp.constant(1.0e15)


@wp.func
def safe_unit_quat(qx: float, qy: float, qz: float, qw: float) -> wp.quat:
    """Normalise a quaternion, falling back to the identity when it is (nearly) zero or not finite.

    Beyond |q| ~ 1.8e19 the squared norm overflows float32 (1/sqrt(inf) = 0 would return a zero
    quaternion): such a q is scaled by its largest component first.
    """
    n2 = qx * qx + qy * qy + qz * qz + qw * qw
    if n2 < 1.0e-20:
        return wp.quat_identity()
    if not wp.isfinite(n2):
        if not (wp.isfinite(qx) and wp.isfinite(qy) and wp.isfinite(qz) and wp.isfinite(qw)):
            return wp.quat_identity()
        big = wp.max(wp.max(wp.abs(qx), wp.abs(qy)), wp.max(wp.abs(qz), wp.abs(qw)))
        qx = qx / big
        qy = qy / big
        qz = qz / big
        qw = qw / big
        n2 = qx * qx + qy * qy + qz * qz + qw * qw
    inv = 1.0 / wp.sqrt(n2)
    return wp.quat(qx * inv, qy * inv, qz * inv, qw * inv)


@wp.func
def primitive_frame(p: vec12):
    """Rotation matrix and clamped axis scales of a primitive.

    Returns:
        (R, s): columns of R are the primitive's local axes in grid coordinates, s the sigmas.
    """
    R = wp.quat_to_matrix(safe_unit_quat(p[6], p[7], p[8], p[9]))
    s = wp.vec3(
        wp.exp(wp.clamp(p[3], LOG_SCALE_MIN, LOG_SCALE_MAX)),
        wp.exp(wp.clamp(p[4], LOG_SCALE_MIN, LOG_SCALE_MAX)),
        wp.exp(wp.clamp(p[5], LOG_SCALE_MIN, LOG_SCALE_MAX)),
    )
    return R, s


@wp.func
def mahalanobis(d: wp.vec3, rot: wp.mat33, inv_s2: wp.vec3) -> float:
    """m = d^T Sigma^-1 d with Sigma = R diag(s^2) R^T, computed in the primitive's frame."""
    y = wp.transpose(rot) @ d
    return y[0] * y[0] * inv_s2[0] + y[1] * y[1] * inv_s2[1] + y[2] * y[2] * inv_s2[2]


@wp.func
def conic_of(rot: wp.mat33, inv_s2: wp.vec3) -> vec6:
    """Sigma^-1 = R diag(1 / s^2) R^T as its six entries (xx, yy, zz, xy, xz, yz)."""
    A = rot @ wp.diag(inv_s2) @ wp.transpose(rot)
    return vec6(A[0, 0], A[1, 1], A[2, 2], 0.5 * (A[0, 1] + A[1, 0]), 0.5 * (A[0, 2] + A[2, 0]), 0.5 * (A[1, 2] + A[2, 1]))


@wp.func
def conic_m(d: wp.vec3, c: vec6) -> float:
    """m = d^T Sigma^-1 d from the six entries of Sigma^-1 (:func:`conic_of`)."""
    return (
        c[0] * d[0] * d[0] + c[1] * d[1] * d[1] + c[2] * d[2] * d[2] + 2.0 * (c[3] * d[0] * d[1] + c[4] * d[0] * d[2] + c[5] * d[1] * d[2])
    )


@wp.func
def in_box(d: wp.vec3, ext: wp.vec3) -> bool:
    """d inside the 5-sigma bounding box (per-axis half-extents ``ext``)."""
    return wp.abs(d[0]) <= ext[0] and wp.abs(d[1]) <= ext[1] and wp.abs(d[2]) <= ext[2]


@wp.func
def conic_g(d: wp.vec3, c: vec6) -> float:
    """G = exp(-m / 2) with the 5-sigma cut, for a d already inside the bounding box: what every
    pair pass of refinement and evaluation computes, so that they agree on every pair."""
    m = conic_m(d, c)
    if m >= TRUNC_M2:
        return 0.0
    return wp.exp(-0.5 * m)


@wp.func
def conic_kernel(d: wp.vec3, ext: wp.vec3, c: vec6) -> float:
    """G at offset d from the centre: 0 outside the 5-sigma box (:func:`in_box`), else
    :func:`conic_g` (for a caller that holds Sigma^-1 already; :func:`add_pair` reads it only
    inside the box)."""
    if not in_box(d, ext):
        return 0.0
    return conic_g(d, c)


@wp.func
def truncated_kernel(p: wp.vec3, mu: wp.vec3, rot: wp.mat33, inv_s2: wp.vec3, ext: wp.vec3) -> float:
    """G(p) with the 5-sigma cut; 0 outside the bounding box or the ellipsoid, in the primitive's
    frame (decoding and rendering). The pair passes of refinement and evaluation read Sigma^-1
    instead (:func:`in_box`, :func:`conic_g`: fewer loads and products a pair), all the same way,
    so they agree exactly on which pairs contribute; the two forms differ by float rounding."""
    d = p - mu
    if wp.abs(d[0]) > ext[0] or wp.abs(d[1]) > ext[1] or wp.abs(d[2]) > ext[2]:
        return 0.0
    m = mahalanobis(d, rot, inv_s2)
    if m >= TRUNC_M2:
        return 0.0
    return wp.exp(-0.5 * m)


@wp.func
def sigmoid(x: float) -> float:
    return 1.0 / (1.0 + wp.exp(-x))


@wp.func
def prepare_one(p: vec12, raw: int):
    """(R, 1 / sigma^2, 5-sigma half-extents, weight) of one primitive, as evaluation reads them."""
    R, s = primitive_frame(p)
    s2 = wp.vec3(s[0] * s[0], s[1] * s[1], s[2] * s[2])
    S = R @ wp.diag(s2) @ wp.transpose(R)
    e = wp.vec3(
        TRUNC_SIGMA * wp.sqrt(wp.max(S[0, 0], 0.0)),
        TRUNC_SIGMA * wp.sqrt(wp.max(S[1, 1], 0.0)),
        TRUNC_SIGMA * wp.sqrt(wp.max(S[2, 2], 0.0)),
    )
    wt = p[11]
    if raw != 0:
        wt = sigmoid(p[11])
    return R, wp.vec3(1.0 / s2[0], 1.0 / s2[1], 1.0 / s2[2]), e, wt


@wp.kernel
def prepare_primitives(
    params: wp.array(dtype=vec12),  # [N]
    raw: int,  # 1: params are training parameters (weight logit in slot 11), 0: model parameters
    mu: wp.array(dtype=wp.vec3),  # [N] out: centres
    rot: wp.array(dtype=wp.mat33),  # [N] out: R (columns = local axes)
    inv_s2: wp.array(dtype=wp.vec3),  # [N] out: 1 / sigma^2 per local axis
    ext: wp.array(dtype=wp.vec3),  # [N] out: per-axis half-extent of the 5-sigma ellipsoid
    radius: wp.array(dtype=float),  # [N] out: max(ext), the binning radius
    a: wp.array(dtype=float),  # [N] out: value
    w: wp.array(dtype=float),  # [N] out: weight
    conic: wp.array(dtype=vec6),  # [N] out: Sigma^-1 (conic_of)
):
    """Turn parameters into what evaluation reads (one thread per primitive)."""
    i = wp.tid()
    R, inv, e, wt = prepare_one(params[i], raw)
    p = params[i]
    mu[i] = wp.vec3(p[0], p[1], p[2])
    rot[i] = R
    inv_s2[i] = inv
    conic[i] = conic_of(R, inv)
    ext[i] = e
    radius[i] = wp.max(e[0], wp.max(e[1], e[2]))
    a[i] = wp.clamp(p[10], -VALUE_BOUND, VALUE_BOUND)
    w[i] = wp.clamp(wt, -VALUE_BOUND, VALUE_BOUND)


@wp.func
def level_cell(x: wp.vec3, cell: float, dims: wp.vec3i) -> wp.vec3i:
    """Clamped cell coordinates of x on a level grid whose cells start at -0.5 (voxel edge)."""
    inv = 1.0 / cell
    return wp.vec3i(
        wp.clamp(int(wp.floor((x[0] + 0.5) * inv)), 0, dims[0] - 1),
        wp.clamp(int(wp.floor((x[1] + 0.5) * inv)), 0, dims[1] - 1),
        wp.clamp(int(wp.floor((x[2] + 0.5) * inv)), 0, dims[2] - 1),
    )


@wp.func
def bin_level(r: float, level_size: wp.array(dtype=float)) -> int:
    """The first level whose cells are at least r (the last, global level catches the rest)."""
    nlev = level_size.shape[0]
    lev = nlev - 1
    for l in range(nlev):
        if level_size[l] >= r and lev == nlev - 1:
            lev = l
    return lev


@wp.func
def cell_key(
    x: wp.vec3,
    l: int,
    level_size: wp.array(dtype=float),
    level_dims: wp.array(dtype=wp.vec3i),
    level_offset: wp.array(dtype=int),
) -> int:
    """Global id of the level-l cell holding x (the key primitives and points are sorted by)."""
    dims = level_dims[l]
    c = level_cell(x, level_size[l], dims)
    return level_offset[l] + (c[2] * dims[1] + c[1]) * dims[0] + c[0]


RADIUS_CLASSES = wp.constant(160)  # power-of-two classes above the least radius (>= 1): all of float32


@wp.kernel
def radius_min(radius: wp.array(dtype=float), rmin: wp.array(dtype=float)):
    """rmin[0] = least finite radius (rmin[0] set to +inf before; min is order-independent)."""
    r = radius[wp.tid()]
    if wp.isfinite(r):
        wp.atomic_min(rmin, 0, r)


@wp.kernel
def radius_class_flags(
    radius: wp.array(dtype=float),
    rmin: wp.array(dtype=float),  # [1] from radius_min
    min_cell: float,
    flags: wp.array(dtype=int),  # [RADIUS_CLASSES] out (zeroed before): 1 where a class is occupied
):
    """Flag the power-of-two class of each finite radius as :func:`warpgauss.field.gaussians.plan_bins`
    computes it in float64: base = 2^floor(log2(max(rmin, min_cell))), class =
    ceil(log2(max(r, base) / base) - 1e-9)."""
    r = radius[wp.tid()]
    if not wp.isfinite(r):
        return
    base = wp.pow(wp.float64(2.0), wp.floor(wp.log2(wp.max(wp.float64(rmin[0]), wp.float64(min_cell)))))
    c = wp.ceil(wp.log2(wp.max(wp.float64(r), base) / base) - wp.float64(1.0e-9))
    flags[wp.clamp(int(c), 0, RADIUS_CLASSES - 1)] = 1


@wp.kernel
def bin_keys(
    mu: wp.array(dtype=wp.vec3),  # [N]
    radius: wp.array(dtype=float),  # [N]
    level_size: wp.array(dtype=float),  # [L] cell size per level, ascending; the last level is global
    level_dims: wp.array(dtype=wp.vec3i),  # [L]
    level_offset: wp.array(dtype=int),  # [L] first cell id of each level
    keys: wp.array(dtype=int),  # [2N] out: cell id (first N entries)
    values: wp.array(dtype=int),  # [2N] out: primitive index (first N entries)
):
    """Assign each primitive to the first level whose cells are at least its radius."""
    i = wp.tid()
    keys[i] = cell_key(mu[i], bin_level(radius[i], level_size), level_size, level_dims, level_offset)
    values[i] = i


@wp.kernel
def cell_ranges(
    sorted_keys: wp.array(dtype=int),  # [>=N]
    n: int,
    cell_start: wp.array(dtype=int),  # [C] out (zeroed before)
    cell_end: wp.array(dtype=int),  # [C] out (zeroed before)
):
    """Record [start, end) of each occupied cell in the cell-sorted primitive order."""
    i = wp.tid()
    k = sorted_keys[i]
    if i == 0:
        cell_start[k] = i
    elif sorted_keys[i - 1] != k:
        cell_start[k] = i
    if i == n - 1:
        cell_end[k] = i + 1
    elif sorted_keys[i + 1] != k:
        cell_end[k] = i + 1


@wp.kernel
def gather_sorted(
    order: wp.array(dtype=int),  # [>=N] primitive index at each sorted slot
    mu: wp.array(dtype=wp.vec3),
    rot: wp.array(dtype=wp.mat33),
    inv_s2: wp.array(dtype=wp.vec3),
    ext: wp.array(dtype=wp.vec3),
    a: wp.array(dtype=float),
    w: wp.array(dtype=float),
    conic: wp.array(dtype=vec6),
    mu_s: wp.array(dtype=wp.vec3),  # [N] out, cell order
    rot_s: wp.array(dtype=wp.mat33),
    inv_s2_s: wp.array(dtype=wp.vec3),
    ext_s: wp.array(dtype=wp.vec3),
    a_s: wp.array(dtype=float),
    w_s: wp.array(dtype=float),
    conic_s: wp.array(dtype=vec6),
):
    """Copy prepared primitives into cell order so that a cell's members are contiguous."""
    i = wp.tid()
    j = order[i]
    mu_s[i] = mu[j]
    rot_s[i] = rot[j]
    inv_s2_s[i] = inv_s2[j]
    ext_s[i] = ext[j]
    a_s[i] = a[j]
    w_s[i] = w[j]
    conic_s[i] = conic[j]


@wp.struct
class BinnedPrimitives:
    """Prepared primitives in cell order with their cell-level index (see ``GaussianField``)."""

    level_size: wp.array(dtype=float)  # [L] cell edge per level, ascending; the last level is global
    level_dims: wp.array(dtype=wp.vec3i)  # [L] cells per axis
    level_offset: wp.array(dtype=int)  # [L] first cell id of each level
    cell_start: wp.array(dtype=int)  # [C] first sorted primitive of each cell
    cell_end: wp.array(dtype=int)  # [C] one past the last
    order: wp.array(dtype=int)  # [N] primitive index of each sorted slot
    mu: wp.array(dtype=wp.vec3)  # [N] centres, cell order
    rot: wp.array(dtype=wp.mat33)  # [N] R
    inv_s2: wp.array(dtype=wp.vec3)  # [N] 1 / sigma^2
    ext: wp.array(dtype=wp.vec3)  # [N] 5-sigma half-extents
    a: wp.array(dtype=float)  # [N] value
    w: wp.array(dtype=float)  # [N] weight
    conic: wp.array(dtype=vec6)  # [N] Sigma^-1 (conic_of): what the pair passes evaluate


@wp.func
def neighbour_cell(dims: wp.vec3i, c: wp.vec3i, nb: int) -> int:
    """Id within its level of neighbour nb (0..26) of cell c on a level of ``dims`` cells; -1 outside."""
    x = c[0] + nb % 3 - 1
    y = c[1] + (nb / 3) % 3 - 1
    z = c[2] + nb / 9 - 1
    if x < 0 or y < 0 or z < 0 or x >= dims[0] or y >= dims[1] or z >= dims[2]:
        return -1
    return (z * dims[1] + y) * dims[0] + x


@wp.func
def neighbour_range(prims: BinnedPrimitives, l: int, c: wp.vec3i, nb: int) -> wp.vec2i:
    """[start, end) of sorted primitives in neighbour nb (0..26) of cell c on level l; empty outside."""
    local = neighbour_cell(prims.level_dims[l], c, nb)
    if local < 0:
        return wp.vec2i(0, 0)
    cid = prims.level_offset[l] + local
    return wp.vec2i(prims.cell_start[cid], prims.cell_end[cid])


@wp.func
def add_pair(p: wp.vec3, b: BinnedPrimitives, j: int, s: wp.vec3) -> wp.vec3:
    """``s`` (numerator, density, contributing pairs) with the pair of point p and sorted slot j
    added where it contributes: (w a G, w G, 1). The centre and box are read first, Sigma^-1 and
    the values only for a point inside the box."""
    d = p - b.mu[j]
    if not in_box(d, b.ext[j]):
        return s
    g = conic_g(d, b.conic[j])
    if g > 0.0:
        w = b.w[j]
        return wp.vec3(s[0] + w * b.a[j] * g, s[1] + w * g, s[2] + 1.0)
    return s


@wp.func
def binned_sums(p: wp.vec3, b: BinnedPrimitives) -> wp.vec3:
    """(numerator, density, contributing pairs) at p over the binned primitives."""
    s = wp.vec3(0.0, 0.0, 0.0)
    for l in range(b.level_size.shape[0]):
        c = level_cell(p, b.level_size[l], b.level_dims[l])
        for nb in range(27):
            r = neighbour_range(b, l, c, nb)
            for j in range(r[0], r[1]):
                s = add_pair(p, b, j, s)
    return s


@wp.func
def store_sums(i: int, s: wp.vec3, value: wp.array(dtype=float), density: wp.array(dtype=float), pairs: wp.array(dtype=int)):
    """Write point i's V~ = num / max(rho, RHO0), rho and pair count from (num, rho, pairs) sums."""
    value[i] = s[0] / wp.max(s[1], RHO0)
    density[i] = s[1]
    pairs[i] = int(s[2])


@wp.kernel
def eval_points_binned(
    points: wp.array(dtype=wp.vec3),  # [M] query positions (voxel units, x,y,z)
    prims: BinnedPrimitives,
    value: wp.array(dtype=float),  # [M] out: V~(p)
    density: wp.array(dtype=float),  # [M] out: rho(p) = sum w G
    pairs: wp.array(dtype=int),  # [M] out: contributing pairs
):
    """V~ at arbitrary points through the binned primitives (one thread per point)."""
    i = wp.tid()
    store_sums(i, binned_sums(points[i], prims), value, density, pairs)


@wp.kernel
def eval_grid_binned(
    z0: int,  # first output slice of this slab
    scale: wp.vec3,  # model voxels per output voxel along x, y, z
    prims: BinnedPrimitives,
    out: wp.array3d(dtype=float),  # [nz_slab, ny, nx] out: V~ at output voxel centres
):
    """Decode a slab of an output grid; output voxel (i,j,k) covers the same extent as the model
    grid, so its centre sits at ((i + 0.5) * scale - 0.5) in model voxel units."""
    k, j, i = wp.tid()
    p = wp.vec3(
        (float(i) + 0.5) * scale[0] - 0.5,
        (float(j) + 0.5) * scale[1] - 0.5,
        (float(k + z0) + 0.5) * scale[2] - 0.5,
    )
    s = binned_sums(p, prims)
    out[k, j, i] = s[0] / wp.max(s[1], RHO0)


@wp.kernel
def eval_points_dense(
    points: wp.array(dtype=wp.vec3),  # [M]
    mu: wp.array(dtype=wp.vec3),  # [N] prepared, any order
    conic: wp.array(dtype=vec6),
    ext: wp.array(dtype=wp.vec3),
    a: wp.array(dtype=float),
    w: wp.array(dtype=float),
    value: wp.array(dtype=float),  # [M] out
    density: wp.array(dtype=float),  # [M] out
    pairs: wp.array(dtype=int),  # [M] out
):
    """Reference: every primitive against every point, same truncation (tests and self-test only)."""
    i = wp.tid()
    p = points[i]
    num = float(0.0)
    den = float(0.0)
    n = int(0)
    for j in range(mu.shape[0]):
        g = conic_kernel(p - mu[j], ext[j], conic[j])
        if g > 0.0:
            num += w[j] * a[j] * g
            den += w[j] * g
            n += 1
    value[i] = num / wp.max(den, RHO0)
    density[i] = den
    pairs[i] = n


@wp.kernel
def eval_points_ordered(
    points: wp.array(dtype=wp.vec3),  # [P] query positions
    order: wp.array(dtype=int),  # [>=P] point index of each thread, cell-sorted for coherent reads
    prims: BinnedPrimitives,
    value: wp.array(dtype=float),  # [P] out: V~
    density: wp.array(dtype=float),  # [P] out: rho
    pairs: wp.array(dtype=int),  # [P] out: contributing pairs
):
    """:func:`eval_points_binned` visiting the points in ``order`` (neighbouring threads read the
    same cells; results are stored at the point's own index)."""
    i = order[wp.tid()]
    store_sums(i, binned_sums(points[i], prims), value, density, pairs)


@wp.kernel
def eval_points_partial(
    points: wp.array(dtype=wp.vec3),  # [P]
    order: wp.array(dtype=int),  # [>=P] point index of each row, cell-sorted
    prims: BinnedPrimitives,
    part: wp.array2d(dtype=wp.vec3),  # [P, 27 L] out: (sum w a G, sum w G, pairs) per neighbour cell
):
    """Partial sums of one (point, level, neighbour cell) each: 27 L threads per point.

    For GPUs, where one thread per point leaves the chip idle when there are few points (a
    training iteration may have only thousands). Every partial is stored, none is added
    atomically: :func:`finish_partials` sums them in a fixed order, so reruns are bit-identical.
    """
    k, t = wp.tid()
    l = t / 27
    p = points[order[k]]
    c = level_cell(p, prims.level_size[l], prims.level_dims[l])
    r = neighbour_range(prims, l, c, t % 27)
    s = wp.vec3(0.0, 0.0, 0.0)
    for j in range(r[0], r[1]):
        s = add_pair(p, prims, j, s)
    part[k, t] = s


@wp.kernel
def finish_partials(
    order: wp.array(dtype=int),  # [>=P]
    part: wp.array2d(dtype=wp.vec3),  # [P, 27 L] from eval_points_partial
    value: wp.array(dtype=float),  # [P] out: V~ = num / max(rho, RHO0)
    density: wp.array(dtype=float),  # [P] out
    pairs: wp.array(dtype=int),  # [P] out
):
    """Sum each point's partials in neighbour order (one thread per point)."""
    k = wp.tid()
    s = wp.vec3(0.0, 0.0, 0.0)
    for t in range(part.shape[1]):
        s += part[k, t]
    store_sums(order[k], s, value, density, pairs)


@wp.kernel
def point_keys(
    points: wp.array(dtype=wp.vec3),  # [>=count]
    count: int,  # points to bin; the launch has L * count threads
    level_size: wp.array(dtype=float),  # [L]
    level_dims: wp.array(dtype=wp.vec3i),  # [L]
    level_offset: wp.array(dtype=int),  # [L]
    keys: wp.array(dtype=int),  # [2 L count] out: cell id of (level, point) in the first L count entries
    values: wp.array(dtype=int),  # [2 L count] out: point index
):
    """Bin every point on every level (the same cells the primitives are binned in)."""
    k = wp.tid()
    l = k / count
    i = k - l * count
    keys[k] = cell_key(points[i], l, level_size, level_dims, level_offset)
    values[k] = i


@wp.kernel
def slot_cells(
    cell_start: wp.array(dtype=int),  # [C]
    cell_end: wp.array(dtype=int),  # [C]
    slot_cell: wp.array(dtype=int),  # [N] out: the cell each sorted slot is binned in
):
    """Invert the cell ranges: the cell id of every sorted slot (one thread per cell)."""
    c = wp.tid()
    for j in range(cell_start[c], cell_end[c]):
        slot_cell[j] = c


@wp.kernel
def cell_members(cell_start: wp.array(dtype=int), cell_end: wp.array(dtype=int), c: int, out: wp.array(dtype=int)):
    """out[0] = the number of slots binned in cell ``c`` (one thread; one read-back instead of two)."""
    out[0] = cell_end[c] - cell_start[c]


@wp.kernel
def count_keys(
    sorted_keys: wp.array(dtype=int),  # [>=K] cell id of each entry, ascending
    count: int,  # K entries (the launch has K threads)
    counts: wp.array(dtype=int),  # [C + 1] out (zeroed before): entries of each cell
):
    """Entries per cell: the last entry of each run of equal keys finds the run's first by a
    binary search and writes the run's length (no atomics: thousands of entries of one cell would
    queue on one address). Their exclusive prefix sum is the cell start table, empty cells holding
    the next cell's start (:func:`warpgauss.field.gaussians.cell_starts`)."""
    i = wp.tid()
    key = sorted_keys[i]
    if i + 1 < count:
        if sorted_keys[i + 1] == key:
            return
    lo = int(0)
    hi = i
    while lo < hi:  # first entry of this key
        mid = (lo + hi) / 2
        if sorted_keys[mid] < key:
            lo = mid + 1
        else:
            hi = mid
    counts[key] = i + 1 - lo
