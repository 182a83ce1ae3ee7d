"""Time series groundwork (issue #21): the evolving example and the warm start (same seed, same
model; exact N; a warm start from another grid or budget refused in one line)."""

from __future__ import annotations

import numpy as np
import pytest

import warpgauss
from warpgauss.errors import WarpgaussError
from warpgauss.readers.synthetic import generate, generate_series

FAST = dict(budget=200, iterations=40, samples=256, device="cpu", self_test=False, format="full")


def test_the_evolving_example_turns_about_z():
    a = list(generate_series("vortex", 20, 3))
    b = list(generate_series("vortex", 20, 3))
    assert len(a) == 3 and all(x.dtype == np.float32 and x.shape == (20, 20, 20) for x in a)
    np.testing.assert_array_equal(a[0], generate("vortex", 20))
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)
    assert all(float(x.min()) == 0.0 and float(x.max()) == 1.0 for x in a)
    d1, d2 = (float(np.abs(a[t] - a[0]).mean()) for t in (1, 2))
    assert 0 < d1 < d2  # further from the start as it turns
    with pytest.raises(WarpgaussError, match="steps must be a positive int"):
        next(generate_series("vortex", 20, 0))


def test_a_warm_start_refines_the_previous_model():
    v0, v1 = generate_series("vortex", 20, 2)
    m0 = warpgauss.encode(v0, **FAST)
    warm = warpgauss.encode(v1, warm_start=m0, **FAST)
    again = warpgauss.encode(v1, warm_start=m0, **FAST)
    np.testing.assert_array_equal(warm.params, again.params)  # same seed and device: same model
    assert warm.n == m0.n == 200
    assert warm.report["refinement"]["iterations"] == 40
    assert any(s["what"] == "S1b-S1e allocation" for s in warm.report["skipped"])
    start = warm.report["evaluation"]["analytic"]["psnr_db"]
    assert warm.report["psnr_db"] >= start  # refinement moved it towards the new timestep
    with pytest.raises(WarpgaussError, match="same budget"):
        warpgauss.encode(v1, **{**FAST, "budget": 150}, warm_start=m0)
    with pytest.raises(WarpgaussError, match="grid"):
        warpgauss.encode(generate("vortex", 16), **FAST, warm_start=m0)
    with pytest.raises(WarpgaussError, match=r"\(N, 12\)"):
        warpgauss.encode(v1, **FAST, warm_start=np.zeros((200, 3)))


def test_a_series_is_checked_before_any_work_and_encoded_at_one_n(tmp_path):
    from warpgauss.series.steps import encode_series

    steps = list(generate_series("interface", 16, 3))
    for t, v in enumerate(steps):
        v.tofile(tmp_path / f"s_{t}_16x16x16_float32.raw")
    pattern = str(tmp_path / "s_*_16x16x16_float32.raw")
    kw = dict(iterations=20, samples=256, device="cpu", self_test=False, format="full")
    models = encode_series(pattern, budget=120, output_pattern=str(tmp_path / "out_{t}.wgs"), warm_iterations=10, **kw)
    assert [m.n for m in models] == [120, 120, 120]
    assert [m.report["series"]["warm_start"] for m in models] == [False, True, True]
    assert [m.report["refinement"]["iterations"] for m in models] == [20, 10, 10]
    assert all(warpgauss.Model.load(tmp_path / f"out_{t}.wgs").n == 120 for t in range(3))
    again = encode_series([str(tmp_path / f"s_{t}_16x16x16_float32.raw") for t in range(3)], budget=120, warm_iterations=10, **kw)
    for a, b in zip(models, again):
        np.testing.assert_array_equal(a.params, b.params)
    cold = encode_series(steps, budget=120, cold=True, **kw)
    assert not any(m.report["series"]["warm_start"] for m in cold)
    # refusals, in one line, before any encode or file
    generate("vortex", 12).tofile(tmp_path / "s_9_12x12x12_float32.raw")
    with pytest.raises(WarpgaussError, match="different grids"):
        encode_series(str(tmp_path / "s_*_float32.raw"), budget=120, output_pattern=str(tmp_path / "x_{t}.wgs"), **kw)
    assert not list(tmp_path.glob("x_*.wgs"))
    with pytest.raises(WarpgaussError, match="no file matches"):
        encode_series(str(tmp_path / "nothing_*.raw"), budget=120, **kw)
    with pytest.raises(WarpgaussError, match="no such file"):
        encode_series([str(tmp_path / "gone.raw")], budget=120, **kw)
    with pytest.raises(WarpgaussError, match=r"must hold \{t\}"):
        encode_series(steps, budget=120, output_pattern=str(tmp_path / "y.wgs"), **kw)


def test_cli_encodes_a_glob_as_a_series(tmp_path):
    import json

    from typer.testing import CliRunner

    from warpgauss.cli.main import app

    for t, v in enumerate(generate_series("vortex", 16, 2)):
        v.tofile(tmp_path / f"r_{t}_16x16x16_float32.raw")
    base = [
        "encode",
        str(tmp_path / "r_*_16x16x16_float32.raw"),
        "--budget",
        "100",
        "--iterations",
        "10",
        "--device",
        "cpu",
        "--no-self-test",
    ]
    r = CliRunner().invoke(app, [*base, "--format", "full", "--warm-iterations", "5", "-o", str(tmp_path / "m_{t}.wgs"), "--json"])
    assert r.exit_code == 0, r.output
    rows = json.loads(r.output)["series"]
    assert [(x["step"], x["warm_start"], x["n"], x["iterations"]) for x in rows] == [(0, False, 100, 10), (1, True, 100, 5)]
    assert (tmp_path / "m_1.wgs.report.json").exists() and warpgauss.Model.load(tmp_path / "m_1.wgs").n == 100
    r = CliRunner().invoke(app, [*base, "-o", str(tmp_path / "m_{t}.wgs")])
    assert r.exit_code == 2 and "exists" in r.output  # nothing overwritten without --force
    r = CliRunner().invoke(app, ["encode", str(tmp_path / "r_0_16x16x16_float32.raw"), "--cold", "--budget", "100"])
    assert r.exit_code == 2 and "apply to a series" in r.output
    r = CliRunner().invoke(app, ["encode", str(tmp_path / "r_0_16x16x16_float32.raw"), "--keyframe-drift", "2", "--budget", "100"])
    assert r.exit_code == 2 and "apply to a series" in r.output
    r = CliRunner().invoke(app, [*base, "--keyframe-drift", "-1", "-o", str(tmp_path / "n_{t}.wgs")])
    assert r.exit_code == 2 and "--keyframe-drift must be >= 0" in r.output and not list(tmp_path.glob("n_*"))


def _time_axis_files(tmp_path, steps):
    """The same series as an HDF5 file (two (t, z, y, x) datasets and a 3D one), a classic netCDF
    file and a Zarr store."""
    import h5py
    from scipy.io import netcdf_file

    cube = np.stack(steps)  # (t, z, y, x)
    h5 = tmp_path / "run.h5"
    with h5py.File(h5, "w") as f:
        f["mask3d"] = steps[0]
        f["density"] = cube
        f["density"].attrs["spacing"] = (0.5, 0.5, 2.0)  # as the readers take it: (x, y, z)
        f["energy"] = cube[:, ::-1].copy()
    nc = tmp_path / "run.nc"
    with netcdf_file(nc, "w") as f:
        for name, n in zip(("time", "z", "y", "x"), cube.shape):
            f.createDimension(name, n)
        v = f.createVariable("density", "f4", ("time", "z", "y", "x"))
        v[:] = cube
    paths = [h5, nc]
    try:
        import zarr

        zpath = tmp_path / "run.zarr"
        z = zarr.open(str(zpath), mode="w", shape=cube.shape, dtype="f4", chunks=(1, 8, 8, 8))
        z[:] = cube
        paths.append(zpath)
    except ImportError:
        pass
    return paths


def test_a_time_axis_in_one_file_is_a_series(tmp_path):
    from warpgauss.series.steps import encode_series, series_chains, time_steps

    steps = list(generate_series("bubbles", 16, 3))
    kw = dict(iterations=15, samples=256, device="cpu", self_test=False, format="full", budget=100, warm_iterations=5)
    reference = encode_series(steps, **kw)
    for path in _time_axis_files(tmp_path, steps):
        found = time_steps(path)
        assert [s.t for s in found] == [0, 1, 2]
        np.testing.assert_array_equal(found[1].read(), steps[1])  # one timestep read alone
        models = encode_series(str(path), **kw)
        assert [m.report["series"]["step"] for m in models] == [0, 1, 2]
        for m, ref in zip(models, reference):  # same voxels, same seed: the same models as the arrays
            np.testing.assert_array_equal(m.params, ref.params)
    h5 = tmp_path / "run.h5"
    both = encode_series(str(h5), variables=["density", "energy"], output_pattern=str(tmp_path / "o_{var}_{t}.wgs"), **kw)
    assert [(m.report["series"]["variable"], m.report["series"]["step"]) for m in both] == [
        ("density", 0),
        ("density", 1),
        ("density", 2),
        ("energy", 0),
        ("energy", 1),
        ("energy", 2),
    ]
    assert (tmp_path / "o_energy_2.wgs").is_file() and all(m.n == 100 for m in both)
    spacings = [tuple(m.header["grid"]["spacing"]) for m in (both[0], both[3])]
    assert spacings == [(0.5, 0.5, 2.0), (1.0, 1.0, 1.0)]  # each array's own
    assert both[1].report["input"]["name"] == "run.h5:density[1]"
    sizes = {(tmp_path / f"o_{v}_{t}.wgs").stat().st_size for v in ("density", "energy") for t in range(3)}
    assert sizes == {both[0].file_size(False)}  # exactly the same bytes for every timestep
    assert time_steps(h5, "mask3d") is None  # a 3D variable is one volume
    assert len(series_chains(str(h5), ["mask3d"])[0][1]) == 1
    with pytest.raises(WarpgaussError, match="no variable 'wind'.*density"):
        time_steps(h5, "wind")
    with pytest.raises(WarpgaussError, match=r"\{var\}"):
        encode_series(str(h5), variables=["density", "energy"], output_pattern=str(tmp_path / "o_{t}.wgs"), **kw)
    with pytest.raises(WarpgaussError, match="named twice"):
        encode_series(str(h5), variables=["density", "density"], **kw)


def test_cli_encodes_a_time_axis_and_several_variables(tmp_path):
    import json

    from typer.testing import CliRunner

    from warpgauss.cli.main import app

    _time_axis_files(tmp_path, list(generate_series("vortex", 16, 2)))
    base = [
        "encode",
        str(tmp_path / "run.h5"),
        "--budget",
        "80",
        "--iterations",
        "8",
        "--device",
        "cpu",
        "--no-self-test",
        "--format",
        "full",
        "--json",
    ]
    r = CliRunner().invoke(app, [*base, "--variable", "density", "-o", str(tmp_path / "d_{t}.wgs")])
    assert r.exit_code == 0, r.output
    assert [(x["variable"], x["step"], x["warm_start"]) for x in json.loads(r.output)["series"]] == [
        ("density", 0, False),
        ("density", 1, True),
    ]
    r = CliRunner().invoke(app, [*base, "--variable", "density", "--variable", "energy", "-o", str(tmp_path / "m.wgs")])
    assert r.exit_code == 0, r.output
    rows = json.loads(r.output)["series"]
    assert [x["output"] for x in rows] == [str(tmp_path / f"m_{v}_{t:03d}.wgs") for v in ("density", "energy") for t in (0, 1)]
    r = CliRunner().invoke(app, [*base, "--variable", "wind"])
    assert r.exit_code == 2 and "no variable 'wind'" in r.output


def test_a_series_with_a_byte_budget_takes_timestep_0s_n(cpu):
    """file_bytes= sizes timestep 0's N like ratio= does, and the later timesteps take that N
    (they failed with "give one of --budget, --ratio and --bytes" before)."""
    from warpgauss.series.steps import encode_series

    steps = list(generate_series("vortex", 16, 3))
    models = encode_series(steps, file_bytes=9000, iterations=5, samples=128, device=cpu, self_test=False)
    first = warpgauss.encode(steps[0], file_bytes=9000, iterations=5, samples=128, device=cpu, self_test=False)
    assert [m.n for m in models] == [first.n] * 3
    assert [m.report["series"]["warm_start"] for m in models] == [False, True, True]


def test_a_series_on_a_local_dask_cluster(tmp_path, monkeypatch):
    pytest.importorskip("distributed")
    import warpgauss.readers.lazy
    from warpgauss.encoding.scale.cluster import local_client
    from warpgauss.series.steps import encode_series

    steps = list(generate_series("vortex", 16, 4))
    kw = dict(budget=90, iterations=12, samples=256, device="cpu", self_test=False, format="full", warm_iterations=6)
    serial = encode_series(steps, **kw)
    client = local_client(2)
    try:
        seen = []
        spread = encode_series(
            steps, client=client, output_pattern=str(tmp_path / "s_{t}.wgs"), on_step=lambda t, n, m: seen.append(t), **kw
        )
        cold = encode_series(steps, client=client, cold=True, **kw)
        by_ratio_kw = {k: v for k, v in kw.items() if k != "budget"}
        by_ratio = encode_series(steps, client=client, ratio=2.0, **by_ratio_kw)
        by_ratio_serial = encode_series(steps, ratio=2.0, **by_ratio_kw)

        def full(arrays):
            raise OSError(28, "No space left on device")

        monkeypatch.setattr(warpgauss.readers.lazy, "shared", full)  # no room for the timesteps' files: they go through the graph
        no_room = encode_series(steps, client=client, **kw)
    finally:
        client.close()
        client.cluster.close()
    # N given: two runs start at once, [0, 1] and [2, 3], each cold at N and then warm
    assert [m.report["series"]["step"] for m in spread] == [0, 1, 2, 3] and sorted(seen) == [0, 1, 2, 3]
    assert [m.report["series"]["warm_start"] for m in spread] == [False, True, False, True]
    assert all(m.n == 90 for m in spread) and all((tmp_path / f"s_{t}.wgs").is_file() for t in range(4))
    for t in (0, 1):  # the same processes' work as the serial run, bit for bit
        np.testing.assert_array_equal(spread[t].params, serial[t].params)
    alone = warpgauss.encode(steps[2], **{k: v for k, v in kw.items() if k != "warm_iterations"})
    np.testing.assert_array_equal(spread[2].params, alone.params)
    # N from a ratio: timestep 0 first (it fixes N), then [1, 2] warm on from it and [3] cold at that N
    assert [m.report["series"]["warm_start"] for m in by_ratio] == [False, True, True, False]
    assert len({m.n for m in by_ratio}) == 1 and by_ratio[0].n == by_ratio_serial[0].n
    for t in (0, 1, 2):
        np.testing.assert_array_equal(by_ratio[t].params, by_ratio_serial[t].params)
    assert [m.report["series"]["warm_start"] for m in cold] == [False] * 4
    for a, b in zip(no_room, spread):
        np.testing.assert_array_equal(a.params, b.params)
    for t in range(4):
        np.testing.assert_array_equal(
            cold[t].params, warpgauss.encode(steps[t], **{k: v for k, v in kw.items() if k != "warm_iterations"}).params
        )


def test_a_drifting_warm_chain_is_re_encoded_cold_at_the_step_that_drifts(tmp_path):
    """The key-frame rule: a warm timestep more than keyframe_drift dB below the chain's best warm
    PSNR is encoded again cold (same N) and the better kept: the cold one is the same model as a
    cold encode of that timestep (and its file), and the chain goes on warm from it."""
    from warpgauss.series.steps import encode_series

    a, b, c = generate_series("bubbles", 16, 3)
    other = np.ascontiguousarray(np.roll(c, 8, axis=2))  # timestep 2 jumps half the grid: warm drifts
    vols = [a, b, other, other]
    kw = dict(iterations=30, samples=256, device="cpu", self_test=False, format="full")
    models = encode_series(vols, budget=120, warm_iterations=3, output_pattern=str(tmp_path / "k_{t}.wgs"), **kw)
    series = [m.report["series"] for m in models]
    assert [s["warm_start"] for s in series] == [False, True, False, True]
    assert "keyframe" not in series[1] and series[2]["keyframe"]["kept"] == "cold"
    kf = series[2]["keyframe"]
    assert kf["warm_psnr_db"] < models[1].report["psnr_db"] - 1.0 and kf["cold_psnr_db"] > kf["warm_psnr_db"]
    cold = warpgauss.encode(other, budget=120, **kw)
    np.testing.assert_array_equal(models[2].params, cold.params)  # the key frame is the cold model
    np.testing.assert_array_equal(warpgauss.Model.load(tmp_path / "k_2.wgs").params, cold.params)  # and its file
    off = encode_series(vols[:3], budget=120, warm_iterations=3, keyframe_drift=None, **kw)
    assert [m.report["series"]["warm_start"] for m in off] == [False, True, True]
    np.testing.assert_array_equal(off[2].params, warpgauss.encode(other, budget=120, warm_start=off[1], **{**kw, "iterations": 3}).params)


def test_a_key_frame_that_scores_below_the_warm_timestep_is_dropped():
    """Where the cold re-encode is the worse (here: cold gets 1 iteration, warm 40), the warm
    model stays, the report says so, and it is the chain's new baseline (no retry next step)."""
    from warpgauss.series.steps import encode_series

    a, b, c = generate_series("bubbles", 16, 3)
    c = np.ascontiguousarray(np.roll(c, 5, axis=2))
    kw = dict(samples=256, device="cpu", self_test=False, format="full")
    models = encode_series([a, b, c, c], budget=120, iterations=1, warm_iterations=40, **kw)
    series = [m.report["series"] for m in models]
    assert [s["warm_start"] for s in series] == [False, True, True, True]
    kf = series[2]["keyframe"]
    assert kf["kept"] == "warm" and kf["cold_psnr_db"] < kf["warm_psnr_db"] == models[2].report["psnr_db"]
    assert "keyframe" not in series[3]


def test_iter_series_yields_what_encode_series_returns_holding_one_model_at_a_time(tmp_path):
    """iter_series (what the CLI runs without a cluster) gives the same models as encode_series,
    each written as it is yielded, and checks every input before the first encode."""
    import gc
    import weakref

    from warpgauss.series.steps import encode_series, iter_series

    vols = list(generate_series("bubbles", 16, 4))
    kw = dict(budget=100, iterations=10, warm_iterations=4, samples=128, device="cpu", self_test=False, format="full")
    want = encode_series(vols, **kw)
    alive = []
    for t, m in enumerate(iter_series(vols, output_pattern=str(tmp_path / "i_{t}.wgs"), **kw)):
        np.testing.assert_array_equal(m.params, want[t].params)
        assert (tmp_path / f"i_{t}.wgs").is_file() and not (tmp_path / f"i_{t + 1}.wgs").exists()
        alive.append(weakref.ref(m))
        del m
        gc.collect()
        assert sum(r() is not None for r in alive) <= 2  # this one and the warm start of the next
    with pytest.raises(WarpgaussError, match="different grids"):
        next(iter_series([vols[0], generate("bubbles", 12)], **kw))
