"""The float64 reference loss: closed-form gradient against central finite differences."""

from __future__ import annotations

import numpy as np
import pytest
from reference.field_ref import RHO0
from reference.field_ref import field as field_ref
from reference.loss_ref import TERMS, analytic_gradient, loss_terms, mahalanobis, numeric_gradient

SHELL = 0.5  # drop samples with |m - 25| < SHELL for any primitive, at the points or the partners
KINK = 1e-3  # drop samples with |rho - rho0| < KINK (the max() kink of the value term)
RTOL = 1e-6  # relative to max |grad|

LAM_ALL = {
    "value_empty": 0.3,
    "density": 0.7,
    "smooth": 1.3,
    "anchor": 0.5,
    "aniso": 2.0,
    "cap": 1.5,
    "log_cap": float(np.log(2.0)),
    "log_min": float(np.log(0.9)),
    "log_aniso": float(np.log(3.0)),
}
SWITCHES = ("density", "smooth", "anchor", "aniso", "cap")


def _lam(**on) -> dict:
    lam = dict(LAM_ALL)
    for k in SWITCHES:
        lam[k] = on.get(k, 0.0)
    return lam


LAM_VALUE = _lam()  # value term only


def _scene(seed: int = 0, n: int = 12, m: int = 200):
    """Rotated anisotropic primitives in a 10^3 box with low weights; half the samples near centres
    (dense, rho > rho0), half uniform over a box a little larger than the primitives' (sparse)."""
    rng = np.random.default_rng(seed)
    raw = np.zeros((n, 12))
    raw[:, 0:3] = rng.uniform(1.5, 8.5, (n, 3))
    raw[:, 3:6] = rng.uniform(-0.2, 0.8, (n, 3))
    # a few strongly anisotropic ones so that |ls_j - ls_k| > ln 3 somewhere (the aniso penalty bites)
    raw[:3, 3:6] = [[-0.5, 0.3, 0.9], [0.8, -0.4, 0.1], [0.0, 1.0, -0.3]]
    q = rng.normal(size=(n, 4))
    raw[:, 6:10] = q / np.linalg.norm(q, axis=1, keepdims=True) * rng.uniform(0.5, 2.0, (n, 1))  # not unit
    raw[:, 10] = rng.uniform(0.0, 1.0, n)
    raw[:, 11] = rng.uniform(-4.0, 0.5, n)  # w in ~[0.02, 0.62]: low weights, sparse tails
    h = m // 2
    near = raw[rng.integers(0, n, h), 0:3] + rng.normal(0.0, 1.0, (h, 3))
    far = rng.uniform(-3.0, 13.0, (m - h, 3))
    points = np.concatenate([near, far])
    partners = points + rng.uniform(-1.0, 1.0, (m, 3))  # within one voxel
    target = np.where(rng.random(m) < 0.3, rng.uniform(0.0, 0.02, m), rng.uniform(0.02, 1.0, m))
    weight = (rng.random(m) < 0.85).astype(np.float64)
    occupied = target > 0.02
    anchor_target = rng.uniform(0.0, 1.0, n)

    # drop samples on the 5-sigma shell (points and partners) and on the max(rho, rho0) kink
    keep = (np.abs(mahalanobis(raw, points) - 25.0) >= SHELL).all(1)
    keep &= (np.abs(mahalanobis(raw, partners) - 25.0) >= SHELL).all(1)
    w = 1.0 / (1.0 + np.exp(-raw[:, 11]))
    g = np.where(mahalanobis(raw, points) < 25.0, np.exp(-0.5 * mahalanobis(raw, points)), 0.0)
    keep &= np.abs(g @ w - RHO0) >= KINK
    args = (points[keep], partners[keep], target[keep], weight[keep], occupied[keep], anchor_target)
    return raw, args


@pytest.fixture(scope="module")
def scene():
    raw, args = _scene()
    assert len(args[0]) >= 60  # enough samples survive the shell filter
    return raw, args


def _rho(raw, pts):
    m = mahalanobis(raw, pts)
    w = 1.0 / (1.0 + np.exp(-raw[:, 11]))
    return np.where(m < 25.0, np.exp(-0.5 * m), 0.0) @ w


def _check(raw, args, lam):
    ga = analytic_gradient(raw, *args, lam)
    gn = numeric_gradient(raw, *args, lam)
    scale = np.abs(gn).max()
    assert scale > 1e-6
    np.testing.assert_allclose(ga, gn, rtol=0, atol=RTOL * scale)
    return ga, gn


def test_scene_covers_both_sides_of_rho0(scene):
    raw, args = scene
    points, _, _, weight, occupied, _ = args
    rho = _rho(raw, points)
    live = weight > 0
    assert (live & (rho < RHO0)).sum() >= 5  # sparse samples: Vt = num / rho0
    assert (live & (rho > RHO0)).sum() >= 5  # dense samples: Vt = num / rho
    assert (live & (rho < RHO0) & (rho > 0)).sum() >= 1  # below rho0 but still inside some primitive
    assert (live & occupied & (rho > RHO0)).sum() >= 5


def test_forward_matches_field_ref(scene):
    raw, args = scene
    points = args[0]
    params = raw.copy()
    params[:, 6:10] /= np.linalg.norm(params[:, 6:10], axis=1, keepdims=True)
    params[:, 11] = 1.0 / (1.0 + np.exp(-raw[:, 11]))
    vt, rho, _ = field_ref(params, points)
    np.testing.assert_allclose(_rho(raw, points), rho, rtol=1e-12, atol=1e-14)
    # the value term recomputed from field_ref
    _, _, target, weight, occupied, _ = args
    c = np.where(occupied, 1.0, LAM_VALUE["value_empty"])
    expect = np.sum(weight * c * (vt - target) ** 2) / len(points)
    assert loss_terms(raw, *args, LAM_VALUE)["value"] == pytest.approx(expect, rel=1e-12)


def test_loss_invariant_to_quaternion_scale_and_q_gradient_tangent(scene):
    raw, args = scene
    scaled = raw.copy()
    scaled[:, 6:10] *= 3.7
    a, b = loss_terms(raw, *args, LAM_ALL), loss_terms(scaled, *args, LAM_ALL)
    for k in (*TERMS, "total"):
        assert a[k] == pytest.approx(b[k], rel=1e-12, abs=1e-15)
    g = analytic_gradient(raw, *args, LAM_ALL)
    radial = np.sum(g[:, 6:10] * raw[:, 6:10], axis=1)
    assert np.abs(radial).max() <= 1e-12 * np.abs(g).max()


def test_value_term_alone(scene):
    raw, args = scene
    t = loss_terms(raw, *args, LAM_VALUE)
    assert t["value"] > 0 and all(t[k] == 0 for k in SWITCHES)
    ga, _ = _check(raw, args, LAM_VALUE)
    # every parameter group carries gradient
    for sl in (slice(0, 3), slice(3, 6), slice(6, 10), slice(10, 11), slice(11, 12)):
        assert np.abs(ga[:, sl]).max() > 1e-6


def test_value_gradient_at_sparse_samples_only(scene):
    """Only samples with rho < rho0: the gradient flows through num alone (d max / d rho = 0)."""
    raw, args = scene
    points = args[0]
    sparse = _rho(raw, points) < RHO0
    sub = tuple(x[sparse] for x in args[:5]) + (args[5],)
    assert loss_terms(raw, *sub, LAM_VALUE)["value"] > 0
    _check(raw, sub, LAM_VALUE)


@pytest.mark.parametrize("term", SWITCHES)
def test_each_term_alone(scene, term):
    """Gradient of `term` alone = gradient(value + term) - gradient(value): analytic vs numeric."""
    raw, args = scene
    lam = _lam(**{term: LAM_ALL[term]})
    t = loss_terms(raw, *args, lam)
    assert t[term] > 0
    assert all(t[k] == 0 for k in SWITCHES if k != term)
    ga, gn = _check(raw, args, lam)
    ga0 = analytic_gradient(raw, *args, LAM_VALUE)
    gn0 = numeric_gradient(raw, *args, LAM_VALUE)
    da, dn = ga - ga0, gn - gn0
    scale = np.abs(dn).max()
    assert scale > 1e-6
    np.testing.assert_allclose(da, dn, rtol=0, atol=RTOL * scale)


def test_all_terms_together(scene):
    raw, args = scene
    t = loss_terms(raw, *args, LAM_ALL)
    assert all(t[k] > 0 for k in TERMS)
    assert t["total"] == pytest.approx(sum(t[k] for k in TERMS), rel=1e-14)
    _check(raw, args, LAM_ALL)


@pytest.mark.parametrize("seed", [1, 2])
def test_all_terms_other_scenes(seed):
    raw, args = _scene(seed, n=16, m=160)
    _check(raw, args, LAM_ALL)
