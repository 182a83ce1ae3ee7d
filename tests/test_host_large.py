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
