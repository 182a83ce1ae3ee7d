"""A volume in host memory (``--volume-on-host``, ``DeviceVolume(on_host=True)``): the paths that
read it differently from a volume on the device give the same model bit for bit. On a CUDA device
the values sit in pinned host memory and the kernels read them over the bus; here the CPU device
stands in, with ``on_host`` forced, so that the slab copies and the wide loads run and are compared
against the plain path."""

from __future__ import annotations

import numpy as np
import pytest
from test_allocate import _blobs

import warpgauss
from warpgauss.core.profiling import StageRecorder
from warpgauss.encoding.allocate import AllocationConfig, allocate
from warpgauss.encoding.refine import draw
from warpgauss.encoding.refine.draw import Sampler
from warpgauss.field import analysis
from warpgauss.field.analysis import DeviceVolume, normalise
from warpgauss.readers.synthetic import generate


@pytest.mark.parametrize("masked", [False, True])
def test_seed_frames_by_slabs_equal_the_whole_volume(device, masked, monkeypatch):
    """A volume in host memory has its seeds' frames worked out a slab of slices at a time on the
    device (warpgauss.field.slabs): with slabs of a few slices each, the model is the same bit for
    bit as with the whole volume on the device (the CPU device stands in for the bus here)."""
    from warpgauss.field import slabs

    v = _blobs(24, seed=7, plateau=False)
    if masked:
        v[:3] = -999.0  # the first slices are "land": a mask whose edge a slab boundary crosses
    f = normalise(v, fill_value=-999.0 if masked else None)
    whole = DeviceVolume(f, device)
    a, _ = allocate(whole, 400, seed=3, config=AllocationConfig(), timer=StageRecorder())
    host = DeviceVolume(f, device)
    host.on_host = True  # the slab path (on a CUDA device: pinned memory read a slab at a time)
    ranges = slabs.slab_ranges(v.shape, 5, 24 * 24 * 4 * 13)
    assert len(ranges) == 8 and ranges[-1][1] == 24  # 3 slices of their own each, 5 either side
    monkeypatch.setattr(slabs, "SLAB_BYTES", 24 * 24 * 4 * 13)
    b, _ = allocate(host, 400, seed=3, config=AllocationConfig(), timer=StageRecorder())
    assert a.tobytes() == b.tobytes()
    monkeypatch.setattr(slabs, "SLAB_BYTES", 1)  # one slice of its own a slab
    c, _ = allocate(host, 400, seed=3, config=AllocationConfig(), timer=StageRecorder())
    assert a.tobytes() == c.tobytes()


def test_slab_groups_cover_every_index_once():
    from warpgauss.field.slabs import by_slab, slab_ranges

    rng = np.random.default_rng(0)
    z = rng.integers(0, 40, 500)
    ranges = slab_ranges((40, 8, 8), 2, 8 * 8 * 4 * 9)
    assert ranges[0] == (0, 5) and ranges[-1] == (35, 40)
    groups = by_slab(z, ranges)
    assert np.array_equal(np.sort(np.concatenate(groups)), np.arange(500))
    for (lo, hi), g in zip(ranges, groups):
        assert np.all((z[g] >= lo) & (z[g] < hi)) and np.all(np.diff(g) > 0)


@pytest.mark.parametrize("shape,masked", [((23, 19, 21), False), ((20, 22, 18), True)])
def test_an_encode_with_the_volume_on_host_is_the_same_model(device, monkeypatch, shape, masked):
    """A whole encode (the seeds' frames by slabs, each draw's corners read a row pair at a time
    from the volume viewed as groups of four, the voxel's own value taken from them, each
    iteration's samples drawn during the iteration before by a few threads striding over them, the
    anchor targets read at each re-bin and held) gives the same model bit for bit as with the
    volume on the device and its anchor targets held alike: sizes that are not multiples of four
    (a row's pair split between two groups, a tail past the last whole group), a mask, jittered
    samples with importance weights and an error stratum (the defaults)."""
    from warpgauss.encoding.refine import update
    from warpgauss.field import slabs

    v = generate("vortex", max(shape))[: shape[0], : shape[1], : shape[2]].copy()
    if masked:
        v[:, :4] = np.nan  # not finite: masked
    kw = dict(budget=120, iterations=25, device=device, seed=5, progress=False)
    monkeypatch.setattr(update, "ANCHOR_CACHE", "always")
    whole = warpgauss.encode(v, **kw)
    monkeypatch.setattr(update, "ANCHOR_CACHE", "host")  # the default: held where the volume is on the host
    plain_init = DeviceVolume.__init__

    def forced(self, f, dev, same_values=None, on_host=False):
        plain_init(self, f, dev, same_values=same_values, on_host=on_host)
        self.on_host = True

    taken = []
    plain_take = Sampler.take

    def counted(self):
        taken.append(self.version)
        plain_take(self)

    monkeypatch.setattr(analysis.DeviceVolume, "__init__", forced)
    monkeypatch.setattr(slabs, "SLAB_BYTES", shape[1] * shape[2] * 4 * 12)
    monkeypatch.setattr(Sampler, "take", counted)
    monkeypatch.setattr(draw, "DRAW_AHEAD", True)  # the default
    monkeypatch.setattr(draw, "DRAW_THREADS_HOST", 7)  # each thread draws every 7th sample
    host = warpgauss.encode(v, **kw)
    assert host.n == whole.n
    np.testing.assert_array_equal(np.asarray(host.params), np.asarray(whole.params))
    # drawn one iteration ahead everywhere but the first iteration and the re-bins (every 10th):
    # there the support marks and the error quota change, and the staged draw is dropped
    assert len(taken) == kw["iterations"] - 3


def test_a_device_peak_is_this_encodes_or_unknown(monkeypatch):
    """Warp's CUDA memory pool keeps one high-water mark for the process: a stage reports it only
    where it rose above the mark when the recorder's device was set, so a second encode in one
    process never reports the first one's peak as its own (this session's 512^3 host-volume row
    did: both rows 1.417 GB)."""
    from warpgauss.core.profiling import StageRecorder

    marks = iter([5_000, 5_000, 7_000])  # the mark when the device is set, after stage a, after stage b

    class Pool:
        @staticmethod
        def get_mempool_used_mem_high(device):
            return next(marks)

        @staticmethod
        def synchronize_device(device):
            pass

    import warpgauss.core.warp as core_warp

    monkeypatch.setattr(core_warp, "warp", lambda: Pool)
    t = StageRecorder(device="cuda:0")
    with t.stage("a", "below an earlier encode's mark"):
        pass
    with t.stage("b", "above it"):
        pass
    assert [s.device_peak_bytes for s in t.stages] == [None, 7_000]
    assert StageRecorder().stages == [] and StageRecorder(device="cpu")._device_peak() is None
