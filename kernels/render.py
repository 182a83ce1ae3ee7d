"""Ray marching of the Gaussian mixture field V~ and of a dense reference grid (emission-absorption).

One thread per pixel. A ray is clipped to the render box (the encoded grid, narrowed to the union of
the primitives' 5-sigma boxes), then sampled on a view-aligned lattice t_k = k * step (world
units) so that a model and a dense volume rendered with the same camera see identical sample
positions. At each sample the transfer function maps the value to colour and opacity, the
opacity times a density factor gives the extinction sigma, and front-to-back compositing adds
T * (1 - exp(-sigma * step)) * colour. Rays stop early once T falls below a threshold.

Empty-space skipping uses a coarse occupancy grid built by a kernel: a cell that no primitive's
5-sigma box touches holds V~ = 0 exactly (its samples all get the transfer function's value at 0,
composited in closed form), and a cell whose largest contributing value maps to zero opacity over
[0, max] is skipped. Both are exact: the skipped samples would have added nothing else. A dense
grid marks its cells the same way from its non-zero voxels (:func:`mark_voxels`).

Shading needs the gradient only where a sample is visible: the mixture computes it in the same
pass as the value when shading is on (one traversal of the binned primitives serves both), the
dense grid only for samples of non-zero opacity (one trilinear fetch of its half-precision
gradient grid, or six more trilinear taps where there is none; nothing for the rest).

Render space ("world") is the model's voxel grid scaled by spacing / min(spacing), so one world
unit is one voxel along the finest axis; t is measured in world units.

The same marcher serves the model (:class:`warpgauss.kernels.field.BinnedPrimitives`, evaluated
through :func:`~warpgauss.kernels.field.binned_sums`: the exact ``march``) and a dense grid
(:class:`DenseVolume`, trilinear), through the overloaded ``march_sample`` / ``sample_gradient``.
The dense grid is either a reference volume or the model decoded once onto a grid (the ``cached``
method of :mod:`warpgauss.render.renderers`): then a sample reads 1 voxel neighbourhood instead of the
~1000 candidate primitives of the binned mixture.
"""

import typing

import warp as wp

from .analysis import trilinear, trilinear_axis
from .field import RHO0, BinnedPrimitives, binned_sums, level_cell, neighbour_range, truncated_kernel

wp.set_module_options({"enable_backward": False})

CELL_EMPTY = wp.constant(0)  # no primitive touches the cell: V~ = 0 everywhere in it
CELL_SKIP = wp.constant(1)  # transparent for the current transfer function
CELL_MARCH = wp.constant(2)  # must be sampled


@wp.struct
class Camera:
    """Pinhole (or orthographic) camera in world coordinates."""

    eye: wp.vec3  # centre of projection (ortho: centre of the image plane)
    right: wp.vec3  # unit image x axis
    up: wp.vec3  # unit image y axis (rows go down the image)
    forward: wp.vec3  # unit viewing direction
    tan_half: float  # tan(vertical field of view / 2), perspective
    half_height: float  # half the image height in world units, orthographic
    ortho: int  # 1: orthographic
    width: int
    height: int


@wp.struct
class TransferLUT:
    """Transfer function sampled at K evenly spaced values over [0, 1]."""

    rgba: wp.array(dtype=wp.vec4)  # [K] colour (0..1) and opacity (0..1)
    max_opacity: wp.array(dtype=float)  # [K] max opacity over entries 0..k (skip test)


@wp.struct
class MarchParams:
    """Everything a ray needs besides the camera, the transfer function and the source."""

    vox_per_world: wp.vec3  # 1 / (spacing / min spacing): world -> model voxel coordinates
    box_lo: wp.vec3  # render box in model voxel coordinates
    box_hi: wp.vec3
    step: float  # sample spacing, world units
    density: float  # extinction per world unit at transfer-function opacity 1
    ert: float  # early ray termination: stop once transmittance < ert (0: never)
    background: wp.vec3
    shading: int  # 1: Blinn-Phong from the field's gradient
    ambient: float
    diffuse: float
    specular: float
    shininess: float
    light: wp.vec3  # unit direction towards the light (world); zero vector: headlight
    tile: int  # the launch goes over the image in tile x tile squares of pixels (1: row by row)


@wp.struct
class Occupancy:
    """Coarse cells over the model grid (cells start at -0.5, the voxel edge)."""

    cell: float  # cell edge in model voxels
    dims: wp.vec3i
    enabled: int  # 0: march every sample
    touched: wp.array(dtype=int)  # [C] 1 where any primitive support (or non-zero voxel's stencil) reaches
    max_value: wp.array(dtype=float)  # [C] largest value that can occur in the cell
    state: wp.array(dtype=int)  # [C] CELL_EMPTY / CELL_SKIP / CELL_MARCH for the current TF


@wp.struct
class DenseVolume:
    """A dense normalised grid as a render source (trilinear, clamped to the edge)."""

    values: wp.array3d(dtype=float)  # [nz, ny, nx]
    scale: wp.vec3  # volume voxels per model voxel along x, y, z
    grad: wp.array3d(dtype=wp.vec4h)  # [nz, ny, nx] (gx, gy, gz, 0) per model voxel at the grid points (half precision)
    has_grad: int  # 1: shade from ``grad`` (8 taps), 0: by central differences of the values (6 trilinear samples)


# ------------------------------------------------------------------------------------------------
# Field samples: value and gradient (model voxel units)
# ------------------------------------------------------------------------------------------------


@wp.func
def binned_sums_grad(p: wp.vec3, b: BinnedPrimitives):
    """(num, rho, d num / dp, d rho / dp) at p over the binned primitives (same pairs as binned_sums)."""
    num = float(0.0)
    den = float(0.0)
    g_num = wp.vec3(0.0)
    g_den = wp.vec3(0.0)
    for l in range(b.level_size.shape[0]):
        c = level_cell(p, b.level_size[l], b.level_dims[l])
        for nb in range(27):
            r = neighbour_range(b, l, c, nb)
            for j in range(r[0], r[1]):
                g = truncated_kernel(p, b.mu[j], b.rot[j], b.inv_s2[j], b.ext[j])
                if g > 0.0:
                    rot = b.rot[j]
                    y = wp.transpose(rot) @ (p - b.mu[j])
                    q = rot @ wp.cw_mul(y, b.inv_s2[j])  # Sigma^-1 d
                    wg = b.w[j] * g
                    num += wg * b.a[j]
                    den += wg
                    g_num -= (wg * b.a[j]) * q
                    g_den -= wg * q
    return num, den, g_num, g_den


@wp.func
def value_density_grad(p: wp.vec3, b: BinnedPrimitives):
    """(V~, rho, grad V~) at p; the gradient by the quotient rule (below RHO0 the denominator is constant)."""
    num, den, g_num, g_den = binned_sums_grad(p, b)
    d = wp.max(den, RHO0)
    v = num / d
    g = g_num / d
    if den > RHO0:
        g = (g_num - v * g_den) / d
    return v, den, g


@wp.func
def field_sample(src: BinnedPrimitives, p: wp.vec3, want_grad: int) -> wp.vec4:
    """(V~, dV~/dx, dV~/dy, dV~/dz) of the mixture at p; the gradient only when asked (else 0)."""
    if want_grad == 0:
        s = binned_sums(p, src)
        return wp.vec4(s[0] / wp.max(s[1], RHO0), 0.0, 0.0, 0.0)
    v, rho, g = value_density_grad(p, src)
    return wp.vec4(v, g[0], g[1], g[2])


@wp.func
def dense_value(src: DenseVolume, p: wp.vec3) -> float:
    q = wp.cw_mul(p + wp.vec3(0.5), src.scale) - wp.vec3(0.5)
    return trilinear(src.values, q)


@wp.func
def dense_gradient(src: DenseVolume, p: wp.vec3) -> wp.vec3:
    """Gradient of the trilinear grid at p by central differences of one model voxel (model voxel units)."""
    gx = dense_value(src, p + wp.vec3(1.0, 0.0, 0.0)) - dense_value(src, p - wp.vec3(1.0, 0.0, 0.0))
    gy = dense_value(src, p + wp.vec3(0.0, 1.0, 0.0)) - dense_value(src, p - wp.vec3(0.0, 1.0, 0.0))
    gz = dense_value(src, p + wp.vec3(0.0, 0.0, 1.0)) - dense_value(src, p - wp.vec3(0.0, 0.0, 1.0))
    return wp.vec3(0.5 * gx, 0.5 * gy, 0.5 * gz)


@wp.func
def grid_gradient(src: DenseVolume, p: wp.vec3) -> wp.vec3:
    """The shading gradient of the grid at p (model voxel units): from the gradient grid when there
    is one (one trilinear fetch of 8 half-precision vectors; :func:`dense_gradient` up to the
    half precision where the grid is the model's, since a central difference of the trilinear
    interpolant over one voxel is the trilinear interpolant of the grid's central differences),
    else by central differences of the values."""
    if src.has_grad != 0:
        q = wp.cw_mul(p + wp.vec3(0.5), src.scale) - wp.vec3(0.5)
        return trilinear_half(src.grad, q)
    return dense_gradient(src, p)


@wp.func
def half3(v: wp.vec4h) -> wp.vec3:
    return wp.vec3(float(v[0]), float(v[1]), float(v[2]))


@wp.func
def trilinear_half(vol: wp.array3d(dtype=wp.vec4h), p: wp.vec3) -> wp.vec3:
    """:func:`trilinear` of a half-precision vector grid (first three lanes), in single precision."""
    i0, i1, tx = trilinear_axis(p[0], vol.shape[2])
    j0, j1, ty = trilinear_axis(p[1], vol.shape[1])
    k0, k1, tz = trilinear_axis(p[2], vol.shape[0])
    c00 = wp.lerp(half3(vol[k0, j0, i0]), half3(vol[k0, j0, i1]), tx)
    c01 = wp.lerp(half3(vol[k0, j1, i0]), half3(vol[k0, j1, i1]), tx)
    c10 = wp.lerp(half3(vol[k1, j0, i0]), half3(vol[k1, j0, i1]), tx)
    c11 = wp.lerp(half3(vol[k1, j1, i0]), half3(vol[k1, j1, i1]), tx)
    return wp.lerp(wp.lerp(c00, c01, ty), wp.lerp(c10, c11, ty), tz)


@wp.func
def field_sample(src: DenseVolume, p: wp.vec3, want_grad: int) -> wp.vec4:
    """(V, gradient) of the trilinear grid at p, the gradient as the marcher shades with it."""
    v = dense_value(src, p)
    if want_grad == 0:
        return wp.vec4(v, 0.0, 0.0, 0.0)
    g = grid_gradient(src, p)
    return wp.vec4(v, g[0], g[1], g[2])


@wp.func
def march_sample(src: BinnedPrimitives, p: wp.vec3, shading: int) -> wp.vec4:
    """What the marcher reads first at a sample: the mixture's value, and its gradient when shading
    (one traversal of the candidates gives both; a second one for visible samples only would cost more)."""
    return field_sample(src, p, shading)


@wp.func
def march_sample(src: DenseVolume, p: wp.vec3, shading: int) -> wp.vec4:
    """What the marcher reads first at a sample of the grid: the value only (one trilinear tap)."""
    return wp.vec4(dense_value(src, p), 0.0, 0.0, 0.0)


@wp.func
def sample_gradient(src: BinnedPrimitives, p: wp.vec3, s: wp.vec4) -> wp.vec3:
    """The gradient for shading a visible sample: the mixture's came with ``s``."""
    return wp.vec3(s[1], s[2], s[3])


@wp.func
def sample_gradient(src: DenseVolume, p: wp.vec3, s: wp.vec4) -> wp.vec3:
    """The gradient for shading a visible sample of the grid, evaluated now."""
    return grid_gradient(src, p)


# ------------------------------------------------------------------------------------------------
# Shared pieces: rays, boxes, transfer function, shading
# ------------------------------------------------------------------------------------------------


@wp.func
def camera_ray(cam: Camera, i: int, j: int):
    """World origin and unit direction of the ray through the centre of pixel (column i, row j)."""
    aspect = float(cam.width) / float(cam.height)
    sx = (2.0 * (float(i) + 0.5) / float(cam.width) - 1.0) * aspect
    sy = 1.0 - 2.0 * (float(j) + 0.5) / float(cam.height)
    if cam.ortho != 0:
        o = cam.eye + cam.right * (sx * cam.half_height) + cam.up * (sy * cam.half_height)
        return o, cam.forward
    d = cam.forward + cam.right * (sx * cam.tan_half) + cam.up * (sy * cam.tan_half)
    return cam.eye, wp.normalize(d)


@wp.func
def clip_box(o: wp.vec3, d: wp.vec3, lo: wp.vec3, hi: wp.vec3) -> wp.vec2:
    """[t_near, t_far] of the ray o + t d inside the box (t_near > t_far: miss)."""
    t0 = float(-1.0e30)
    t1 = float(1.0e30)
    for a in range(3):
        if wp.abs(d[a]) < 1.0e-12:
            if o[a] < lo[a] or o[a] > hi[a]:
                t0 = 1.0e30
                t1 = -1.0e30
        else:
            inv = 1.0 / d[a]
            ta = (lo[a] - o[a]) * inv
            tb = (hi[a] - o[a]) * inv
            t0 = wp.max(t0, wp.min(ta, tb))
            t1 = wp.min(t1, wp.max(ta, tb))
    return wp.vec2(t0, t1)


@wp.func
def cell_exit(o: wp.vec3, d: wp.vec3, c: wp.vec3i, cell: float) -> float:
    """t at which the ray leaves cell c (cells start at -0.5)."""
    t = float(1.0e30)
    for a in range(3):
        lo = -0.5 + float(c[a]) * cell
        if d[a] > 1.0e-12:
            t = wp.min(t, (lo + cell - o[a]) / d[a])
        elif d[a] < -1.0e-12:
            t = wp.min(t, (lo - o[a]) / d[a])
    return t


@wp.func
def tf_lookup(tf: TransferLUT, v: float) -> wp.vec4:
    """Colour and opacity at value v (clamped to [0, 1]), linear between LUT entries."""
    k = tf.rgba.shape[0]
    x = wp.clamp(v, 0.0, 1.0) * float(k - 1)
    i0 = wp.min(int(x), k - 2)
    f = x - float(i0)
    return tf.rgba[i0] * (1.0 - f) + tf.rgba[i0 + 1] * f


@wp.func
def tf_max_opacity(tf: TransferLUT, v: float) -> float:
    """Largest opacity the transfer function reaches over [0, v] (conservative)."""
    k = tf.max_opacity.shape[0]
    i = wp.min(int(wp.ceil(wp.clamp(v, 0.0, 1.0) * float(k - 1))), k - 1)
    return tf.max_opacity[i]


@wp.func
def shade(rgb: wp.vec3, g_vox: wp.vec3, view: wp.vec3, prm: MarchParams) -> wp.vec3:
    """Two-sided Blinn-Phong with the normal along the field gradient (world space).

    Args:
        g_vox: Gradient of the value in model voxel coordinates.
        view: Unit vector from the sample towards the eye.
    """
    g = wp.cw_mul(g_vox, prm.vox_per_world)
    gl = wp.length(g)
    if gl < 1.0e-8:
        return rgb * (prm.ambient + prm.diffuse)
    n = g / gl
    l = prm.light
    if wp.length(l) < 0.5:
        l = view
    h = wp.normalize(l + view)
    ndl = wp.abs(wp.dot(n, l))
    ndh = wp.abs(wp.dot(n, h))
    # Warp's pow takes its own float types (Warp scalars, not Python floats); mypy sees object
    spec = prm.specular * wp.pow(ndh, prm.shininess)  # type: ignore[type-var]
    return rgb * (prm.ambient + prm.diffuse * ndl) + wp.vec3(spec, spec, spec)


# ------------------------------------------------------------------------------------------------
# Kernels
# ------------------------------------------------------------------------------------------------


@wp.kernel
def march(
    src: typing.Any,  # BinnedPrimitives (the model) or DenseVolume (the reference)
    cam: Camera,
    prm: MarchParams,
    tf: TransferLUT,
    occ: Occupancy,
    image: wp.array2d(dtype=wp.vec4),  # [H, W] out: rgb over the background, alpha = 1 - T
    samples: wp.array2d(dtype=int),  # [H, W] out: field evaluations spent on the pixel
):
    """Emission-absorption ray marching, one thread per pixel, launched over ``prm.tile`` x
    ``prm.tile`` tiles of the image (``dim`` = tiles x tile^2; tile 1: row by row).

    Args:
        src: The field: mixture model or dense grid.
    """
    tid = wp.tid()
    tt = prm.tile * prm.tile
    tile = tid // tt
    within = tid - tile * tt
    tiles_x = (cam.width + prm.tile - 1) // prm.tile
    i = (tile % tiles_x) * prm.tile + within % prm.tile
    j = (tile // tiles_x) * prm.tile + within // prm.tile
    if i >= cam.width or j >= cam.height:
        return
    o_w, d_w = camera_ray(cam, i, j)
    o = wp.cw_mul(o_w, prm.vox_per_world)  # model voxel coordinates, t still in world units
    d = wp.cw_mul(d_w, prm.vox_per_world)
    span = clip_box(o, d, prm.box_lo, prm.box_hi)
    col = wp.vec3(0.0)
    trans = float(1.0)
    n_eval = int(0)
    k = int(wp.ceil(wp.max(span[0], 0.0) / prm.step))
    k_end = int(wp.floor(span[1] / prm.step))
    if span[1] < span[0]:
        k_end = k - 1
    empty = tf_lookup(tf, 0.0)  # what a sample with V~ = 0 contributes
    empty_rgb = wp.vec3(empty[0], empty[1], empty[2]) * (prm.ambient + prm.diffuse)
    if prm.shading == 0:
        empty_rgb = wp.vec3(empty[0], empty[1], empty[2])
    empty_sigma = empty[3] * prm.density
    while k <= k_end:
        t = float(k) * prm.step
        p = o + d * t
        if occ.enabled != 0:
            c = level_cell(p, occ.cell, occ.dims)
            cid = (c[2] * occ.dims[1] + c[1]) * occ.dims[0] + c[0]
            state = occ.state[cid]
            if state != CELL_MARCH:
                kn = wp.min(wp.max(k + 1, int(wp.ceil(cell_exit(o, d, c, occ.cell) / prm.step))), k_end + 1)
                if state == CELL_EMPTY and empty_sigma > 0.0:
                    a = 1.0 - wp.exp(-empty_sigma * prm.step * float(kn - k))
                    col += trans * a * empty_rgb
                    trans *= 1.0 - a
                    if trans < prm.ert:
                        break
                k = kn
                continue
        s = march_sample(src, p, prm.shading)
        n_eval += 1
        rgba = tf_lookup(tf, s[0])
        sigma = rgba[3] * prm.density
        if sigma > 0.0:
            a = 1.0 - wp.exp(-sigma * prm.step)
            rgb = wp.vec3(rgba[0], rgba[1], rgba[2])
            if prm.shading != 0:
                rgb = shade(rgb, sample_gradient(src, p, s), -d_w, prm)
            col += trans * a * rgb
            trans *= 1.0 - a
            if trans < prm.ert:
                break
        k += 1
    out = col + trans * prm.background
    image[j, i] = wp.vec4(out[0], out[1], out[2], 1.0 - trans)
    samples[j, i] = n_eval


wp.overload(march, {"src": BinnedPrimitives})
wp.overload(march, {"src": DenseVolume})


@wp.kernel
def to_rgb8(image: wp.array2d(dtype=wp.vec4), out: wp.array3d(dtype=wp.uint8)):
    """RGB8 of a frame on the device (as ``Image.rgb8``: clamp to [0, 1], x 255, + 0.5, truncate),
    so a frame crosses to the host as 3 bytes a pixel and is not converted there."""
    i, j = wp.tid()
    c = image[i, j]
    for k in range(3):
        out[i, j, k] = wp.uint8(int(wp.clamp(c[k], 0.0, 1.0) * 255.0 + 0.5))


@wp.kernel
def central_gradient(values: wp.array3d(dtype=float), scale: wp.vec3, grad: wp.array3d(dtype=wp.vec4h)):
    """The gradient grid of a dense volume: half the difference of the two neighbours along each
    axis (the edge voxel stands in for a missing one, as the clamped trilinear sample does),
    times ``scale`` (volume voxels per model voxel) so it is per model voxel; stored in half
    precision (8 bytes a voxel: shading needs directions, not 7 digits)."""
    k, j, i = wp.tid()
    nz, ny, nx = values.shape[0], values.shape[1], values.shape[2]
    gx = values[k, j, wp.min(i + 1, nx - 1)] - values[k, j, wp.max(i - 1, 0)]
    gy = values[k, wp.min(j + 1, ny - 1), i] - values[k, wp.max(j - 1, 0), i]
    gz = values[wp.min(k + 1, nz - 1), j, i] - values[wp.max(k - 1, 0), j, i]
    g = wp.vec3(0.5 * gx * scale[0], 0.5 * gy * scale[1], 0.5 * gz * scale[2])
    grad[k, j, i] = wp.vec4h(wp.float16(g[0]), wp.float16(g[1]), wp.float16(g[2]), wp.float16(0.0))


@wp.kernel
def row_sums_max(counts: wp.array2d(dtype=int), sums: wp.array(dtype=wp.int64), maxes: wp.array(dtype=int)):
    """Per row of a (H, W) count image: the exact sum (int64) and the maximum."""
    i = wp.tid()
    s = wp.int64(0)
    m = int(0)
    for j in range(counts.shape[1]):
        c = counts[i, j]
        s += wp.int64(c)
        m = wp.max(m, c)
    sums[i] = s
    maxes[i] = m


@wp.kernel
def count_positive(a: wp.array(dtype=int), out: wp.array(dtype=int)):
    """out[0] += how many entries of ``a`` are > 0 (integer atomics: the same count every run)."""
    i = wp.tid()
    if a[i] > 0:
        wp.atomic_add(out, 0, 1)


@wp.kernel
def sample_points(
    src: typing.Any,  # BinnedPrimitives or DenseVolume
    points: wp.array(dtype=wp.vec3),  # [M] model voxel coordinates
    want_grad: int,
    out: wp.array(dtype=wp.vec4),  # [M] out: value and gradient, as the marcher sees them
):
    """The marcher's field samples at arbitrary points (for tests and probing)."""
    i = wp.tid()
    out[i] = field_sample(src, points[i], want_grad)


wp.overload(sample_points, {"src": BinnedPrimitives})
wp.overload(sample_points, {"src": DenseVolume})


@wp.kernel
def mark_primitives(
    mu: wp.array(dtype=wp.vec3),  # [N] centres (model voxels)
    ext: wp.array(dtype=wp.vec3),  # [N] 5-sigma half-extents
    a: wp.array(dtype=float),  # [N] values
    occ: Occupancy,  # touched and max_value are updated
):
    """Mark every occupancy cell a primitive's 5-sigma box overlaps (one thread per primitive)."""
    i = wp.tid()
    lo = level_cell(mu[i] - ext[i], occ.cell, occ.dims)
    hi = level_cell(mu[i] + ext[i], occ.cell, occ.dims)
    v = wp.clamp(a[i], 0.0, 1.0)
    for z in range(lo[2], hi[2] + 1):
        for y in range(lo[1], hi[1] + 1):
            for x in range(lo[0], hi[0] + 1):
                cid = (z * occ.dims[1] + y) * occ.dims[0] + x
                occ.touched[cid] = 1
                wp.atomic_max(occ.max_value, cid, v)


@wp.kernel
def mark_voxels(
    vol: DenseVolume,
    occ: Occupancy,  # touched and max_value are updated (zeroed before)
):
    """Mark the cells a non-zero voxel can reach (one thread per voxel).

    A sample's value reads the voxels within one volume voxel of it (trilinear, clamped at the
    edges), its gradient those within one model voxel more (central differences). A non-zero
    voxel raises ``max_value`` over the first reach and marks ``touched`` over the second, so an
    untouched cell has value 0 and gradient 0 at every sample: exactly what the marcher composites
    in closed form for an empty cell. Zero voxels mark nothing.
    """
    k, j, i = wp.tid()
    raw = vol.values[k, j, i]
    if raw == 0.0:
        return
    v = wp.clamp(raw, 0.0, 1.0)
    # voxel centre in model voxel coordinates
    c = wp.cw_div(wp.vec3(float(i), float(j), float(k)) + wp.vec3(0.5), vol.scale) - wp.vec3(0.5)
    r = wp.cw_div(wp.vec3(1.0), vol.scale)
    rg = r + wp.vec3(1.0)
    lo = level_cell(c - rg, occ.cell, occ.dims)
    hi = level_cell(c + rg, occ.cell, occ.dims)
    for z in range(lo[2], hi[2] + 1):
        for y in range(lo[1], hi[1] + 1):
            for x in range(lo[0], hi[0] + 1):
                occ.touched[(z * occ.dims[1] + y) * occ.dims[0] + x] = 1
    if v > 0.0:
        lo = level_cell(c - r, occ.cell, occ.dims)
        hi = level_cell(c + r, occ.cell, occ.dims)
        for z in range(lo[2], hi[2] + 1):
            for y in range(lo[1], hi[1] + 1):
                for x in range(lo[0], hi[0] + 1):
                    wp.atomic_max(occ.max_value, (z * occ.dims[1] + y) * occ.dims[0] + x, v)


@wp.kernel
def classify_cells(occ: Occupancy, tf: TransferLUT):
    """Per cell: empty (no primitive), transparent under this transfer function, or to be marched."""
    c = wp.tid()
    if occ.touched[c] == 0:
        occ.state[c] = CELL_EMPTY
    elif tf_max_opacity(tf, occ.max_value[c]) <= 0.0:
        occ.state[c] = CELL_SKIP
    else:
        occ.state[c] = CELL_MARCH


@wp.kernel
def support_bounds(
    mu: wp.array(dtype=wp.vec3),  # [N]
    ext: wp.array(dtype=wp.vec3),  # [N]
    bounds: wp.array(dtype=float),  # [6] in/out: lo xyz (atomic min), hi xyz (atomic max)
):
    """Union of the primitives' 5-sigma boxes (one thread per primitive)."""
    i = wp.tid()
    lo = mu[i] - ext[i]
    hi = mu[i] + ext[i]
    for a in range(3):
        wp.atomic_min(bounds, a, lo[a])
        wp.atomic_max(bounds, 3 + a, hi[a])
