"""Motion between two timesteps (a warm start's motion compensation, issue #21).

The previous model, decoded on the grid (``ref``), and the new timestep (``cur``) are matched by
block Lucas-Kanade on an image pyramid: each block of ``block``^3 voxels of a level finds the
displacement d that minimises sum (ref(x) - cur(x + d))^2 over its voxels by Gauss-Newton steps
(``lk_step``), starting from the coarser level's estimate (``upsample_blocks``); a block without
texture takes its neighbours' motion through a confidence-weighted 3^3 average
(``smooth_blocks``, weight: the trace of its normal matrix). A primitive then moves by the
displacement interpolated at its centre (``shift_centres``): structure at x at the previous
timestep is at x + d now (a primitive it would carry out of the grid stays).
"""

import warp as wp

from .analysis import trilinear

wp.set_module_options({"enable_backward": False})

MAX_STEP = wp.constant(2.0)  # voxels one Gauss-Newton step may move a block (at its level)


@wp.kernel
def downsample2(src: wp.array3d(dtype=float), dst: wp.array3d(dtype=float)):
    """dst = the 2x2x2 mean of src (a voxel past the edge repeats the last one)."""
    k, j, i = wp.tid()
    nz, ny, nx = src.shape[0], src.shape[1], src.shape[2]
    s = float(0.0)
    for dk in range(2):
        for dj in range(2):
            for di in range(2):
                s += src[wp.min(2 * k + dk, nz - 1), wp.min(2 * j + dj, ny - 1), wp.min(2 * i + di, nx - 1)]
    dst[k, j, i] = 0.125 * s


@wp.kernel
def lk_step(
    ref: wp.array3d(dtype=float),
    cur: wp.array3d(dtype=float),
    disp: wp.array3d(dtype=wp.vec3),
    block: int,
    lam: float,
    out: wp.array3d(dtype=wp.vec3),
    conf: wp.array3d(dtype=float),
):
    """One Gauss-Newton step of each block's displacement (see the module docstring)."""
    bk, bj, bi = wp.tid()
    nz, ny, nx = ref.shape[0], ref.shape[1], ref.shape[2]
    d = disp[bk, bj, bi]
    a = wp.mat33()
    b = wp.vec3(0.0)
    for dk in range(block):
        k = bk * block + dk
        if k < nz:
            for dj in range(block):
                j = bj * block + dj
                if j < ny:
                    for di in range(block):
                        i = bi * block + di
                        if i < nx:
                            p = wp.vec3(float(i), float(j), float(k)) + d
                            c = trilinear(cur, p)
                            g = wp.vec3(
                                0.5 * (trilinear(cur, p + wp.vec3(1.0, 0.0, 0.0)) - trilinear(cur, p - wp.vec3(1.0, 0.0, 0.0))),
                                0.5 * (trilinear(cur, p + wp.vec3(0.0, 1.0, 0.0)) - trilinear(cur, p - wp.vec3(0.0, 1.0, 0.0))),
                                0.5 * (trilinear(cur, p + wp.vec3(0.0, 0.0, 1.0)) - trilinear(cur, p - wp.vec3(0.0, 0.0, 1.0))),
                            )
                            a += wp.outer(g, g)
                            b += g * (ref[k, j, i] - c)
    tr = a[0, 0] + a[1, 1] + a[2, 2]
    step = wp.inverse(a + wp.identity(n=3, dtype=float) * (lam + 1.0e-3 * tr)) * b
    n = wp.length(step)
    if n > MAX_STEP:
        step = step * (MAX_STEP / n)
    out[bk, bj, bi] = d + step
    conf[bk, bj, bi] = tr


@wp.kernel
def smooth_blocks(disp: wp.array3d(dtype=wp.vec3), conf: wp.array3d(dtype=float), floor: float, out: wp.array3d(dtype=wp.vec3)):
    """Confidence-weighted 3^3 mean of the block displacements (a textureless block takes its neighbours')."""
    bk, bj, bi = wp.tid()
    nz, ny, nx = disp.shape[0], disp.shape[1], disp.shape[2]
    s = wp.vec3(0.0)
    w = float(0.0)
    for dk in range(-1, 2):
        for dj in range(-1, 2):
            for di in range(-1, 2):
                k, j, i = bk + dk, bj + dj, bi + di
                if k >= 0 and j >= 0 and i >= 0 and k < nz and j < ny and i < nx:
                    c = conf[k, j, i] + floor
                    if dk == 0 and dj == 0 and di == 0:
                        c = 2.0 * c
                    s += c * disp[k, j, i]
                    w += c
    out[bk, bj, bi] = s / w


@wp.kernel
def upsample_blocks(coarse: wp.array3d(dtype=wp.vec3), coarse_block: int, fine_block: int, fine: wp.array3d(dtype=wp.vec3)):
    """A finer level's blocks start from twice the coarser level's displacement at their centre."""
    bk, bj, bi = wp.tid()
    centre = (wp.vec3(float(bi), float(bj), float(bk)) + wp.vec3(0.5)) * float(fine_block) * 0.5  # coarse voxels
    fine[bk, bj, bi] = 2.0 * trilinear(coarse, centre / float(coarse_block) - wp.vec3(0.5))


@wp.kernel
def shift_centres(
    params: wp.array2d(dtype=float), disp: wp.array3d(dtype=wp.vec3), block: int, size: wp.vec3, turn: int, moved: wp.array(dtype=float)
):
    """mu += the displacement at mu (columns 0-2 of the (N, 12) parameters); ``moved`` = its length.

    A primitive whose structure leaves the grid stays where it is (``moved`` = -1): the inflow
    beside it is new structure to fit, whereas clamping it onto the boundary piled the outflow
    of every timestep up on the faces (measured: a 4-degree turn carries 2.6 % of the primitives
    out a step; a 512^3 chain lost 0.3-0.7 dB a step even with the true motion)."""
    t = wp.tid()
    mu = wp.vec3(params[t, 0], params[t, 1], params[t, 2])
    q = (mu + wp.vec3(0.5)) / float(block) - wp.vec3(0.5)
    d = trilinear(disp, q)
    to = mu + d
    for a in range(3):
        if to[a] < -0.5 or to[a] > size[a] - 0.5:
            moved[t] = -1.0
            return
    for a in range(3):
        params[t, a] = to[a]
    moved[t] = wp.length(d)
    if turn == 0:
        return
    # the local rotation of the motion (half its curl, small angles) turns the primitive's frame too
    h = 0.5
    ex = (trilinear(disp, q + wp.vec3(h, 0.0, 0.0)) - trilinear(disp, q - wp.vec3(h, 0.0, 0.0))) / (2.0 * h * float(block))
    ey = (trilinear(disp, q + wp.vec3(0.0, h, 0.0)) - trilinear(disp, q - wp.vec3(0.0, h, 0.0))) / (2.0 * h * float(block))
    ez = (trilinear(disp, q + wp.vec3(0.0, 0.0, h)) - trilinear(disp, q - wp.vec3(0.0, 0.0, h))) / (2.0 * h * float(block))
    omega = 0.5 * wp.vec3(ey[2] - ez[1], ez[0] - ex[2], ex[1] - ey[0])
    angle = wp.length(omega)
    if angle > 1.0e-6:
        r = wp.quat_from_axis_angle(omega / angle, angle)
        qq = r * wp.quat(params[t, 6], params[t, 7], params[t, 8], params[t, 9])
        for a in range(4):
            params[t, 6 + a] = qq[a]
