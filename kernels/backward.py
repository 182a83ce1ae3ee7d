"""Refinement loss and its closed-form gradients (paper stage S2, SPEC section 3).

Per iteration, with M samples p_s and M partner points p'_s (p_s jittered by about a voxel):

    L_val   = (1/M) sum_s om_s c_s (V~(p_s) - t_s)^2      c_s = 1 occupied, value_empty otherwise
    L_rho   = (1/M) sum_s om_s o_s (rho(p_s) - 1)^2        rho = sum_i w_i G_i (density)
    L_sm    = (1/M) sum_s om_s o_s (rho(p_s) - rho(p'_s))^2
    L_anc   = (1/N) sum_i (a_i - V(mu_i))^2                V(mu_i) trilinear, held constant (cached
                                                           between re-bins with the volume on the host)
    L_aniso = (1/N) sum_i sum_{j<k} relu(|ls_ij - ls_ik| - ln 3)^2
    L_cap   = (1/N) sum_i sum_k relu(ls_ik - ln cap)^2 + relu(ln s_min - ls_ik)^2
    L = L_val + l_rho L_rho + l_sm(t) L_sm + l_anc L_anc + l_aniso L_aniso + l_cap L_cap

Training parameters per primitive: mu(3), log-sigma(3), unnormalised quaternion(4), a, weight
logit (w = sigmoid). The point pass (:func:`point_grads`) turns the forward values into dL/dV~
and dL/drho per point; the pair pass visits exactly the pairs the forward pass visited (same
bins, same ``conic_g``) and accumulates, per primitive in cell order, dL/dmu,
dL/dlog-sigma, dL/dR (3x3), dL/da and dL/dw. Training uses the balanced chunk pass of :mod:`.chunked` (no
float atomics, bit-identical reruns); :func:`accumulate_pairs` (one thread per point scattering
through atomics) is its reference.
:func:`finish_grads` adds the per-primitive terms and chains R(q/|q|) and the sigmoid into the
12 raw gradients.

Derivation of the pair terms (d = p - mu, y = R^T d, m = sum_k y_k^2 / s_k^2, G = exp(-m/2)):
    dG/dmu = G R (y / s^2)          dG/dls_k = G y_k^2 / s_k^2      dG/dR = -G d (y / s^2)^T
    V~ = num / D, D = max(rho, RHO0): dV~/dG_i = w_i (a_i - Vd) / D with Vd = V~ if rho > RHO0
    else 0 (the max has zero slope below the floor); dV~/da_i = w_i G_i / D;
    dV~/dw_i = G_i (a_i - Vd) / D; drho/dG_i = w_i, drho/dw_i = G_i.
"""

import warp as wp

from .analysis import trilinear
from .field import RHO0, BinnedPrimitives, conic_g, in_box, level_cell, neighbour_range, sigmoid, vec12

wp.set_module_options({"enable_backward": False})


@wp.kernel
def point_grads(
    value: wp.array(dtype=float),  # [2M] V~ at samples then partners
    density: wp.array(dtype=float),  # [2M] rho
    target: wp.array(dtype=float),  # [M]
    weight: wp.array(dtype=float),  # [M] 0 excludes a sample (masked voxels near it)
    occupied: wp.array(dtype=float),  # [M] 1 if target > 0.02
    m: int,
    value_empty: float,  # value-loss weight of empty samples (paper: 0)
    l_density: float,
    now: wp.array(dtype=wp.vec4),  # [1] this iteration's schedule; now[0][1] is the smoothness weight
    g_value: wp.array(dtype=float),  # [2M] out: dL/dV~
    g_density: wp.array(dtype=float),  # [2M] out: dL/drho
    loss: wp.array(dtype=wp.vec3),  # [M] out: (value, density, smooth) loss terms of the sample
):
    """dL/dV~ and dL/drho at each sample and its partner (one thread per sample)."""
    s = wp.tid()
    l_smooth = now[0][1]
    om = weight[s]
    o = occupied[s]
    c = wp.where(o > 0.0, 1.0, value_empty)
    inv_m = 1.0 / float(m)
    r = value[s] - target[s]
    dr = density[s] - 1.0
    ds = density[s] - density[m + s]
    g_value[s] = 2.0 * inv_m * om * c * r
    g_density[s] = 2.0 * inv_m * om * o * (l_density * dr + l_smooth * ds)
    g_value[m + s] = 0.0
    g_density[m + s] = -2.0 * inv_m * om * o * l_smooth * ds
    loss[s] = wp.vec3(inv_m * om * c * r * r, l_density * inv_m * om * o * dr * dr, l_smooth * inv_m * om * o * ds * ds)


@wp.func
def point_state(
    i: int,
    value: wp.array(dtype=float),
    density: wp.array(dtype=float),
    g_value: wp.array(dtype=float),
    g_density: wp.array(dtype=float),
) -> wp.vec4:
    """(dL/dV~, dL/drho, D = max(rho, RHO0), Vd) of point i: what every pair of it needs."""
    rho = density[i]
    return wp.vec4(g_value[i], g_density[i], wp.max(rho, RHO0), wp.where(rho > RHO0, value[i], 0.0))


@wp.func
def pair_terms(p: wp.vec3, st: wp.vec4, g: float, mu: wp.vec3, R: wp.mat33, inv: wp.vec3, a: float, w: float):
    """One contributing pair's gradient terms: (k y/s^2, k y^2/s^2, -k d (y/s^2)^T, dL/da, dL/dw)
    with k = dL/dG * G (see the module docstring); zero when the point carries no gradient."""
    gv = st[0]
    gr = st[1]
    dv_dg = (a - st[3]) / st[2]
    kk = w * (gv * dv_dg + gr) * g
    d = p - mu
    yl = wp.transpose(R) @ d
    ys = wp.vec3(yl[0] * inv[0], yl[1] * inv[1], yl[2] * inv[2])
    return (
        kk * ys,
        kk * wp.vec3(yl[0] * ys[0], yl[1] * ys[1], yl[2] * ys[2]),
        -kk * wp.outer(d, ys),
        gv * w * g / st[2],
        g * (gv * dv_dg + gr),
    )


@wp.func
def pair_grad(
    p: wp.vec3,
    j: int,
    prims: BinnedPrimitives,
    st: wp.vec4,  # point_state(): (dL/dV~, dL/drho, D, Vd)
    d_mu: wp.array(dtype=wp.vec3),
    d_ls: wp.array(dtype=wp.vec3),
    d_rot: wp.array(dtype=wp.mat33),
    d_a: wp.array(dtype=float),
    d_w: wp.array(dtype=float),
) -> int:
    """Accumulate one pair's gradient into sorted slot j; returns 1 if the pair contributes."""
    R = prims.rot[j]
    inv = prims.inv_s2[j]
    d = p - prims.mu[j]
    if not in_box(d, prims.ext[j]):
        return 0
    g = conic_g(d, prims.conic[j])
    if not (g > 0.0):
        return 0
    if st[0] != 0.0 or st[1] != 0.0:
        t_ky, t_ls, t_rot, t_a, t_w = pair_terms(p, st, g, prims.mu[j], R, inv, prims.a[j], prims.w[j])
        wp.atomic_add(d_mu, j, R @ t_ky)
        wp.atomic_add(d_ls, j, t_ls)
        wp.atomic_add(d_rot, j, t_rot)
        wp.atomic_add(d_a, j, t_a)
        wp.atomic_add(d_w, j, t_w)
    return 1


@wp.kernel
def accumulate_pairs(
    points: wp.array(dtype=wp.vec3),  # [P]
    value: wp.array(dtype=float),  # [P] forward V~
    density: wp.array(dtype=float),  # [P] forward rho
    g_value: wp.array(dtype=float),  # [P]
    g_density: wp.array(dtype=float),  # [P]
    prims: BinnedPrimitives,
    d_mu: wp.array(dtype=wp.vec3),  # [N] out (cell order, zeroed before): dL/dmu
    d_ls: wp.array(dtype=wp.vec3),  # [N] out: dL/dlog-sigma
    d_rot: wp.array(dtype=wp.mat33),  # [N] out: dL/dR
    d_a: wp.array(dtype=float),  # [N] out: dL/da
    d_w: wp.array(dtype=float),  # [N] out: dL/dw (activated weight)
    pairs: wp.array(dtype=int),  # [P] out: contributing pairs visited
):
    """Scatter each point's loss gradient onto the primitives it touches (one thread per point)."""
    i = wp.tid()
    p = points[i]
    st = point_state(i, value, density, g_value, g_density)
    n = int(0)
    for l in range(prims.level_size.shape[0]):
        c = level_cell(p, prims.level_size[l], prims.level_dims[l])
        for nb in range(27):
            r = neighbour_range(prims, l, c, nb)
            for j in range(r[0], r[1]):
                n += pair_grad(p, j, prims, st, d_mu, d_ls, d_rot, d_a, d_w)
    pairs[i] = n


@wp.kernel
def accumulate_pairs_dense(
    points: wp.array(dtype=wp.vec3),
    value: wp.array(dtype=float),
    density: wp.array(dtype=float),
    g_value: wp.array(dtype=float),
    g_density: wp.array(dtype=float),
    prims: BinnedPrimitives,
    d_mu: wp.array(dtype=wp.vec3),
    d_ls: wp.array(dtype=wp.vec3),
    d_rot: wp.array(dtype=wp.mat33),
    d_a: wp.array(dtype=float),
    d_w: wp.array(dtype=float),
    pairs: wp.array(dtype=int),
):
    """Reference for :func:`accumulate_pairs`: every primitive against every point (self-test)."""
    i = wp.tid()
    p = points[i]
    st = point_state(i, value, density, g_value, g_density)
    n = int(0)
    for j in range(prims.mu.shape[0]):
        n += pair_grad(p, j, prims, st, d_mu, d_ls, d_rot, d_a, d_w)
    pairs[i] = n


@wp.func
def relu(x: float) -> float:
    return wp.max(x, 0.0)


@wp.func
def raw_gradient(
    p: vec12,  # raw training parameters of the primitive
    gm: wp.vec3,  # accumulated pair gradients: dL/dmu
    gl: wp.vec3,  # dL/dlog-sigma
    gR: wp.mat33,  # dL/dR
    g_a: float,  # dL/da
    g_w: float,  # dL/dw
    v_mu: float,  # the anchor target: V at the centre (anchor_target)
    l_anchor: float,
    l_aniso: float,
    l_cap: float,
    log_aniso: float,
    log_cap: float,
    log_min: float,
    inv_n: float,  # 1 / N
):
    """Per-primitive loss terms and the chain rule to the 12 raw parameters.

    Returns:
        (gradient, (anchor, aniso, cap) loss terms of the primitive).
    """
    # quaternion: R(qh) with qh = q / |q|, Warp's (x, y, z, w) order
    qn2 = p[6] * p[6] + p[7] * p[7] + p[8] * p[8] + p[9] * p[9]
    qn = wp.sqrt(wp.max(qn2, 1.0e-20))
    if not wp.isfinite(qn2):  # |q| beyond 1.8e19: scale before squaring, as safe_unit_quat does
        big = wp.max(wp.max(wp.abs(p[6]), wp.abs(p[7])), wp.max(wp.abs(p[8]), wp.abs(p[9])))
        u = wp.vec4(p[6] / big, p[7] / big, p[8] / big, p[9] / big)
        qn = big * wp.length(u)
    x = p[6] / qn
    y = p[7] / qn
    z = p[8] / qn
    w = p[9] / qn
    gx = 2.0 * (
        gR[0, 1] * y + gR[0, 2] * z + gR[1, 0] * y - 2.0 * gR[1, 1] * x - gR[1, 2] * w + gR[2, 0] * z + gR[2, 1] * w - 2.0 * gR[2, 2] * x
    )
    gy = 2.0 * (
        -2.0 * gR[0, 0] * y + gR[0, 1] * x + gR[0, 2] * w + gR[1, 0] * x + gR[1, 2] * z - gR[2, 0] * w + gR[2, 1] * z - 2.0 * gR[2, 2] * y
    )
    gz = 2.0 * (
        -2.0 * gR[0, 0] * z - gR[0, 1] * w + gR[0, 2] * x + gR[1, 0] * w - 2.0 * gR[1, 1] * z + gR[1, 2] * y + gR[2, 0] * x + gR[2, 1] * y
    )
    gw = 2.0 * (-gR[0, 1] * z + gR[0, 2] * y + gR[1, 0] * z - gR[1, 2] * x - gR[2, 0] * y + gR[2, 1] * x)
    radial = x * gx + y * gy + z * gz + w * gw
    # per-primitive terms on the log-scales
    ls = wp.vec3(p[3], p[4], p[5])
    l_an = float(0.0)
    l_cp = float(0.0)
    for a_ in range(3):
        hi = relu(ls[a_] - log_cap)
        lo = relu(log_min - ls[a_])
        l_cp += hi * hi + lo * lo
        gl[a_] = gl[a_] + l_cap * inv_n * 2.0 * (hi - lo)
        for b_ in range(a_ + 1, 3):
            diff = ls[a_] - ls[b_]
            ex = relu(wp.abs(diff) - log_aniso)
            l_an += ex * ex
            gd = l_aniso * inv_n * 2.0 * ex * wp.sign(diff)
            gl[a_] = gl[a_] + gd
            gl[b_] = gl[b_] - gd
    anchor = p[10] - v_mu
    sw = sigmoid(p[11])
    out = vec12()
    out[0] = gm[0]
    out[1] = gm[1]
    out[2] = gm[2]
    out[3] = gl[0]
    out[4] = gl[1]
    out[5] = gl[2]
    out[6] = (gx - x * radial) / qn
    out[7] = (gy - y * radial) / qn
    out[8] = (gz - z * radial) / qn
    out[9] = (gw - w * radial) / qn
    out[10] = g_a + l_anchor * inv_n * 2.0 * anchor
    out[11] = g_w * sw * (1.0 - sw)
    reg = wp.vec3(l_anchor * inv_n * anchor * anchor, l_aniso * inv_n * l_an, l_cap * inv_n * l_cp)
    return out, reg


@wp.func
def anchor_target(vol: wp.array3d(dtype=float), anchors: wp.array(dtype=float), cached: int, j: int, p: vec12) -> float:
    """The anchor term's V(mu) of slot j: the volume at the centre of parameters ``p`` or, with
    ``cached``, the value :func:`warpgauss.kernels.optim.anchor_targets` stored at the last re-bin
    (a volume in host memory: the read would cross the bus for every touched slot every iteration)."""
    if cached != 0:
        return anchors[j]
    return trilinear(vol, wp.vec3(p[0], p[1], p[2]))


@wp.func
def touched(j: int, d_mu: wp.array(dtype=wp.vec3), d_a: wp.array(dtype=float), d_w: wp.array(dtype=float)) -> bool:
    """Whether any pair reached slot j this iteration (all its pair gradients are exactly 0 if not)."""
    return d_w[j] != 0.0 or d_a[j] != 0.0 or wp.length_sq(d_mu[j]) != 0.0


@wp.kernel
def finish_grads(
    params: wp.array(dtype=vec12),  # [N] raw training parameters, slot order
    d_mu: wp.array(dtype=wp.vec3),  # [N] slot order
    d_ls: wp.array(dtype=wp.vec3),
    d_rot: wp.array(dtype=wp.mat33),
    d_a: wp.array(dtype=float),
    d_w: wp.array(dtype=float),
    vol: wp.array3d(dtype=float),  # the normalised field, for the anchor targets
    anchors: wp.array(dtype=float),  # [N] the targets stored at the last re-bin (cached only)
    cached: int,  # 1: the anchor targets from anchors (anchor_target)
    l_anchor: float,
    l_aniso: float,
    l_cap: float,
    log_aniso: float,
    log_cap: float,
    log_min: float,
    grad: wp.array(dtype=vec12),  # [N] out: dL/d(raw parameters), slot order
    reg_loss: wp.array(dtype=wp.vec3),  # [N] out: (anchor, aniso, cap) loss terms of the primitive
):
    """:func:`raw_gradient` of every slot (tests, self-test and loss reports; training fuses it
    into :func:`warpgauss.kernels.optim.refine_update`).

    A primitive no sample touched this iteration gets an all-zero gradient (its per-primitive
    terms included), which Adam treats as "not visible" (sparse Adam).
    """
    j = wp.tid()
    g, reg = raw_gradient(
        params[j],
        d_mu[j],
        d_ls[j],
        d_rot[j],
        d_a[j],
        d_w[j],
        anchor_target(vol, anchors, cached, j, params[j]),
        l_anchor,
        l_aniso,
        l_cap,
        log_aniso,
        log_cap,
        log_min,
        1.0 / float(params.shape[0]),
    )
    reg_loss[j] = reg
    if touched(j, d_mu, d_a, d_w):
        grad[j] = g
    else:
        grad[j] = vec12()
