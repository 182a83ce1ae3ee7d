"""Relocation at fixed N (issue #53): dead primitives move to where the error is, off by default."""

from __future__ import annotations

import math

import numpy as np
import pytest

from warpgauss.encoding.refine import RefineConfig, Refiner
from warpgauss.errors import WarpgaussError
from warpgauss.field.analysis import DeviceVolume, normalise

N = 40
DEAD = np.array([3, 7, 11, 19, 23, 31])  # model indices made dead
DEAD_W = np.array([1e-5, 1e-4, 1e-3, 2e-3, 4e-3, 8e-3])  # logits -11.5 .. -4.8, all below logit(0.02) = -3.9


def _field():
    from warpgauss.readers.synthetic import generate

    return normalise(generate("vortex", 16, seed=1))


def _params(f, dead: bool = True) -> np.ndarray:
    rng = np.random.default_rng(0)
    p = np.zeros((N, 12), np.float32)
    p[:, :3] = rng.uniform(0, 1, (N, 3)) * (np.array(f.shape_xyz) - 1)
    p[:, 3:6], p[:, 9], p[:, 10], p[:, 11] = 0.8, 1.0, 0.5, 0.5
    if dead:
        p[DEAD, 11] = DEAD_W
    return p


def _refiner(cpu, f=None, params=None, seed=0, **cfg) -> Refiner:
    f = _field() if f is None else f
    params = _params(f) if params is None else params
    return Refiner(DeviceVolume(f, cpu), params, RefineConfig(**{"iterations": 40, "samples": 256, **cfg}), seed, 0.3, 4.0)


def _run(cpu, **cfg) -> Refiner:
    r = _refiner(cpu, **cfg)
    r.run(log_every=40)
    return r


def _sigmoid(x):
    return 1.0 / (1.0 + np.exp(-x.astype(np.float64)))


def test_relocation_off_is_the_run_without_it(cpu, monkeypatch):
    """relocate_every 0 (the default) gives the bytes of a run whose refiner has no relocation
    at all, whatever the other relocation settings; the settings stay out of to_dict()."""
    base = _run(cpu).model_params()
    off = _run(cpu, relocate_every=0, relocate_weight=0.9, relocate_share=1.0, relocate_until=1.0)
    assert off.relocations == []
    assert base.tobytes() == off.model_params().tobytes()
    # the refiner as it was before relocation existed: the step never asks, nothing to relocate with
    monkeypatch.setattr(Refiner, "relocating", lambda self, it: False)
    monkeypatch.setattr(Refiner, "relocate", lambda self, rebin=True: pytest.fail("relocated"))
    assert base.tobytes() == _run(cpu).model_params().tobytes()
    assert not any(k.startswith("relocate") for k in RefineConfig().to_dict())
    assert RefineConfig(relocate_every=5).to_dict()["relocate_every"] == 5


def test_dead_primitives_move_to_the_error(cpu):
    """After 11 iterations, a relocation moves the lowest-weight dead primitives (at most
    ceil(share x N)) into bricks the error quota draws, isotropic, unrotated, at weight 0.5, with
    their voxel's value, their moments and reach zeroed; every other slot keeps its state."""
    f = _field()
    r = _refiner(cpu, f, relocate_share=0.1)
    for _ in range(11):  # through the re-bin at iteration 10, which draws the error quota
        r.step()
    s = r.state
    before = r.raw_params()
    w = _sigmoid(before[:, 11])
    dead = np.flatnonzero(w < 0.02)
    assert set(dead) == set(DEAD)  # the dead stayed dead and no live one died
    most = math.ceil(0.1 * N)
    want = dead[np.argsort(w[dead], kind="stable")][:most]
    s.m1.fill_(1.0)  # every slot's moments and reach set, so that the zeroing shows
    s.m2.fill_(1.0)
    s.reach.fill_(1.0)
    quota = r.sampler.err_quota.numpy()
    assert quota.shape == (4, 4, 4) and (quota > 0).all()  # the error is everywhere in this field:
    quota = np.zeros_like(quota)  # a quota in two bricks only, so that where the centres go shows
    quota[1, 2, 3], quota[3, 0, 1] = 5, 1
    r.sampler.err_quota.assign(quota)
    r.sampler.err_cum.assign(np.cumsum(quota.ravel()).astype(np.int32))
    moved = r.relocate(rebin=False)
    assert moved == most == 4
    assert r.relocations == [{"iteration": 11, "moved": 4}]
    after = r.raw_params()
    m1, m2 = (s.to_primitive_order(m) for m in (s.m1, s.m2))
    reach = np.empty(N, np.float32)
    reach[s.ids.numpy()] = s.reach.numpy()
    rest = np.setdiff1d(np.arange(N), want)
    np.testing.assert_array_equal(after[rest], before[rest])
    assert (m1[rest] == 1).all() and (m2[rest] == 1).all() and (reach[rest] == 1).all()
    assert (m1[want] == 0).all() and (m2[want] == 0).all() and (reach[want] == 0).all()
    new = after[want]
    np.testing.assert_array_equal(new[:, 11], 0.0)
    np.testing.assert_array_equal(new[:, 6:10], np.tile([0.0, 0.0, 0.0, 1.0], (most, 1)))
    assert (new[:, 3:6] == new[:1, 3]).all()  # one isotropic scale
    live = np.setdiff1d(np.arange(N), dead)
    assert new[0, 3] == pytest.approx(np.median(before[live, 3:6].min(axis=1)), abs=1e-6)
    mu = new[:, :3].astype(np.float64)
    assert (mu >= 0).all() and (mu <= np.array(f.shape_xyz) - 1).all()
    vox = np.floor(mu + 0.5).astype(int)  # the voxel drawn (offsets below half a voxel)
    assert (quota[vox[:, 2] // 4, vox[:, 1] // 4, vox[:, 0] // 4] > 0).all()
    np.testing.assert_allclose(new[:, 10], f.values[vox[:, 2], vox[:, 1], vox[:, 0]])
    assert not np.allclose(new[:, :3], before[want, :3])
    r.rebin()  # the refiner carries on from the relocated state
    r.run(log_every=40)
    assert np.isfinite(r.model_params()).all()


def test_relocation_runs_at_its_iterations_and_is_reproducible(cpu):
    """With relocation on, the step relocates every ``relocate_every`` iterations before
    ``relocate_until``; the same seed gives the same bytes, and the model differs from the run
    without relocation."""
    a = _run(cpu, relocate_every=10, relocate_until=1.0)
    b = _run(cpu, relocate_every=10, relocate_until=1.0)
    assert [x["iteration"] for x in a.relocations] == [10, 20, 30]
    assert a.relocations[0]["moved"] == math.ceil(0.05 * N) == 2
    assert sum(x["moved"] for x in a.relocations) == len(DEAD)  # 2 a time, the dead ones only
    assert a.relocations == b.relocations
    assert a.model_params().tobytes() == b.model_params().tobytes()
    assert (_sigmoid(a.raw_params()[DEAD, 11]) > 0.02).all()  # none left dead
    off = _run(cpu)
    assert not np.array_equal(a.model_params(), off.model_params())
    half = _run(cpu, relocate_every=10)  # relocate_until 0.5: before iteration 20 only
    assert [x["iteration"] for x in half.relocations] == [10]
    other = _run(cpu, seed=1, relocate_every=10, relocate_until=1.0)  # another seed, other centres
    assert not np.array_equal(a.raw_params()[DEAD, :3], other.raw_params()[DEAD, :3])


def test_no_error_stratum_moves_nothing(cpu):
    """Without an error stratum (error_share 0) there is nothing to draw a new centre from: no
    relocation runs and the model is the one without relocation."""
    a = _run(cpu, relocate_every=10, relocate_until=1.0, error_share=0.0)
    assert a.relocations == []
    assert a.model_params().tobytes() == _run(cpu, error_share=0.0).model_params().tobytes()


@pytest.mark.parametrize(
    "bad",
    [
        {"relocate_every": -1},
        {"relocate_every": 2.5},
        {"relocate_every": True},
        {"relocate_until": 1.5},
        {"relocate_until": float("nan")},
        {"relocate_weight": 0.0},
        {"relocate_weight": 1.0},
        {"relocate_share": 0.0},
        {"relocate_share": 1.2},
    ],
    ids=lambda d: f"{next(iter(d))}={next(iter(d.values()))}",
)
def test_bad_relocation_settings_are_refused(bad):
    name = next(iter(bad))
    with pytest.raises(WarpgaussError, match=name):
        RefineConfig(**bad).validate()
    RefineConfig(relocate_every=100, relocate_until=1.0, relocate_weight=0.5, relocate_share=1.0).validate()


def test_the_report_counts_the_relocated(cpu):
    """An encode's report carries refinement.relocated: 0 without relocation, the relocations'
    sum with it."""
    import warpgauss
    from warpgauss.readers.synthetic import generate

    vol = generate("vortex", 24)
    kw = dict(budget=150, format="full", device=cpu, self_test=False, seed=3, evaluate=False)
    off = warpgauss.encode(vol, refine=RefineConfig(iterations=30, samples=256, auto_samples=False), **kw)
    assert off.report["refinement"]["relocated"] == 0
    cfg = RefineConfig(iterations=30, samples=256, auto_samples=False, relocate_every=10, relocate_until=1.0, relocate_weight=0.5)
    on = warpgauss.encode(vol, refine=cfg, **kw)
    assert on.report["refinement"]["relocated"] > 0
    assert on.report["refinement"]["relocated"] <= 2 * math.ceil(0.05 * 150)


def test_a_resumed_run_relocates_as_the_uninterrupted_one(cpu):
    """A checkpoint between two relocations (its scalars through JSON, as the file stores them)
    continues to the uninterrupted run's bytes and relocation record."""
    import json

    cfg = dict(relocate_every=10, relocate_until=1.0)
    whole = _run(cpu, **cfg)
    first = _refiner(cpu, **cfg)
    for _ in range(15):
        first.step()
    arrays, scalars = first.state_arrays()
    resumed = _refiner(cpu, **cfg)
    resumed.restore(arrays, json.loads(json.dumps(scalars)))
    resumed.run(log_every=40)
    assert resumed.relocations == whole.relocations
    assert resumed.model_params().tobytes() == whole.model_params().tobytes()
