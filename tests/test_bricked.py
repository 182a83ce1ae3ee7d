"""Bricked encoding: the plan covers the grid, the budget split is exact and within each brick's
seed limit, and a bricked model is the same bit for bit in this process and on a local Dask
cluster of two processes (same seed, same bricking, same device)."""

from __future__ import annotations

import numpy as np
import pytest

import warpgauss
from warpgauss.analysis import normalise, seed_limit
from warpgauss.bricked import brick_fields, parse_bricks, plan_bricks, seam_weights, split_bricks
from warpgauss.errors import WarpgaussError
from warpgauss.synthetic import generate

FAST = dict(iterations=20, samples=256, device="cpu", self_test=False, format="full")


@pytest.mark.parametrize("shape, counts, halo", [((20, 17, 9), (2, 3, 1), 2), ((16, 16, 16), (2, 2, 2), 4), ((12, 10, 8), (1, 1, 1), 3)])
def test_bricks_cover_the_grid_once_with_their_halo(shape, counts, halo):
    bricks = plan_bricks(shape, counts, halo)
    assert len(bricks) == int(np.prod(counts))
    cover = np.zeros(shape[::-1], int)
    for b in bricks:
        cover[b.slices("interior")] += 1
        for (i0, i1), (b0, b1), n in zip(b.interior, b.box, shape[::-1]):
            assert b0 == max(0, i0 - halo) and b1 == min(n, i1 + halo)
    assert (cover == 1).all()
    shares = np.zeros(shape[::-1])
    for b in bricks:
        shares[b.slices("box")] += seam_weights(b)
    np.testing.assert_allclose(shares, 1.0, atol=1e-6)  # a partition of unity over the grid


def test_bad_bricking_is_refused():
    with pytest.raises(WarpgaussError, match="three positive integers"):
        parse_bricks("2x2")
    with pytest.raises(WarpgaussError, match="fewer than 2 voxels"):
        plan_bricks((8, 8, 8), (5, 1, 1))


def test_budget_split_is_exact_and_within_seed_limits():
    f = normalise(generate("bubbles", 32))
    bricks = plan_bricks(f.shape_xyz, (2, 2, 2), 3)
    total = seed_limit(f.eligible, f.occupied)
    for n in (1, 57, 400, total // 3):
        counts, stats = split_bricks(f, bricks, n)
        assert sum(counts) == n
        for c, b in zip(counts, bricks):
            alloc, _ = brick_fields(f, b)
            assert 0 <= c <= seed_limit(alloc.eligible, alloc.occupied)
        assert counts == split_bricks(f, bricks, n)[0]  # deterministic
    # the bricks with more structure get more: the detail share follows |grad V|
    counts, stats = split_bricks(f, bricks, 400)
    order = np.argsort([s["grad_sum"] for s in stats])
    assert counts[order[-1]] >= counts[order[0]]


def test_bricked_encode_is_exact_and_repeatable():
    v = generate("vortex", 24)
    a = warpgauss.encode(v, budget=300, bricks="2x2x1", halo=2, **FAST)
    b = warpgauss.encode(v, budget=300, bricks="2x2x1", halo=2, **FAST)
    assert a.n == 300 and sum(x["n"] for x in a.report["bricking"]["bricks"]) == 300
    np.testing.assert_array_equal(a.params, b.params)
    lo = np.array([0, 0, 0]) - 0.5
    hi = np.array(v.shape[::-1]) - 0.5
    assert ((a.params[:, :3] >= lo - 3) & (a.params[:, :3] <= hi + 3)).all()  # global coordinates
    assert a.report["psnr_db"] > 25.0


def test_bricked_encode_on_a_local_dask_cluster_equals_the_serial_one():
    distributed = pytest.importorskip("distributed")
    from warpgauss.bricked import local_client

    v = generate("interface", 24)
    serial = warpgauss.encode(v, budget=250, bricks="2x1x2", halo=2, **FAST)
    client = local_client(2)
    try:
        on_cluster = warpgauss.encode(v, budget=250, bricks="2x1x2", halo=2, client=client, **FAST)
        workers = {b["device"] for b in on_cluster.report["bricking"]["bricks"]}
    finally:
        client.close()
        client.cluster.close()
    assert isinstance(client, distributed.Client) and workers == {"cpu"}
    np.testing.assert_array_equal(serial.params, on_cluster.params)
    assert on_cluster.report["bricking"]["scheduler"].startswith("tcp://")


def test_cli_bricked_encode_and_its_refusals(tmp_path):
    from typer.testing import CliRunner

    from warpgauss.cli.main import app

    out = tmp_path / "b.wgs"
    base = ["encode", "--example", "vortex", "--size", "20", "--budget", "120", "--iterations", "5", "--device", "cpu", "--no-self-test", "--format", "full"]
    r = CliRunner().invoke(app, [*base, "--bricks", "2x1x1", "--halo", "2", "--workers", "0", "-o", str(out)])
    assert r.exit_code == 0, r.output
    assert warpgauss.Model.load(out).n == 120
    r = CliRunner().invoke(app, [*base, "--halo", "2", "-o", str(tmp_path / "c.wgs")])
    assert r.exit_code == 2 and "give --bricks" in r.output and not (tmp_path / "c.wgs").exists()
    r = CliRunner().invoke(app, [*base, "--bricks", "11x1x1", "--workers", "0", "-o", str(tmp_path / "d.wgs")])
    assert r.exit_code == 2 and "fewer than 2 voxels" in r.output and not (tmp_path / "d.wgs").exists()
