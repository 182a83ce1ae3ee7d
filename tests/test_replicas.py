"""One model refined on several devices (issue #55 part 3), as replicas on the CPU device: the
combined gradient is the gradient of all the replicas' samples together, the replicas stay equal
bit for bit, and a run is reproducible."""

from __future__ import annotations

import numpy as np
import pytest

from warpgauss.encoding.refine import RefineConfig, Refiner
from warpgauss.encoding.refine.replicas import Replicas, _like, sample_shares
from warpgauss.errors import WarpgaussError
from warpgauss.field.analysis import DeviceVolume, normalise
from warpgauss.field.evaluate import evaluate_field
from warpgauss.field.gaussians import GaussianField

N = 48


def _field():
    from warpgauss.readers.synthetic import generate

    return normalise(generate("vortex", 16, seed=1))


def _params(f) -> np.ndarray:
    rng = np.random.default_rng(0)
    p = np.zeros((N, 12), np.float32)
    p[:, :3] = rng.uniform(0, 1, (N, 3)) * (np.array(f.shape_xyz) - 1)
    p[:, 3:6], p[:, 9], p[:, 10], p[:, 11] = 1.2, 1.0, 0.5, 0.5
    return p


def _refiner(cpu, f, seed=0, **cfg) -> Refiner:
    conf = {"iterations": 30, "samples": 256, "importance": True, "error_share": 0.2, **cfg}
    return Refiner(DeviceVolume(f, cpu), _params(f), RefineConfig(**conf), seed, 0.3, 4.0)


def _replicated(cpu, f, copies: int = 1, **cfg) -> Refiner:
    r = _refiner(cpu, f, **cfg)
    r.replicate([cpu] * copies)
    return r


def test_sample_shares_split_evenly():
    assert sample_shares(256, 2) == [128, 128]
    assert sample_shares(257, 2) == [129, 128]
    assert sample_shares(10, 3) == [4, 3, 3]
    assert sum(sample_shares(1001, 4)) == 1001


def _load(r: Refiner, points, target, weight, occupied, rows) -> None:
    """The samples ``rows`` of a larger draw (and their partners) into ``r``'s sample buffers."""
    s, m = r.sampler, r.m
    assert len(rows) == m
    total = len(target)
    s.points.assign(np.concatenate([points[rows], points[total + rows]]))
    s.target.assign(target[rows])
    s.weight.assign(weight[rows])
    s.occupied.assign(occupied[rows])
    r.passes.points_changed()


def test_combined_gradient_is_the_gradient_of_all_samples(cpu):
    """Samples shared 160 / 96 between two replicas give, after the exchange, the pair gradients
    one refiner takes from all 256 at once (float64 sums of the same terms: to float32 rounding),
    on both replicas bit for bit."""
    f = _field()
    whole = _refiner(cpu, f)
    whole.sample()
    pts, tgt, wgt, occ = (a.numpy().copy() for a in (whole.sampler.points, whole.target, whole.weight, whole.occupied))
    whole.forward_backward()
    expect = [a.numpy().astype(np.float64) for a in whole.pair_grads]

    r = _refiner(cpu, f)
    params, lo, cap = r._made
    r.replicas = reps = Replicas(r, [cpu], lambda dv, c, seed: Refiner(dv, params, c, seed, lo, cap))
    reps.shares, reps.weights = [160, 96], [160 / 256, 96 / 256]
    r.set_samples(160)
    peer = reps.peers[0]
    peer.set_samples(96)
    reps._recv = {(0, 1): _like(peer.state.pair_grads), (1, 0): _like(r.state.pair_grads)}
    _load(r, pts, tgt, wgt, occ, np.arange(160))
    _load(peer, pts, tgt, wgt, occ, np.arange(160, 256))
    for x in (r, peer):
        x.forward_backward()
    assert np.array_equal(r.state.ids.numpy(), whole.state.ids.numpy())  # the same slot order
    reps.exchange()
    got = [a.numpy() for a in r.pair_grads]
    for g, e in zip(got, expect):
        scale = max(float(np.abs(e).max()), 1e-30)
        assert np.abs(g - e).max() <= 2e-5 * scale
    assert any(np.abs(e).max() > 0 for e in expect)
    for a, b in zip(r.pair_grads, peer.pair_grads):
        assert a.numpy().tobytes() == b.numpy().tobytes()


def test_replicas_stay_equal_and_refine(cpu):
    """Two replicas of 128 samples each through 30 iterations (re-bins, re-plans, the error
    stratum's folds): the same parameters bit for bit at the end, a model as good as one device's
    with 256 samples (other draws: both gain over the start, within 1 dB of each other on the grid), and the same run twice gives
    the same model (same seed, same devices)."""
    f = _field()
    one = _refiner(cpu, f)
    one.run(log_every=30)
    two = _replicated(cpu, f)
    assert two.m == 128 and two.replicas.peers[0].m == 128
    two.run(log_every=30)
    assert two.replicas.equal()
    assert two.iteration == 30 and two.replicas.peers[0].iteration == 30
    assert two.replicas.peers[0].sampler.m_err > 0  # the error stratum drawn on the peer too

    def psnr(r):
        return evaluate_field(GaussianField(r.model_params(), f.shape_xyz, cpu), f)["psnr_db"]

    start = psnr(_refiner(cpu, f))
    p1, p2 = psnr(one), psnr(two)
    assert p1 > start + 1.0 and p2 > start + 1.0, (start, p1, p2)
    assert abs(p1 - p2) < 1.0, (p1, p2)
    again = _replicated(cpu, f)
    again.run(log_every=30)
    assert again.model_params().tobytes() == two.model_params().tobytes()


def test_replicas_without_importance_or_error_stratum(cpu):
    """Plain uniform draws (no importance weights, no error stratum, no support): the replicas
    still stay equal and refine."""
    f = _field()
    r = _replicated(cpu, f, importance=False, error_share=0.0, uniform_support=False)
    r.run(log_every=30)
    assert r.replicas.equal() and r.replicas.peers[0].sampler.m_err == 0


def test_silence_is_mirrored(cpu):
    """The rate control's re-plan takes primitives out on every replica: they stay equal."""
    f = _field()
    r = _replicated(cpu, f)
    for _ in range(5):
        r.step()
    r.silence(np.array([1, 5, 9]))
    assert r.n_live == N - 3 and r.replicas.peers[0].n_live == N - 3
    for _ in range(12):
        r.step()
    assert r.replicas.equal()


def test_a_restored_run_resyncs_the_peers(cpu):
    """A checkpoint restored into the primary reaches the peers (a resume)."""
    f = _field()
    r = _replicated(cpu, f)
    for _ in range(7):
        r.step()
    arrays, scalars = r.state_arrays()
    fresh = _replicated(cpu, f)
    fresh.restore(arrays, scalars)
    assert fresh.replicas.equal() and fresh.replicas.peers[0].iteration == 7
    for x in (r, fresh):
        for _ in range(6):
            x.step()
    assert fresh.replicas.equal()


@pytest.mark.parametrize(
    "cfg, words",
    [({"relocate_every": 10}, "relocation"), ({"samples": 1}, "cannot be shared")],
)
def test_what_does_not_combine_is_refused(cpu, cfg, words):
    f = _field()
    r = _refiner(cpu, f, **cfg)
    with pytest.raises(WarpgaussError, match=words):
        r.replicate([cpu])


def test_a_time_budget_is_refused(cpu):
    r = _replicated(cpu, _field())
    with pytest.raises(WarpgaussError, match="one device"):
        r.run(deadline=1e9)


def test_an_encode_on_two_replicas(cpu):
    """``devices`` through warpgauss.encode: the report names the replicas, their shares and that
    they ended equal; the same call twice gives the same model (same seed, same devices)."""
    import warpgauss

    kw = {"example": "vortex", "example_size": 16, "budget": 80, "iterations": 20, "samples": 512, "progress": False}
    m = warpgauss.encode(devices=f"{cpu},{cpu}", **kw)
    rep = m.report["refinement"]
    assert rep["replicas"] == {"devices": [cpu, cpu], "samples": [256, 256], "equal": True}
    assert rep["samples"] == 512
    again = warpgauss.encode(devices=[cpu, cpu], **kw)
    assert again.params.tobytes() == m.params.tobytes()
    assert "replicas" not in warpgauss.encode(device=cpu, **kw).report["refinement"]


@pytest.mark.parametrize(
    "kw, words",
    [
        ({"devices": "cpu,", "device": None}, "comma list"),
        ({"devices": "cpu,cpu", "time_budget": 5.0}, "time budget"),
        ({"devices": "cpu,cpu", "bricks": "2x1x1"}, "bricked"),
        ({"devices": "cpu,nowhere:3"}, "not available"),
        ({"devices": "cpu,cpu", "source": "array"}, "device array"),
    ],
)
def test_devices_refused_in_one_line(tmp_path, kw, words):
    import warpgauss

    out = tmp_path / "m.wgs"
    source = {}
    if kw.pop("source", None):  # a Warp array on the CPU device stands in for a device array
        from warpgauss.core.warp import warp
        from warpgauss.readers.synthetic import generate

        source = {"source": warp().array(generate("vortex", 16), dtype=float, device="cpu")}
    else:
        source = {"example": "vortex", "example_size": 16}
    with pytest.raises(WarpgaussError, match=words):
        warpgauss.encode(**source, budget=40, iterations=5, output=out, progress=False, **kw)
    assert not out.exists()


def test_the_command_line_refuses_a_bad_devices_list(tmp_path):
    from typer.testing import CliRunner

    from warpgauss.cli.main import app

    out = tmp_path / "m.wgs"
    res = CliRunner().invoke(
        app,
        ["encode", "--example", "vortex", "--size", "16", "--budget", "40", "--devices", "cpu,cpu", "--time-budget", "3", "-o", str(out)],
    )
    assert res.exit_code == 2 and "time budget" in res.output and "Traceback" not in res.output
    assert not out.exists()


def test_a_ladder_refuses_devices(tmp_path):
    from typer.testing import CliRunner

    from warpgauss.cli.main import app

    args = ["encode", "--example", "vortex", "--size", "16", "--ladder", "40,80", "--devices", "cpu,cpu", "-o", str(tmp_path / "m.wgs")]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 2 and "--ladder" in res.output and "Traceback" not in res.output
    assert not list(tmp_path.iterdir())


def test_the_command_line_says_where_it_refined(tmp_path):
    from typer.testing import CliRunner

    from warpgauss.cli.main import app

    out = tmp_path / "m.wgs"
    args = ["encode", "--example", "vortex", "--size", "16", "--budget", "40", "--iterations", "10", "--devices", "cpu,cpu", "-o", str(out)]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    assert "refined on cpu, cpu" in res.output and out.exists()
