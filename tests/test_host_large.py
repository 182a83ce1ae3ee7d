"""Volumes of more than 2^31 voxels on the host path (``--volume-on-host``): the index arithmetic
that passes int32 there, run on small CPU volumes. The draw's ranks among more than
``draw.RANK32_MAX`` voxels take 64 bits (lowered here so that a small volume takes that path and
is checked voxel for voxel against a numpy twin of Warp's generator), the wide loads' view of the
volume is split into rows (``draw.FLAT4_COLUMNS``, lowered: the same samples bit for bit) and the
seeds' race keys of voxel indices past 2^32 mix in the high word."""

from __future__ import annotations

import numpy as np
import pytest

from warpgauss.encoding.refine import draw
from warpgauss.encoding.refine.draw import Sampler
from warpgauss.field.analysis import DeviceVolume, normalise

M32 = 0xFFFFFFFF


def pcg(x: int) -> int:
    """Warp's ``rand_pcg`` (native/rand.h) on Python ints."""
    b = (x * 747796405 + 2891336453) & M32
    c = (((b >> ((b >> 28) + 4)) ^ b) * 277803737) & M32
    return (c >> 22) ^ c


def rand_init(seed: int, offset: int | None = None) -> int:
    if offset is None:
        return pcg(seed & M32)
    return pcg(((seed & M32) + pcg(offset & M32)) & M32)


def rank_twin(stream: int, s: int, n: int, rank32_max: int) -> int:
    """kernels.sampling.rank_below of sample s's first draw: u mod n up to rank32_max, else a
    64-bit draw whose high word comes from a second stream of (stream, s)."""
    u = pcg(rand_init(stream, s))
    if n <= rank32_max:
        return u % n
    hi = pcg(rand_init(rand_init(stream), s))
    return ((hi << 32) | u) % n


def stratum_lists(v: np.ndarray, ok: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Linear indices of the high and mid stratum voxels in the draw's order: 4^3 bricks in z, y,
    x order, each brick's voxels in z, y, x order."""
    nz, ny, nx = v.shape
    k, j, i = (a.ravel() for a in np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij"))
    order = np.lexsort((i % 4, j % 4, k % 4, i // 4, j // 4, k // 4)).astype(np.int64)
    flat_v, flat_ok = v.reshape(-1)[order], ok.reshape(-1)[order]
    high = order[flat_ok & (flat_v > 0.4)]
    mid = order[flat_ok & (flat_v > 0.02) & (flat_v <= 0.4)]
    return high, mid


def _volume(shape=(13, 11, 9), seed=3):
    rng = np.random.default_rng(seed)
    v = rng.uniform(0, 1, shape).astype(np.float32)
    v[rng.uniform(size=shape) < 0.3] = 0.0
    v[rng.uniform(size=shape) < 0.05] = np.nan  # masked
    return normalise(v, value_range=(0.0, 1.0))


def _draw(dv, stream: int, m: int = 600, jitter: float = 0.0, value_empty: float = 1.0):
    import warp as wp

    smp = Sampler(dv, uniform_support=False, value_empty=value_empty, partner_distance=(0.5, 1.5), jitter=jitter, importance=True)
    smp.resize(m)
    smp.draw(wp.array([stream], dtype=int, device=dv.device))
    return smp, tuple(a.numpy() for a in (smp.points, smp.target, smp.weight, smp.occupied))


def test_rank_below_is_randi_up_to_its_limit_and_64_bit_beyond(cpu):
    """The draw's rank of n voxels: u mod n, as wp.randi gave it, up to the limit (the same
    samples as before for every volume below 2^31 voxels); beyond, 64 bits, as the numpy twin."""
    import warp as wp

    from warpgauss.kernels import sampling as ks

    @wp.kernel
    def ranks(n: wp.array(dtype=wp.int64), limit: wp.int64, stream: int, out: wp.array(dtype=wp.int64), old: wp.array(dtype=int)):
        s = wp.tid()
        state = wp.rand_init(stream, s)
        out[s] = ks.rank_below(wp.randu(state), n[s], limit, stream, s)
        if n[s] <= wp.int64(2147483647):
            state2 = wp.rand_init(stream, s)
            old[s] = wp.randi(state2, 0, int(n[s]))

    sizes = [1, 7, 1000, 2**31 - 1, 2**31, 3 * 2**33 + 7, 2**40]
    n = np.array(sizes * 40, np.int64)
    for limit in (2**31 - 1, 5):
        out = wp.zeros(n.size, dtype=wp.int64, device=cpu)
        old = wp.zeros(n.size, dtype=int, device=cpu)
        wp.launch(ranks, dim=n.size, inputs=[wp.array(n, dtype=wp.int64, device=cpu), limit, 1234], outputs=[out, old], device=cpu)
        got = out.numpy()
        want = np.array([rank_twin(1234, s, int(x), limit) for s, x in enumerate(n)], np.int64)
        np.testing.assert_array_equal(got, want)
        assert np.all((got >= 0) & (got < n))
        if limit == 2**31 - 1:
            small = n <= limit
            np.testing.assert_array_equal(got[small], old.numpy()[small])
    big = n == 2**40
    assert np.unique(got[big]).size == big.sum() and got[big].max() > 2**33  # ranks reach past 2^32


@pytest.mark.parametrize("value_empty", [1.0, 0.0])
def test_each_sample_is_the_voxel_the_numpy_twin_draws(cpu, monkeypatch, value_empty):
    """Every sample's voxel (jitter 0: the point is the voxel) is the twin's: the r-th voxel of
    its stratum in brick-then-scan order, or voxel r of the grid (value_empty 1) or of the
    occupied voxels (value_empty 0), with r drawn in 32 bits (the default) or 64 (the limit
    lowered so that this small volume takes the path of a stratum of more than 2^31 voxels)."""
    f = _volume()
    dv = DeviceVolume(f, cpu)
    ok = f.mask if f.mask is not None else np.ones(f.values.shape, bool)
    high, mid = stratum_lists(f.values, ok)
    nz, ny, nx = f.values.shape
    for limit in (draw.RANK32_MAX, 10):
        monkeypatch.setattr(draw, "RANK32_MAX", limit)
        smp, (points, *_) = _draw(dv, stream=77, value_empty=value_empty)
        m = smp.m
        m_high, m_mid, _ = smp.strata
        assert smp.n_high == high.size and smp.n_mid == mid.size
        want = np.empty(m, np.int64)
        for s in range(m):
            if s < m_high:
                want[s] = high[rank_twin(77, s, high.size, limit)]
            elif s < m_high + m_mid:
                want[s] = mid[rank_twin(77, s, mid.size, limit)]
            elif value_empty == 0:
                r = rank_twin(77, s, high.size + mid.size, limit)
                want[s] = high[r] if r < high.size else mid[r - high.size]
            else:
                want[s] = rank_twin(77, s, f.values.size, limit)
        p = points[:m].astype(np.int64)
        got = (p[:, 2] * ny + p[:, 1]) * nx + p[:, 0]
        np.testing.assert_array_equal(got, want)


def test_wide_loads_split_into_rows_give_the_same_samples(cpu, monkeypatch):
    """The volume in host memory viewed as rows of a few groups of four (at 2048^3 the groups are
    2^31, more than a Warp array dimension holds): the same samples bit for bit as one row and as
    the plain loads (jittered: every corner read through the view, a row pair split between two
    groups, a tail past the last whole row)."""
    f = _volume((10, 7, 13))
    plain = _draw(DeviceVolume(f, cpu), stream=5, jitter=0.5)[1]
    for cols in (draw.FLAT4_COLUMNS, 7, 1):
        monkeypatch.setattr(draw, "FLAT4_COLUMNS", cols)
        dv = DeviceVolume(f, cpu)
        dv.on_host = True  # the wide loads (on a CUDA device: pinned host memory read over the bus)
        smp, got = _draw(dv, stream=5, jitter=0.5)
        wide, flat4 = smp._wide()
        assert wide == 1 and flat4.shape == ((f.values.size // 4) // min(cols, f.values.size // 4), min(cols, f.values.size // 4))
        for a, b in zip(plain, got):
            assert a.tobytes() == b.tobytes()


def test_race_keys_of_voxels_past_2_to_the_32_mix_the_high_word(cpu):
    """The seeds' race key of voxel idx: the uniform at offset idx of the draw's stream below 2^32
    (the keys, and seeds, of every volume before), else at offset idx mod 2^32 of a stream mixed
    with idx's high word (voxels 2^32 apart do not share a key)."""
    import warp as wp

    from warpgauss.kernels import analysis as ka

    @wp.kernel
    def keys(idx: wp.array(dtype=wp.int64), stream: int, out: wp.array(dtype=float)):
        t = wp.tid()
        out[t] = ka.race_key(stream, idx[t], 1.0)

    idx = np.array([0, 5, 2**31 - 1, 2**31 + 3, 2**32 + 5, 3 * 2**32 + 5, 2**40 - 1], np.int64)
    out = wp.zeros(idx.size, dtype=float, device=cpu)
    wp.launch(keys, dim=idx.size, inputs=[wp.array(idx, dtype=wp.int64, device=cpu), 99], outputs=[out], device=cpu)

    def twin(x: int) -> float:
        seed = 99 if x >> 32 == 0 else rand_init(99, x >> 32)
        u = 1.0 - np.float32(pcg(rand_init(seed, x & M32)) >> 8) * np.float32(1.0 / 16777216.0)
        return float(-np.log(np.float32(u)))

    np.testing.assert_allclose(out.numpy(), [twin(int(x)) for x in idx], rtol=1e-6)
    got = out.numpy()
    assert got[4] != got[1] and got[5] != got[4]  # 2^32 apart: keys of their own


def test_the_limits_name_the_way_out():
    """In core a volume indexes at most 2^31 - 1 voxels; in host memory up to 2^37 (a 2048^3
    volume passes), within Warp's int32 strides (a slice under 2 GiB) and 2^31 4^3 bricks."""
    from warpgauss.field.limits import MAX_HOST_VOXELS, voxels_problem

    assert voxels_problem((1024, 1024, 2047)) is None
    said = voxels_problem((2048, 2048, 2048))
    assert said is not None and "--volume-on-host" in said and "\n" not in said
    assert voxels_problem((2048, 2048, 2048), MAX_HOST_VOXELS) is None
    assert voxels_problem((8188, 4096, 4096), MAX_HOST_VOXELS) is None  # 2^37 - 2^26
    assert "--bricks" in voxels_problem((8192, 4096, 4096), MAX_HOST_VOXELS)  # 2^37: 2^31 bricks
    assert "slice" in voxels_problem((4, 32768, 16384), MAX_HOST_VOXELS)
    assert "bricks" in voxels_problem((8190, 4094, 4094), MAX_HOST_VOXELS)  # 2^31 + bricks of part-filled edges


def test_past_the_in_core_limit_an_encode_takes_the_volume_on_host(cpu, monkeypatch):
    """The in-core limit lowered below a small volume's voxels: the encode is refused in one line
    that names --volume-on-host, and with the volume on the host it runs, to the model of an
    in-core encode bit for bit (normalised into host memory of its own, which the device volume
    reads as it is); past the host limit it is refused naming --bricks."""
    import warpgauss
    from warpgauss.errors import WarpgaussError
    from warpgauss.field import limits
    from warpgauss.readers.synthetic import generate

    v = generate("vortex", 14)[:, :13, :12].copy()
    v[:, :2] = np.nan  # masked
    kw = dict(budget=60, iterations=8, device=cpu, seed=2, progress=False)
    whole = warpgauss.encode(v, **kw)
    monkeypatch.setattr(limits, "MAX_VOXELS", v.size - 1)
    with pytest.raises(WarpgaussError, match="--volume-on-host") as e:
        warpgauss.encode(v, **kw)
    assert "\n" not in str(e.value)
    host = warpgauss.encode(v, volume_on_host=True, **kw)
    np.testing.assert_array_equal(np.asarray(host.params), np.asarray(whole.params))
    monkeypatch.setattr(limits, "MAX_HOST_VOXELS", v.size - 1)
    with pytest.raises(WarpgaussError, match="--bricks"):
        warpgauss.encode(v, volume_on_host=True, **kw)


@pytest.mark.parametrize("masked", [False, True])
def test_normalised_into_host_memory_the_device_volume_holds_no_copy(cpu, monkeypatch, masked):
    """normalise(pinned=True) writes into Warp host arrays (page-locked where CUDA is available)
    whose numpy views are the field's values and mask: the same values, mask and counts as
    before, and the device volume reads those arrays as they are. Passes of a few slices each
    (analysis.SLAB_VOXELS lowered: at 2048^2 a pass holds 8 slices) count the same."""
    from warpgauss.field import analysis

    f0 = _volume((11, 9, 10)) if masked else normalise(np.random.default_rng(1).uniform(0, 1, (11, 9, 10)).astype(np.float32))
    src = analysis.denormalise(f0.values, f0.vmin, f0.vmax)
    if masked:
        src[~f0.mask] = np.nan
    plain = normalise(src)
    monkeypatch.setattr(analysis, "SLAB_VOXELS", 2 * 90)  # two slices a pass
    f = normalise(src, pinned=True)
    assert f.host_arrays is not None and np.shares_memory(f.values, f.host_arrays[0].numpy())
    assert f.values.tobytes() == plain.values.tobytes()
    assert (f.occupied, f.eligible, f.n_valid) == (plain.occupied, plain.eligible, plain.n_valid)
    assert (f.mask is None) == (not masked) and (plain.mask is None) == (not masked)
    dv = DeviceVolume(f, cpu)
    assert dv.values is f.host_arrays[0]
    if masked:
        np.testing.assert_array_equal(f.mask, plain.mask)
        assert dv.mask is f.host_arrays[1] and np.shares_memory(f.mask, dv.mask.numpy())


def test_a_file_read_into_memory_may_declare_what_the_host_path_indexes(tmp_path, monkeypatch):
    """A format read into memory (chunked HDF5) is refused past the in-core limit with the way
    out, and read where the caller indexes more (the volume in host memory)."""
    import h5py

    from warpgauss.errors import WarpgaussError
    from warpgauss.readers import common, read_volume

    p = tmp_path / "v.h5"
    with h5py.File(p, "w") as h:
        h.create_dataset("v", data=np.ones((6, 5, 4), np.float32), chunks=(2, 5, 4))
    monkeypatch.setattr(common, "MAX_READ_VOXELS", 100)
    with pytest.raises(WarpgaussError, match="--volume-on-host"):
        read_volume(p)
    assert read_volume(p, max_voxels=120).data.shape == (6, 5, 4)


def test_a_model_file_may_hold_a_grid_past_2_to_the_31():
    """A model of a 2048^3 grid (the host path's) is a valid header; past 2^37 it is not."""
    from warpgauss.format.model import _header_problem

    h = {
        "grid": {"shape_xyz": [2048] * 3, "spacing": [1.0] * 3, "origin": [0.0] * 3},
        "values": {"min": 0.0, "max": 1.0},
        "source": {"bytes": 4},
    }
    assert _header_problem(h) is None
    h["grid"]["shape_xyz"] = [8192, 8192, 8192]
    assert "more than" in _header_problem(h)


def test_a_whole_encode_on_the_64_bit_paths(cpu, monkeypatch):
    """A whole encode with the volume on the host (forced on the CPU device: the slabs, the wide
    loads, the draw ahead by a few threads, the held anchor targets) through the paths of a volume
    past 2^31 voxels: the wide loads split into rows of 3 groups give the model of one row bit for
    bit; every rank drawn with 64 bits (RANK32_MAX lowered to 10) gives a model of its own, finite
    and the same on a rerun."""
    import warpgauss
    from warpgauss.field import analysis
    from warpgauss.readers.synthetic import generate

    v = generate("vortex", 15)[:, :14, :13].copy()
    kw = dict(budget=80, iterations=12, device=cpu, seed=4, progress=False)
    plain_init = DeviceVolume.__init__

    def forced(self, f, dev, same_values=None, on_host=False):
        plain_init(self, f, dev, same_values=same_values, on_host=on_host)
        self.on_host = True

    monkeypatch.setattr(analysis.DeviceVolume, "__init__", forced)
    one_row = warpgauss.encode(v, volume_on_host=True, **kw)
    monkeypatch.setattr(draw, "FLAT4_COLUMNS", 3)
    split = warpgauss.encode(v, volume_on_host=True, **kw)
    np.testing.assert_array_equal(np.asarray(split.params), np.asarray(one_row.params))
    monkeypatch.setattr(draw, "RANK32_MAX", 10)
    wide = [warpgauss.encode(v, volume_on_host=True, **kw) for _ in range(2)]
    assert wide[0].n == split.n and np.isfinite(np.asarray(wide[0].params)).all()
    np.testing.assert_array_equal(np.asarray(wide[0].params), np.asarray(wide[1].params))
    assert not np.array_equal(np.asarray(wide[0].params), np.asarray(split.params))


@pytest.mark.parametrize("huge", [False, True])
def test_the_host_volume_is_registered_page_locked_after_it_is_written(monkeypatch, huge):
    """Where CUDA is available the host path's volume is normalised into ordinary memory on threads
    and then registered page-locked with the driver (field.slabs.page_locked): with a stand-in
    driver, one registration an array of its own pointer and size, portable and mapped; the Warp
    arrays share that memory and hold the normalised values; each registration is undone when its
    array goes; a refused registration falls back to a copy of the same values."""
    import gc

    from warpgauss.field import analysis, slabs

    calls: list[tuple] = []

    class Driver:
        rc = 0

        def cuCtxPushCurrent_v2(self, ctx):
            return 0

        def cuCtxPopCurrent_v2(self, out):
            return 0

        def cuMemHostRegister_v2(self, ptr, size, flags):
            calls.append(("register", ptr, size, flags))
            return self.rc

        def cuMemHostUnregister(self, ptr):
            calls.append(("unregister", ptr))
            return 0

    lib = Driver()
    monkeypatch.setattr(slabs, "_registers", lambda: True)
    monkeypatch.setattr(slabs, "_driver", lambda: lib)
    monkeypatch.setattr(slabs, "_context", lambda: 1)
    monkeypatch.setattr(slabs, "HUGE_PAGES", huge)  # the memory in transparent huge pages (an anonymous map) or not
    vol = np.random.default_rng(3).random((12, 9, 10)).astype(np.float32)
    vol[0, 0, :3] = np.nan
    plain = analysis.normalise(vol)
    f = analysis.normalise(vol, pinned=True)
    np.testing.assert_array_equal(f.values, plain.values)
    np.testing.assert_array_equal(f.mask, plain.mask)
    v, m = f.host_arrays
    assert np.shares_memory(v.numpy(), f.values) and np.shares_memory(m.numpy(), f.mask)
    if huge and hasattr(__import__("mmap"), "MADV_HUGEPAGE"):
        import mmap

        owner = f.values
        while isinstance(owner, np.ndarray):
            owner = owner.base
        assert isinstance(getattr(owner, "obj", owner), mmap.mmap)  # the values live in the anonymous map
    registered = [c[1:] for c in calls if c[0] == "register"]
    assert registered == [(f.values.ctypes.data, f.values.nbytes, 3), (f.mask.ctypes.data, f.mask.nbytes, 3)]
    del v, m
    f.host_arrays = None
    gc.collect()
    assert sorted(c[1] for c in calls if c[0] == "unregister") == sorted(r[0] for r in registered)
    lib.rc = 1  # the driver refuses: a copy
    g = analysis.normalise(vol, pinned=True)
    np.testing.assert_array_equal(g.host_arrays[0].numpy(), plain.values)
    assert not np.shares_memory(g.host_arrays[0].numpy(), g.values)
