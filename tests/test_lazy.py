"""Out-of-core reading (issue #20 part 3): a raw, .npy or chunked HDF5 file is read on demand, the
bricked encode of it equals the bricked encode of the same array in memory bit for bit, and a
device-memory limit chooses the bricking."""

from __future__ import annotations

import numpy as np
import pytest

import warpgauss
from warpgauss.core.limits import DEVICE_FIXED_BYTES, brick_device_bytes, parse_memory
from warpgauss.encoding.scale.plan import choose_bricks, smallest_wave
from warpgauss.errors import WarpgaussError
from warpgauss.field.analysis import normalise
from warpgauss.readers import read_volume
from warpgauss.readers.lazy import LazyValues, is_lazy
from warpgauss.readers.synthetic import generate

FAST = dict(iterations=10, samples=128, device="cpu", self_test=False, format="full", evaluate=True)


def _files(tmp_path, v):
    raw = tmp_path / f"v_{v.shape[2]}x{v.shape[1]}x{v.shape[0]}_float32.raw"
    v.astype(">f4").tofile(tmp_path / "big.raw")  # big-endian: converted per read
    v.tofile(raw)
    npy = tmp_path / "v.npy"
    np.save(npy, v)
    import h5py

    h5 = tmp_path / "v.nc"  # netCDF-4: HDF5 with a leading time axis
    with h5py.File(h5, "w") as f:
        d = f.create_dataset("t0/rho", data=v[None], chunks=(1, 8, 8, 8), compression="gzip")  # chunked, with a time axis
        d.attrs["spacing"] = [1.0, 1.0, 1.0]
    return raw, npy, h5


def test_lazy_fields_read_the_same_values_as_in_memory(tmp_path):
    v = generate("bubbles", 20)
    v[3, 4, 5] = np.nan  # a masked voxel
    raw, npy, h5 = _files(tmp_path, v)
    ref = normalise(v)
    for path, kw in (
        (raw, {}),
        (npy, {}),
        (h5, {"dataset": "t0/rho"}),
        (tmp_path / "big.raw", {"shape": v.shape[::-1], "dtype": "float32", "endian": "big"}),
    ):
        vol = read_volume(path, lazy=True, **kw)
        f = normalise(vol.data, lazy=True, source_dtype=vol.source_dtype)
        assert is_lazy(f.values) and isinstance(f.values, LazyValues)
        assert (f.vmin, f.vmax) == (ref.vmin, ref.vmax)
        np.testing.assert_array_equal(f.values[2:9, :, 3:17], ref.values[2:9, :, 3:17])
        np.testing.assert_array_equal(f.mask[0:20], ref.mask)
        # out of order, repeated, the masked voxel among them: gathered from a mapped file, by slabs from HDF5
        idx = np.array([v.size - 1, 7, 0, 3 * 400 + 4 * 20 + 5, 401, 7])
        np.testing.assert_array_equal(f.values.take_flat(idx), ref.values.reshape(-1)[idx])
        np.testing.assert_array_equal(f.mask.take_flat(idx), ref.mask.reshape(-1)[idx])
        assert (f.values.source.gather(idx) is None) == (path.suffix == ".nc")
        assert abs(f.eligible - ref.eligible) <= 0.05 * ref.eligible and f.occupied == ref.occupied
        import pickle  # our own object between our own workers: the source is plain data

        g = pickle.loads(pickle.dumps(f.values))
        np.testing.assert_array_equal(g[5:6], ref.values[5:6])


def test_a_file_read_brick_by_brick_encodes_as_the_array_in_memory(tmp_path):
    """Bit for bit the model of the array in memory without the seams' refit (which needs the
    whole volume: the array in memory gets it on the CPU, the file read by bricks does not)."""
    from warpgauss.encoding.scale import schedule as wsched

    v = generate("vortex", 20)
    raw, _, h5 = _files(tmp_path, v)
    refit = warpgauss.encode(v, budget=160, bricks="2x1x2", halo=2, **FAST)
    assert refit.report["bricking"]["seam_refit"] is not None
    with wsched.schedule(None, 0.0):
        mem = warpgauss.encode(v, budget=160, bricks="2x1x2", halo=2, **FAST)
    for path, kw in ((raw, {}), (h5, {})):
        read = warpgauss.readers.ReadOptions(dataset="t0/rho") if path == h5 else None
        lazy = warpgauss.encode(str(path), budget=160, bricks="2x1x2", halo=2, read=read, read_by_bricks=True, **FAST, **kw)
        assert lazy.report["bricking"]["read_lazily"] and lazy.report["bricking"]["chosen"] == "given"
        assert lazy.report["bricking"]["seam_refit"] is None
        np.testing.assert_array_equal(lazy.params, mem.params)
        assert lazy.report["psnr_db"] == pytest.approx(mem.report["psnr_db"], abs=1e-6)
        # no counting pass of its own: the bricks' statistics count the file, as the whole array counts
        assert lazy.report["budget"]["n_max"] == mem.report["budget"]["n_max"]


def test_a_file_given_bricks_is_read_whole_where_it_fits_the_host_limit(tmp_path):
    """Issue #55: a small file with --bricks was always read brick by brick, so it got no seams'
    refit (which needs the whole grid). Read whole where its encode fits the host limit, it gets
    the refit, and the model of the same array in memory bit for bit; read_by_bricks=True, or a
    host limit it does not fit, keeps the lazy path."""
    from warpgauss.core.limits import HOST_BYTES_PER_VOXEL
    from warpgauss.encoding.entry import read_by_bricks_rule

    v = generate("vortex", 20)
    raw, _, _ = _files(tmp_path, v)
    whole = warpgauss.encode(str(raw), budget=160, bricks="2x1x2", halo=2, **FAST)
    b = whole.report["bricking"]
    assert not b["read_lazily"] and "fits the host limit" in b["read_why"]
    assert b["seam_refit"] is not None and b["seam_refit"]["iterations"] > 0
    mem = warpgauss.encode(v, budget=160, bricks="2x1x2", halo=2, **FAST)
    np.testing.assert_array_equal(whole.params, mem.params)
    need = HOST_BYTES_PER_VOXEL * 40**3
    assert read_by_bricks_rule((40, 40, 40), int(need), None)[0] is False
    lazy, why = read_by_bricks_rule((40, 40, 40), int(need) - 1, None)
    assert lazy and "GiB allowed" in why
    assert read_by_bricks_rule((40, 40, 40), None, True) == (True, "asked (read_by_bricks True)")
    assert read_by_bricks_rule((40, 40, 40), 10**12, True)[0] and not read_by_bricks_rule((4, 4, 4), 1, False)[0]
    assert read_by_bricks_rule((40, 40, 40), 10**12, None, gpu_cluster=True)[0]  # waves with no refit there: the workers read their boxes
    import json

    from typer.testing import CliRunner

    from warpgauss.cli.main import app

    base = ["encode", str(raw), "--budget", "120", "--iterations", "5", "--device", "cpu", "--no-self-test", "--format", "full"]
    for flag, lazy_read in (("--read-by-bricks", True), ("--read-whole", False)):
        out = tmp_path / f"{flag}.wgs"
        r = CliRunner().invoke(app, [*base, "--bricks", "2x1x1", "--halo", "2", "--workers", "0", flag, "-o", str(out)])
        assert r.exit_code == 0, r.output
        assert json.loads(out.with_name(out.name + ".report.json").read_text())["bricking"]["read_lazily"] is lazy_read


def test_a_budget_past_the_seed_limit_of_a_file_read_brick_by_brick_is_refused_before_refinement(tmp_path):
    v = np.zeros((16, 16, 16), np.float32)
    v[6:9, 6:9, 6:9] = 1.0  # 27 occupied voxels: a seed limit far under the budget
    raw = tmp_path / "v_16x16x16_float32.raw"
    v.tofile(raw)
    out = tmp_path / "v.wgs"
    with pytest.raises(WarpgaussError, match="seed limit|can hold at most"):
        warpgauss.encode(str(raw), budget=500, bricks="2x1x1", halo=2, output=out, read_by_bricks=True, **FAST)
    assert not out.exists()


def test_a_device_memory_limit_chooses_the_bricking(tmp_path):
    assert choose_bricks((64, 32, 32), 100, None) == (1, 1, 1)
    one = brick_device_bytes(64 * 32 * 32, 100)
    assert choose_bricks((64, 32, 32), 100, one) == (1, 1, 1)
    assert choose_bricks((64, 32, 32), 100, one - 1, 2) == (2, 1, 1)  # the longest axis first
    assert choose_bricks((64, 64, 64), 100, brick_device_bytes(36 * 36 * 36, 1.5 * 100 / 8), 2) == (2, 2, 2)
    # a cluster of two workers: every wave holds a brick for each (2x2x2 runs 8 waves of one)
    assert choose_bricks((64, 64, 64), 100, brick_device_bytes(36 * 36 * 36, 1.5 * 100 / 8), 2, workers=2) == (4, 2, 2)
    assert smallest_wave((4, 2, 2)) == 2 and smallest_wave((2, 2, 2)) == 1 and smallest_wave((4, 4, 1)) == 4
    assert choose_bricks((64, 32, 32), 100, None, workers=2) == (1, 1, 1)  # a grid that fits stays whole
    thin = brick_device_bytes(38 * 38 * 38, 1.5 * 100 / 8)  # halo 6: 2x2x2 fits; bricks of 16 would be thinner than 4 halos
    assert choose_bricks((64, 64, 64), 100, thin, 6, workers=2) == (2, 2, 2)
    with pytest.raises(WarpgaussError, match="no bricking"):
        choose_bricks((64, 64, 64), 100, DEVICE_FIXED_BYTES + 10, 2)
    assert parse_memory("24GiB") == 24 * 2**30 and parse_memory("1.5GB") == 1_500_000_000
    with pytest.raises(WarpgaussError, match="max-device-memory"):
        parse_memory("lots")
    v = generate("vortex", 24)
    raw, _, _ = _files(tmp_path, v)
    limit = brick_device_bytes(24 * 24 * 24, 150) - 1  # the whole grid does not fit
    m = warpgauss.encode(str(raw), budget=150, max_device_memory=limit, halo=2, **FAST)
    b = m.report["bricking"]
    assert b["chosen"] == "by the device and host limits" and b["read_lazily"] and b["bricks_xyz"] == [2, 1, 1]
    assert m.n == 150


def test_cli_max_device_memory(tmp_path):
    from typer.testing import CliRunner

    from warpgauss.cli.main import app

    v = generate("vortex", 20)
    raw, _, _ = _files(tmp_path, v)
    base = ["encode", str(raw), "--budget", "120", "--iterations", "5", "--device", "cpu", "--no-self-test", "--format", "full"]
    r = CliRunner().invoke(app, [*base, "--max-device-memory", "many", "-o", str(tmp_path / "a.wgs")])
    assert r.exit_code == 2 and "--max-device-memory must be a size" in r.output and not (tmp_path / "a.wgs").exists()
    limit = str(brick_device_bytes(20 * 20 * 20, 120) - 1)
    r = CliRunner().invoke(app, [*base, "--max-device-memory", limit, "--halo", "2", "-o", str(tmp_path / "b.wgs")])
    assert r.exit_code == 0, r.output
    assert warpgauss.Model.load(tmp_path / "b.wgs").n == 120


def test_dask_workers_read_their_own_boxes(tmp_path):
    pytest.importorskip("distributed")
    from warpgauss.encoding.scale.cluster import local_client

    v = generate("interface", 20)
    raw, _, _ = _files(tmp_path, v)
    serial = warpgauss.encode(str(raw), budget=150, bricks="2x1x2", halo=2, read_by_bricks=True, **FAST)
    client = local_client(2)
    try:
        on_cluster = warpgauss.encode(str(raw), budget=150, bricks="2x1x2", halo=2, client=client, read_by_bricks=True, **FAST)
        whole = warpgauss.encode(str(raw), budget=150, bricks="2x1x2", halo=2, client=client, **FAST)  # issue #55's path, small
    finally:
        client.close()
        client.cluster.close()
    assert on_cluster.report["bricking"]["read_lazily"]
    # the file fits the host limit: read whole, every brick at once over both workers, the seams refit here
    b = whole.report["bricking"]
    assert not b["read_lazily"] and b["schedule"]["waves"] == "together" and b["seam_refit"]["iterations"] > 0
    assert len(b["workers"]) == 2 and b["volume_to_workers"] == "a temporary file the workers read"
    np.testing.assert_array_equal(serial.params, on_cluster.params)


def test_an_array_shared_with_local_workers_is_one_file_read_box_by_box_and_then_removed():
    """shared(): the arrays written once, each read back by slices and as a whole, pickled as a
    name (a few hundred bytes, not the voxels), the folder gone on exit."""
    import os
    import pickle

    from warpgauss.readers.lazy import Shared, opened, shared

    v = generate("vortex", 20)
    mask = v > v.mean()
    with shared([v, None, mask]) as (a, none, m):
        assert isinstance(a, Shared) and none is None and isinstance(m, Shared)
        folder = os.path.dirname(a.source.path)
        np.testing.assert_array_equal(a[2:9, :, 3:5], v[2:9, :, 3:5])
        np.testing.assert_array_equal(m[1:4], mask[1:4])
        assert m[1:4].dtype == bool and a.shape == v.shape
        np.testing.assert_array_equal(opened(a), v)
        assert opened(v) is v
        blob = pickle.dumps(a)
        assert len(blob) < 1000
        np.testing.assert_array_equal(pickle.loads(blob)[5], v[5])
    assert not os.path.exists(folder)


def test_a_cluster_is_local_when_every_worker_reads_the_file_this_process_wrote():
    """is_local asks the workers (a host name says too little: on one lent GPU machine the workers
    listened on an address the host name did not resolve to). Workers that run elsewhere do not
    see the probe file; one that cannot answer counts as elsewhere."""
    from warpgauss.encoding.scale.cluster import is_local, reads_token

    class FakeClient:
        def __init__(self, here: list[bool], fails: bool = False):
            self.here, self.fails = here, fails

        def run(self, fn, path, token):
            if self.fails:
                raise OSError("connection closed")
            return {f"w{i}": fn(path, token) if h else fn(path + ".elsewhere", token) for i, h in enumerate(self.here)}

    assert is_local(FakeClient([True, True]))
    assert not is_local(FakeClient([True, False]))
    assert not is_local(FakeClient([]))
    assert not is_local(FakeClient([True], fails=True))
    assert not reads_token("/nonexistent/probe", "x")


def test_zarr_stores_are_read_whole_or_by_bricks(tmp_path):
    zarr = pytest.importorskip("zarr")
    v = generate("vortex", 20)
    path = tmp_path / "v.zarr"
    g = zarr.open_group(str(path), mode="w")
    make = g.create_array if hasattr(g, "create_array") else g.create_dataset
    a = make("fields/rho", shape=v.shape, chunks=(8, 8, 8), dtype="float32")
    a[...] = v
    a.attrs["spacing"] = [2.0, 2.0, 2.0]
    whole = read_volume(path)
    np.testing.assert_array_equal(whole.data, v)
    assert whole.spacing == (2.0, 2.0, 2.0)
    ref = normalise(v)
    lazy = normalise(read_volume(path, lazy=True).data, lazy=True)
    np.testing.assert_array_equal(lazy.values[3:11, 2:5], ref.values[3:11, 2:5])
    from warpgauss.encoding.scale import schedule as wsched

    with wsched.schedule(None, 0.0):  # the seams' refit needs the volume whole: the store read by bricks has none
        mem = warpgauss.encode(v, budget=150, bricks="1x2x2", halo=2, **FAST)
    from_store = warpgauss.encode(str(path), budget=150, bricks="1x2x2", halo=2, read_by_bricks=True, **FAST)
    assert from_store.report["bricking"]["read_lazily"]
    np.testing.assert_array_equal(from_store.params, mem.params)
    with pytest.raises(WarpgaussError, match="has no array 'nope'"):
        read_volume(path, dataset="nope")


def test_brick_statistics_run_within_the_host_limit():
    """The budget split takes several bricks' statistics at once only as far as the host limit
    holds their boxes (at 2048^3 the thread pool once peaked at 61.7 GB under a 16 GiB limit)."""
    import os

    from warpgauss.encoding.scale.plan import STATS_BYTES_PER_VOXEL, map_bricks, plan_bricks

    bricks = plan_bricks((32, 32, 32), (2, 2, 1), 2)
    seen: list[dict] = []

    def fn(b, **kw):
        seen.append(kw)
        return b.index

    box = max(b.box_voxels for b in bricks)
    assert map_bricks(fn, bricks, host_limit=STATS_BYTES_PER_VOXEL * box) == [b.index for b in bricks]
    assert all("threads" not in kw for kw in seen)  # one box at a time: the bricks one after another
    if (os.cpu_count() or 1) >= 2:
        seen.clear()
        assert map_bricks(fn, bricks, host_limit=2 * STATS_BYTES_PER_VOXEL * box) == [b.index for b in bricks]
        assert all(kw.get("threads", 0) >= 1 for kw in seen) and len(seen) == 4


def test_a_volume_kept_on_the_host_encodes_one_model(tmp_path, monkeypatch):
    """--volume-on-host (issue #55 part 1): the volume stays in (pinned) host memory, the model
    whole on the device, so a file whose encode does not fit --max-device-memory but whose model
    does is one model with no seams. On the CPU device the volume is there anyway: the same model
    bit for bit as the default encode, the report saying where the volume was and why. Asked for
    with bricks, or where the model alone would not fit the limit, it is refused before any work;
    chosen by the limits on a CUDA device (entry.host_volume_auto; here made to say so)."""
    from typer.testing import CliRunner

    from warpgauss.cli.main import app
    from warpgauss.core.limits import host_volume_device_bytes
    from warpgauss.encoding import entry

    v = generate("vortex", 24)
    raw, _, _ = _files(tmp_path, v)
    whole = warpgauss.encode(str(raw), budget=150, **FAST)
    host = warpgauss.encode(str(raw), budget=150, volume_on_host=True, **FAST)
    np.testing.assert_array_equal(np.asarray(host.params), np.asarray(whole.params))
    assert host.report["volume_memory"] == {"where": "host memory (the CPU device)", "why": "asked (--volume-on-host)"}
    assert "volume_memory" not in whole.report and "bricking" not in host.report
    with pytest.raises(WarpgaussError, match="give it or --bricks, not both"):
        warpgauss.encode(str(raw), budget=150, volume_on_host=True, bricks="2x1x1", **FAST)
    small = host_volume_device_bytes(24**3, 150) - 1
    with pytest.raises(WarpgaussError, match="the model alone needs about"):
        warpgauss.encode(str(raw), budget=150, volume_on_host=True, max_device_memory=small, **FAST)
    # the limits: the whole grid does not fit, its model does -> bricks, or the host with the rule on
    # (a grid this small fits nowhere between the two estimates' fixed parts: the host path's is
    # made the bricks' here)
    from warpgauss.core import limits

    monkeypatch.setattr(limits, "HOST_VOLUME_FIXED_BYTES", DEVICE_FIXED_BYTES)
    limit = brick_device_bytes(24 * 24 * 24, 150) - 1
    assert host_volume_device_bytes(24**3, 150) <= limit
    assert "bricking" in warpgauss.encode(str(raw), budget=150, max_device_memory=limit, halo=2, **FAST).report
    assert not entry.host_volume_auto("cpu")  # the CPU device: bricks, as above
    monkeypatch.setattr(entry, "host_volume_auto", lambda device: True)  # as on a CUDA device
    auto = warpgauss.encode(str(raw), budget=150, max_device_memory=limit, halo=2, **FAST)
    assert "bricking" not in auto.report and "does not fit the device limit" in auto.report["volume_memory"]["why"]
    np.testing.assert_array_equal(np.asarray(auto.params), np.asarray(whole.params))
    base = ["encode", str(raw), "--budget", "150", "--iterations", "5", "--device", "cpu", "--no-self-test", "--format", "full"]
    r = CliRunner().invoke(app, [*base, "--volume-on-host", "--bricks", "2x1x1", "-o", str(tmp_path / "c.wgs")])
    assert r.exit_code == 2 and "not both" in r.output and "Traceback" not in r.output and not (tmp_path / "c.wgs").exists()
    ladder = ["encode", str(raw), "--ladder", "60,120", "--iterations", "5", "--device", "cpu", "--volume-on-host"]
    r = CliRunner().invoke(app, [*ladder, "-o", str(tmp_path / "l_{n}.wgs")])
    assert r.exit_code == 2 and "--ladder" in r.output and "Traceback" not in r.output
    r = CliRunner().invoke(app, [*base, "--volume-on-host", "-o", str(tmp_path / "d.wgs")])
    assert r.exit_code == 0, r.output
    assert warpgauss.Model.load(tmp_path / "d.wgs").n == 150


def test_the_host_volume_benchmark_compares_the_two_paths(tmp_path):
    """benchmarks/bricked/volume_on_host.py on a tiny CPU case: both rows, the same model, and the
    issue's keys written into a summary that keeps its other keys."""
    import importlib.util
    import json
    from pathlib import Path

    script = Path(__file__).resolve().parents[1] / "benchmarks" / "bricked" / "volume_on_host.py"
    spec = importlib.util.spec_from_file_location("_bench_volume_on_host", script)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    summary = tmp_path / "round3.json"
    summary.write_text(json.dumps({"cpu48_mono_db": 1.0}))
    out = tmp_path / "voh.json"
    args = ["--size", "24", "--ratio", "8", "--iterations", "5", "--device", "cpu", "--out", str(out), "--summary", str(summary)]
    res = module.main(args)
    assert [r["path"] for r in res["rows"]] == ["in core", "volume on host"] and res["host_equals_in_core"]
    assert res["rows"][1]["volume_memory"]["where"] == "host memory (the CPU device)"
    s = json.loads(summary.read_text())
    assert s["cpu48_mono_db"] == 1.0 and s["ooc1024_db"] == s["incore1024_db"] == res["rows"][0]["psnr_db"]
    assert s["ooc1024_time_ratio"] == res["host_time_ratio"] > 0 and json.loads(out.read_text())["device"] == "cpu"
    # both settings of the draw one iteration ahead, the host rows first; the summary takes the last
    from warpgauss.encoding.refine import draw

    before = draw.DRAW_AHEAD, draw.DRAW_THREADS_HOST
    res = module.main([*args, "--draw-ahead", "both", "--draw-threads", "5", "--host-first"])
    paths = [r["path"] for r in res["rows"]]
    assert paths == [
        "volume on host, draw ahead off, draw threads 5",
        "volume on host, draw ahead on, draw threads 5",
        "in core",
    ]
    assert (draw.DRAW_AHEAD, draw.DRAW_THREADS_HOST) == before
    assert all(r["equals_in_core"] for r in res["rows"][:2]) and res["host_time_ratio"] == res["rows"][1]["time_ratio"]
    assert "draw ahead on, draw threads 5" in json.loads(summary.read_text())["ooc1024_source"]
