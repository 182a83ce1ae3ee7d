"""float64 numpy twin of the refinement loss and its closed-form gradient (SPEC sections 2-3).

Used only by the tests: the Warp refinement kernels are checked against `analytic_gradient`, which is
itself checked against central finite differences (`numeric_gradient`) of `loss_terms`.

Raw training parameters, one row of `raw` (N, 12) per primitive::

    mu (3) | ls (3) log-sigmas | q (4) UNnormalised quaternion (x, y, z, w) | a | wl (weight logit)

with ``w = sigmoid(wl)``, ``s = exp(ls)``, ``qhat = q / |q|``, ``R = quat_to_matrix(qhat)``,
``Sigma = R diag(s^2) R^T``.  For a sample point p and primitive i::

    d = p - mu_i,   y = R^T d,   z = S^-2 y  (z_k = y_k exp(-2 ls_k)),   m = d^T Sigma^-1 d = y . z
    G_i(p) = exp(-m / 2) if m < 25 else 0
    rho(p) = sum_i w_i G_i(p),   num(p) = sum_i w_i a_i G_i(p),   Vt(p) = num(p) / max(rho(p), 0.05)

Loss (M samples, N primitives; omega_s = weight, o_s = occupied, p'_s = partners[s])::

    L_val   = (1/M) sum_s omega_s c_s (Vt(p_s) - t_s)^2,     c_s = 1 if o_s else lam["value_empty"]
    L_rho   = (1/M) sum_s omega_s o_s (rho(p_s) - 1)^2
    L_sm    = (1/M) sum_s omega_s o_s (rho(p_s) - rho(p'_s))^2
    L_anc   = (1/N) sum_i (a_i - anchor_target_i)^2            (anchor_target = V(mu_i), a constant)
    L_aniso = (1/N) sum_i sum_{j<k} relu(|ls_ij - ls_ik| - log_aniso)^2
    L_cap   = (1/N) sum_i sum_k [relu(ls_ik - log_cap)^2 + relu(log_min - ls_ik)^2]
    L = L_val + lam.density L_rho + lam.smooth L_sm + lam.anchor L_anc + lam.aniso L_aniso + lam.cap L_cap

`lam` is a dict with the float keys ``value_empty, density, smooth, anchor, aniso, cap, log_cap,
log_min, log_aniso``.  M is ``len(points)`` (samples with omega_s = 0 still count in the 1/M).

Conventions of the closed form (the Warp kernels must follow the same ones):
- the truncation indicator [m < 25] is a constant (its derivative, a delta on the 5-sigma shell, is
  dropped); finite-difference tests must avoid samples with m near 25 (see `mahalanobis`);
- d max(rho, rho0) / d rho = 1 if rho > rho0 else 0 (so for rho <= rho0 the value term still
  depends on the parameters through num, but not through rho);
- relu'(x) = 1 if x > 0 else 0, d|x|/dx = sign(x).
"""

from __future__ import annotations

import numpy as np

from .field_ref import RHO0, TRUNC_M2, quat_to_matrix

TERMS = ("value", "density", "smooth", "anchor", "aniso", "cap")
_PAIRS = ((0, 1), (0, 2), (1, 2))  # the j < k axis pairs of the anisotropy penalty


def _sigmoid(x: np.ndarray) -> np.ndarray:
    # numerically stable logistic: exp never overflows
    e = np.exp(-np.abs(x))
    return np.where(x >= 0, 1.0 / (1.0 + e), e / (1.0 + e))


def _relu(x: np.ndarray) -> np.ndarray:
    return np.maximum(x, 0.0)


def _unpack(raw: np.ndarray):
    raw = np.asarray(raw, np.float64)
    if raw.ndim != 2 or raw.shape[1] != 12:
        raise ValueError(f"raw must be (N, 12), got {raw.shape}")
    mu, ls, q, a, wl = raw[:, 0:3], raw[:, 3:6], raw[:, 6:10], raw[:, 10], raw[:, 11]
    return mu, ls, q, a, wl


def _pairs(raw: np.ndarray, points: np.ndarray) -> dict:
    """Per-pair geometry of every (sample, primitive) pair, shapes (M, N[, 3])."""
    mu, ls, q, _, _ = _unpack(raw)
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    R = quat_to_matrix(q)  # normalises q inside: R = R(q / |q|)
    inv_s2 = np.exp(-2.0 * ls)  # (N, 3) = diag(S^-2)
    d = pts[:, None, :] - mu[None, :, :]  # (M, N, 3)
    y = np.einsum("nji,mnj->mni", R, d)  # y = R^T d, coordinates in the primitive's frame
    z = y * inv_s2[None]  # z = S^-2 y, so Sigma^-1 d = R z
    m = np.einsum("mni,mni->mn", y, z)  # m = y^T S^-2 y = d^T Sigma^-1 d
    inside = m < TRUNC_M2
    G = np.where(inside, np.exp(-0.5 * np.minimum(m, TRUNC_M2)), 0.0)
    return {"R": R, "d": d, "y": y, "z": z, "m": m, "G": G}


def mahalanobis(raw: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(M, N) squared Mahalanobis distance m of every (point, primitive) pair.

    Tests drop samples with |m - 25| small for any primitive: there the hard 5-sigma cut makes the
    loss discontinuous and finite differences meaningless.
    """
    return _pairs(raw, points)["m"]


def _forward(raw, points, partners, target, weight, occupied, anchor_target, lam) -> dict:
    mu, ls, q, a, wl = _unpack(raw)
    n = mu.shape[0]
    w = _sigmoid(wl)
    P = _pairs(raw, points)
    Pp = _pairs(raw, partners)
    rho = P["G"] @ w  # (M,)
    num = P["G"] @ (w * a)
    D = np.maximum(rho, RHO0)
    vt = num / D
    rho_p = Pp["G"] @ w  # density at the partners (only the density is needed there)

    t = np.asarray(target, np.float64)
    om = np.asarray(weight, np.float64)
    occ = np.asarray(occupied, bool)
    o = occ.astype(np.float64)
    c = np.where(occ, 1.0, float(lam["value_empty"]))
    M = rho.shape[0]
    anc = np.asarray(anchor_target, np.float64)

    l_val = np.sum(om * c * (vt - t) ** 2) / M
    l_rho = np.sum(om * o * (rho - 1.0) ** 2) / M
    l_sm = np.sum(om * o * (rho - rho_p) ** 2) / M
    l_anc = np.sum((a - anc) ** 2) / n
    l_aniso = sum(np.sum(_relu(np.abs(ls[:, j] - ls[:, k]) - lam["log_aniso"]) ** 2) for j, k in _PAIRS) / n
    l_cap = np.sum(_relu(ls - lam["log_cap"]) ** 2 + _relu(lam["log_min"] - ls) ** 2) / n

    terms = {
        "value": float(l_val),
        "density": float(lam["density"] * l_rho),
        "smooth": float(lam["smooth"] * l_sm),
        "anchor": float(lam["anchor"] * l_anc),
        "aniso": float(lam["aniso"] * l_aniso),
        "cap": float(lam["cap"] * l_cap),
    }
    terms["total"] = float(sum(terms[k] for k in TERMS))
    return {
        "terms": terms,
        "P": P,
        "Pp": Pp,
        "w": w,
        "a": a,
        "ls": ls,
        "q": q,
        "rho": rho,
        "num": num,
        "D": D,
        "vt": vt,
        "rho_p": rho_p,
        "t": t,
        "om": om,
        "o": o,
        "c": c,
        "anc": anc,
        "M": M,
        "n": n,
    }


def loss_terms(raw, points, partners, target, weight, occupied, anchor_target, lam) -> dict:
    """{"value", "density", "smooth", "anchor", "aniso", "cap", "total"} as floats.

    Every term except "value" is already multiplied by its lambda; "total" is their sum.
    """
    return _forward(raw, points, partners, target, weight, occupied, anchor_target, lam)["terms"]


def numeric_gradient(raw, *args, h: float = 1e-6, **kw) -> np.ndarray:
    """(N, 12) central differences (L(x + h) - L(x - h)) / 2h of loss_terms(raw, *args, **kw)["total"]."""
    raw = np.array(raw, np.float64)
    g = np.zeros_like(raw)
    for idx in np.ndindex(*raw.shape):
        x0 = raw[idx]
        raw[idx] = x0 + h
        lp = loss_terms(raw, *args, **kw)["total"]
        raw[idx] = x0 - h
        lm = loss_terms(raw, *args, **kw)["total"]
        raw[idx] = x0
        g[idx] = (lp - lm) / (2.0 * h)
    return g


# dR/dq_c of the rotation matrix of field_ref.quat_to_matrix, for a unit quaternion (x, y, z, w):
#   R = [[1-2(y^2+z^2), 2(xy-zw),     2(xz+yw)    ],
#        [2(xy+zw),     1-2(x^2+z^2), 2(yz-xw)    ],
#        [2(xz-yw),     2(yz+xw),     1-2(x^2+y^2)]]
def _dR_dq(qh: np.ndarray) -> np.ndarray:
    """(N, 4, 3, 3): derivative of R(qhat) w.r.t. each component of qhat (x, y, z, w order)."""
    x, y, z, w = qh.T
    o = np.zeros_like(x)

    def mat(*rows):
        return np.stack([np.stack(r, -1) for r in rows], -2)  # (N, 3, 3)

    dx = mat((o, 2 * y, 2 * z), (2 * y, -4 * x, -2 * w), (2 * z, 2 * w, -4 * x))
    dy = mat((-4 * y, 2 * x, 2 * w), (2 * x, o, 2 * z), (-2 * w, 2 * z, -4 * y))
    dz = mat((-4 * z, -2 * w, 2 * x), (2 * w, -4 * z, 2 * y), (2 * x, 2 * y, o))
    dw = mat((o, -2 * z, 2 * y), (2 * z, o, -2 * x), (-2 * y, 2 * x, o))
    return np.stack([dx, dy, dz, dw], axis=1)


def _geometry_backward(P: dict, gG: np.ndarray):
    """Back-propagate dL/dG (M, N) of one point set through G(mu, ls, R).

    With k = dL/dG * G (pair-wise) and the pair quantities d, y = R^T d, z = S^-2 y:
      m = y^T S^-2 y, dm/dd = 2 Sigma^-1 d = 2 R z, and dG = -G/2 dm:
      dG/dmu   = -G/2 * dm/dd * (dd/dmu = -I) = G Sigma^-1 d = G R z
      dG/dls_k = -G/2 * dm/dls_k = -G/2 * (-2 y_k^2 exp(-2 ls_k)) = G y_k z_k
      dG/dR    : y_k = sum_j R_jk d_j, dm/dy = 2 z  =>  dm/dR_jk = 2 d_j z_k, dG/dR = -G d z^T
    The truncation indicator [m < 25] is treated as a constant (G = 0 there, so k = 0: no gradient).
    Returns (dL/dmu (N,3), dL/dls (N,3), dL/dR (N,3,3)).
    """
    k = gG * P["G"]  # (M, N)
    g_mu = np.einsum("mn,nij,mnj->ni", k, P["R"], P["z"])  # sum_s k R z
    g_ls = np.einsum("mn,mni->ni", k, P["y"] * P["z"])  # sum_s k y_k z_k
    g_R = -np.einsum("mn,mnj,mnk->njk", k, P["d"], P["z"])  # -sum_s k d z^T
    return g_mu, g_ls, g_R


def analytic_gradient(raw, points, partners, target, weight, occupied, anchor_target, lam) -> np.ndarray:
    """(N, 12) closed-form float64 gradient of loss_terms(...)["total"] w.r.t. raw.

    Derivation (per sample s; all sums over samples also include the 1/M):
      value:   dL/dVt_s   = 2/M omega c (Vt - t)
               Vt = num / D, D = max(rho, rho0):
               dL/dnum_s  = dL/dVt_s / D
               dL/drho_s += -dL/dVt_s * Vt / D * [rho > rho0]     (max has zero slope below rho0)
      density: dL/drho_s += lam.density * 2/M omega o (rho - 1)
      smooth:  dL/drho_s += lam.smooth * 2/M omega o (rho - rho'),  dL/drho'_s = -(the same)
      mixture: num = sum_i w_i a_i G_i, rho = sum_i w_i G_i, rho' = sum_i w_i G'_i
               dL/dG_si  = dL/dnum_s w_i a_i + dL/drho_s w_i,   dL/dG'_si = dL/drho'_s w_i
               dL/da_i   = sum_s dL/dnum_s w_i G_si  (+ anchor: lam.anchor * 2/N (a_i - V(mu_i)))
               dL/dw_i   = sum_s [dL/dnum_s a_i + dL/drho_s] G_si + dL/drho'_s G'_si
               dL/dwl_i  = dL/dw_i * w_i (1 - w_i)                   (sigmoid)
      geometry: see _geometry_backward, applied to the points and to the partners and summed.
      rotation: dL/dqhat_c = sum_jk dL/dR_jk dR_jk/dqhat_c; qhat = q/|q| has the Jacobian
               (I - qhat qhat^T) / |q|, so dL/dq = (g - qhat (qhat . g)) / |q| with g = dL/dqhat.
      aniso:   r = relu(|ls_j - ls_k| - log_aniso): dL/dls_j += lam.aniso/N 2 r sign(ls_j - ls_k),
               dL/dls_k -= the same.
      cap:     dL/dls += lam.cap/N (2 relu(ls - log_cap) - 2 relu(log_min - ls)).
    """
    f = _forward(raw, points, partners, target, weight, occupied, anchor_target, lam)
    M, n = f["M"], f["n"]
    w, a, ls, q = f["w"], f["a"], f["ls"], f["q"]
    rho, D, vt, rho_p = f["rho"], f["D"], f["vt"], f["rho_p"]
    om, o, c, t = f["om"], f["o"], f["c"], f["t"]

    # --- per-sample upstream gradients ---
    g_vt = 2.0 / M * om * c * (vt - t)
    g_num = g_vt / D
    g_rho = np.where(rho > RHO0, -g_vt * vt / D, 0.0)
    g_rho = g_rho + lam["density"] * 2.0 / M * om * o * (rho - 1.0)
    g_sm = lam["smooth"] * 2.0 / M * om * o * (rho - rho_p)
    g_rho = g_rho + g_sm
    g_rho_p = -g_sm

    # --- mixture ---
    G, Gp = f["P"]["G"], f["Pp"]["G"]
    g_a = w * (g_num @ G) + lam["anchor"] * 2.0 / n * (a - f["anc"])
    g_w = a * (g_num @ G) + g_rho @ G + g_rho_p @ Gp
    g_wl = g_w * w * (1.0 - w)

    # --- geometry (points and partners) ---
    gG = g_num[:, None] * (w * a)[None, :] + g_rho[:, None] * w[None, :]
    gGp = g_rho_p[:, None] * w[None, :]
    g_mu, g_ls, g_R = _geometry_backward(f["P"], gG)
    g_mu2, g_ls2, g_R2 = _geometry_backward(f["Pp"], gGp)
    g_mu, g_ls, g_R = g_mu + g_mu2, g_ls + g_ls2, g_R + g_R2

    # --- rotation: R(qhat), qhat = q / |q| ---
    qn = np.linalg.norm(q, axis=1, keepdims=True)
    qh = q / qn
    g_qh = np.einsum("njk,ncjk->nc", g_R, _dR_dq(qh))
    g_q = (g_qh - qh * np.sum(qh * g_qh, axis=1, keepdims=True)) / qn

    # --- regularisers on the log-sigmas ---
    for j, k in _PAIRS:
        diff = ls[:, j] - ls[:, k]
        r = _relu(np.abs(diff) - lam["log_aniso"])
        gd = lam["aniso"] / n * 2.0 * r * np.sign(diff)
        g_ls[:, j] += gd
        g_ls[:, k] -= gd
    g_ls = g_ls + lam["cap"] / n * (2.0 * _relu(ls - lam["log_cap"]) - 2.0 * _relu(lam["log_min"] - ls))

    out = np.empty((n, 12), np.float64)
    out[:, 0:3] = g_mu
    out[:, 3:6] = g_ls
    out[:, 6:10] = g_q
    out[:, 10] = g_a
    out[:, 11] = g_wl
    return out
