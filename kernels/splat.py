"""EWA splatting of the Gaussian primitives (the interactive render path).

Each primitive becomes a screen-space 2D Gaussian: its world covariance is projected through the
view rotation and the perspective Jacobian (EWA: Sigma_2D = J W Sigma W^T J^T), truncated at the
same Mahalanobis 25 (5 sigma) as the field. The transfer function is applied per primitive: a
primitive of value a and weight w gets colour TF_rgb(a) (shaded with V~'s gradient at its centre)
and extinction coefficient

    kappa_i = density * TF_opacity(a_i) * w_i / max(rho(mu_i), RHO0)

so that, where primitives overlap, the extinctions sum to about density * TF_opacity(V~) as in the
mixture's normalised field (the normaliser rho is taken at the primitive's centre). Its optical
depth along a pixel's ray is kappa_i times the line integral of the truncated 3D Gaussian,

    L(m) = sqrt(2 pi / (d^T Sigma^-1 d)) exp(-m / 2) erf(sqrt((25 - m) / 2)),

m the 2D Mahalanobis distance of the pixel from the projected centre. Primitives are sorted by
view depth (centre), binned into 16x16-pixel tiles (a stable sort by tile keeps depth order within
each tile) and alpha-blended front to back with early termination, one thread per pixel.
"""

import warp as wp

from .field import RHO0, BinnedPrimitives
from .render import Camera, MarchParams, TransferLUT, shade, tf_lookup, value_density_grad

wp.set_module_options({"enable_backward": False})

TILE = wp.constant(16)  # tile edge in pixels
NEAR = wp.constant(1.0e-3)  # primitives closer to the eye plane than this are culled (world units)
TWO_PI = wp.constant(6.283185307179586)


@wp.kernel
def centre_samples(
    mu: wp.array(dtype=wp.vec3),  # [N] centres, model voxels
    prims: BinnedPrimitives,
    rho_c: wp.array(dtype=float),  # [N] out: density rho at the centre
    grad_c: wp.array(dtype=wp.vec3),  # [N] out: gradient of V~ at the centre (model voxels)
):
    """The mixture's density and gradient at each primitive's centre (camera-independent; once per model)."""
    i = wp.tid()
    v, rho, g = value_density_grad(mu[i], prims)
    rho_c[i] = rho
    grad_c[i] = g


@wp.kernel
def project(
    cam: Camera,
    prm: MarchParams,
    tf: TransferLUT,
    tiles_x: int,
    tiles_y: int,
    mu: wp.array(dtype=wp.vec3),  # [N] centres, model voxels
    rot: wp.array(dtype=wp.mat33),  # [N]
    inv_s2: wp.array(dtype=wp.vec3),  # [N] 1 / sigma^2 (model voxels)
    a: wp.array(dtype=float),  # [N]
    w: wp.array(dtype=float),  # [N]
    rho_c: wp.array(dtype=float),  # [N] density rho at each centre
    grad_c: wp.array(dtype=wp.vec3),  # [N] gradient of V~ at each centre (model voxels)
    xy: wp.array(dtype=wp.vec2),  # [N] out: projected centre, pixel units (pixel (i, j) centre at i + 0.5, j + 0.5)
    conic: wp.array(dtype=wp.vec3),  # [N] out: inverse 2D covariance (xx, xy, yy)
    amp: wp.array(dtype=float),  # [N] out: kappa * sqrt(2 pi / d^T Sigma^-1 d)
    color: wp.array(dtype=wp.vec3),  # [N] out: shaded colour
    depth: wp.array(dtype=float),  # [>=N] out: view depth (sort key)
    rect: wp.array(dtype=wp.vec4i),  # [N] out: tiles covered, tx0, ty0, tx1, ty1 inclusive
    count: wp.array(dtype=int),  # [N] out: tiles covered (0: culled)
):
    """Project one primitive: 2D mean and conic, amplitude, colour, tile rectangle."""
    i = wp.tid()
    count[i] = 0
    depth[i] = 3.0e38
    rgba = tf_lookup(tf, a[i])
    kappa = prm.density * rgba[3] * w[i] / wp.max(rho_c[i], RHO0)
    if kappa <= 0.0:
        return
    wpv = wp.cw_div(wp.vec3(1.0), prm.vox_per_world)  # world units per model voxel
    c_w = wp.cw_mul(mu[i], wpv)
    rel = c_w - cam.eye
    x = wp.dot(rel, cam.right)
    y = wp.dot(rel, cam.up)
    z = wp.dot(rel, cam.forward)
    if cam.ortho == 0 and z < NEAR:
        return
    # covariance in camera coordinates: V S R diag(s^2) R^T S V^T, V = rows (right, up, forward)
    r = rot[i]
    s2 = wp.vec3(1.0 / inv_s2[i][0], 1.0 / inv_s2[i][1], 1.0 / inv_s2[i][2])
    m = wp.diag(wpv) @ r
    cov_w = m @ wp.diag(s2) @ wp.transpose(m)
    view = wp.mat33(
        cam.right[0], cam.right[1], cam.right[2], cam.up[0], cam.up[1], cam.up[2], cam.forward[0], cam.forward[1], cam.forward[2]
    )
    cov_c = view @ cov_w @ wp.transpose(view)
    width = float(cam.width)
    height = float(cam.height)
    j0 = wp.vec3(0.0)
    j1 = wp.vec3(0.0)
    u = float(0.0)
    v = float(0.0)
    d_c = cam.forward
    if cam.ortho != 0:
        f = height / (2.0 * cam.half_height)
        u = 0.5 * width + f * x
        v = 0.5 * height - f * y
        j0 = wp.vec3(f, 0.0, 0.0)
        j1 = wp.vec3(0.0, -f, 0.0)
    else:
        f = height / (2.0 * cam.tan_half)
        u = 0.5 * width + f * x / z
        v = 0.5 * height - f * y / z
        # the Jacobian at a point clamped to 1.3x the view cone (as 3DGS): primitives far off-axis
        # near the eye would otherwise get unbounded footprints from the affine approximation
        lim_y = 1.3 * cam.tan_half
        lim_x = lim_y * width / height
        jx = wp.clamp(x / z, -lim_x, lim_x)
        jy = wp.clamp(y / z, -lim_y, lim_y)
        j0 = wp.vec3(f / z, 0.0, -f * jx / z)
        j1 = wp.vec3(0.0, -f / z, f * jy / z)
        d_c = wp.normalize(rel)
    sxx = wp.dot(j0, cov_c @ j0)
    sxy = wp.dot(j0, cov_c @ j1)
    syy = wp.dot(j1, cov_c @ j1)
    det = sxx * syy - sxy * sxy
    if det <= 1.0e-12 or sxx <= 0.0 or syy <= 0.0:
        return
    hx = 5.0 * wp.sqrt(sxx)
    hy = 5.0 * wp.sqrt(syy)
    if u + hx < 0.0 or u - hx > width or v + hy < 0.0 or v - hy > height:
        return
    tx0 = wp.clamp(int(wp.floor((u - hx) / float(TILE))), 0, tiles_x - 1)
    tx1 = wp.clamp(int(wp.floor((u + hx) / float(TILE))), 0, tiles_x - 1)
    ty0 = wp.clamp(int(wp.floor((v - hy) / float(TILE))), 0, tiles_y - 1)
    ty1 = wp.clamp(int(wp.floor((v + hy) / float(TILE))), 0, tiles_y - 1)
    # line integral of the 3D Gaussian through its centre along the central ray (world units)
    yv = wp.transpose(r) @ wp.cw_mul(d_c, prm.vox_per_world)
    along = yv[0] * yv[0] * inv_s2[i][0] + yv[1] * yv[1] * inv_s2[i][1] + yv[2] * yv[2] * inv_s2[i][2]
    rgb = wp.vec3(rgba[0], rgba[1], rgba[2])
    if prm.shading != 0:
        rgb = shade(rgb, grad_c[i], -d_c, prm)
    xy[i] = wp.vec2(u, v)
    conic[i] = wp.vec3(syy / det, -sxy / det, sxx / det)
    amp[i] = kappa * wp.sqrt(TWO_PI / wp.max(along, 1.0e-30))
    color[i] = rgb
    depth[i] = z
    rect[i] = wp.vec4i(tx0, ty0, tx1, ty1)
    count[i] = (tx1 - tx0 + 1) * (ty1 - ty0 + 1)


@wp.kernel
def iota(order: wp.array(dtype=int)):  # [>=N] out: order[i] = i
    i = wp.tid()
    order[i] = i


@wp.kernel
def gather_counts(
    order: wp.array(dtype=int),  # [>=N] primitive index by depth rank
    count: wp.array(dtype=int),  # [N]
    sorted_count: wp.array(dtype=int),  # [N] out: count in depth order
):
    r = wp.tid()
    sorted_count[r] = count[order[r]]


@wp.kernel
def total_pairs(offsets: wp.array(dtype=int), sorted_count: wp.array(dtype=int), total: wp.array(dtype=int)):
    """total[0] = last exclusive offset + last count (one thread)."""
    n = offsets.shape[0]
    total[0] = offsets[n - 1] + sorted_count[n - 1]


@wp.kernel
def emit_pairs(
    order: wp.array(dtype=int),  # [>=N] primitive index by depth rank
    offsets: wp.array(dtype=int),  # [N] exclusive prefix sum of the counts in depth order
    rect: wp.array(dtype=wp.vec4i),  # [N]
    count: wp.array(dtype=int),  # [N]
    tiles_x: int,
    keys: wp.array(dtype=int),  # [>=2P] out: tile id
    values: wp.array(dtype=int),  # [>=2P] out: primitive index
):
    """One (tile, primitive) pair per tile a primitive covers, written in depth order."""
    r = wp.tid()
    i = order[r]
    if count[i] == 0:
        return
    k = offsets[r]
    b = rect[i]
    for ty in range(b[1], b[3] + 1):
        for tx in range(b[0], b[2] + 1):
            keys[k] = ty * tiles_x + tx
            values[k] = i
            k += 1


@wp.kernel
def blend(
    cam: Camera,
    prm: MarchParams,
    tiles_x: int,
    tile_start: wp.array(dtype=int),  # [T]
    tile_end: wp.array(dtype=int),  # [T]
    prim: wp.array(dtype=int),  # [>=P] primitive of each pair, tile order then depth order
    xy: wp.array(dtype=wp.vec2),  # [N]
    conic: wp.array(dtype=wp.vec3),  # [N]
    amp: wp.array(dtype=float),  # [N]
    color: wp.array(dtype=wp.vec3),  # [N]
    image: wp.array2d(dtype=wp.vec4),  # [H, W] out
    drawn: wp.array2d(dtype=int),  # [H, W] out: splats that contributed to the pixel
):
    """Front-to-back alpha blending of a pixel's tile list (one thread per pixel).

    Threads run tile by tile (TILE^2 consecutive threads per tile), so a warp's pixels share one
    tile's list: the same loop bounds and the same primitive reads for all 32 (a row-major warp
    would straddle two tiles).
    """
    tid = wp.tid()
    t = tid / (TILE * TILE)
    local = tid - t * TILE * TILE
    j = (t / tiles_x) * TILE + local / TILE
    i = (t % tiles_x) * TILE + local % TILE
    if j >= image.shape[0] or i >= image.shape[1]:
        return
    px = wp.vec2(float(i) + 0.5, float(j) + 0.5)
    col = wp.vec3(0.0)
    trans = float(1.0)
    n = int(0)
    for k in range(tile_start[t], tile_end[t]):
        g = prim[k]
        d = px - xy[g]
        c = conic[g]
        m = c[0] * d[0] * d[0] + 2.0 * c[1] * d[0] * d[1] + c[2] * d[1] * d[1]
        if m < 25.0:
            tau = amp[g] * wp.exp(-0.5 * m) * wp.erf(wp.sqrt(0.5 * (25.0 - m)))
            alpha = 1.0 - wp.exp(-tau)
            col += trans * alpha * color[g]
            trans *= 1.0 - alpha
            n += 1
            if trans < prm.ert:
                break
    out = col + trans * prm.background
    image[j, i] = wp.vec4(out[0], out[1], out[2], 1.0 - trans)
    drawn[j, i] = n
