"""In situ encoding (issue #21 part 3): device arrays taken without a host copy (a Warp array, a
DLPack producer, strided views, other dtypes, NaN/fill masks), normalised on the device exactly as
the host does, and the Encoder that keeps buffers and the previous model between calls."""

from __future__ import annotations

import numpy as np
import pytest

import warpgauss
from warpgauss.core.warp import warp
from warpgauss.errors import WarpgaussError
from warpgauss.readers import ReadOptions
from warpgauss.readers.synthetic import generate, generate_series

FAST = dict(budget=200, iterations=30, samples=256, self_test=False, format="full")


class Producer:
    """A foreign array that offers only DLPack (as a PyTorch or CuPy array does)."""

    def __init__(self, a: np.ndarray):
        self.a = a

    def __dlpack__(self, **kw):
        return self.a.__dlpack__(**kw)

    def __dlpack_device__(self):
        return self.a.__dlpack_device__()


class CudaArrayOnly:
    """A foreign array that offers only ``__cuda_array_interface__`` (as a Numba array does)."""

    def __init__(self, a: np.ndarray):
        self.a = a
        self.__cuda_array_interface__ = {
            "shape": a.shape,
            "typestr": a.dtype.str,
            "data": (a.ctypes.data, True),
            "strides": None,
            "version": 3,
        }


@pytest.fixture(scope="module")
def wp():
    return warp()


def _fields_equal(a, b):
    assert (a.vmin, a.vmax, a.occupied, a.eligible, a.n_valid) == (b.vmin, b.vmax, b.occupied, b.eligible, b.n_valid)
    np.testing.assert_array_equal(a.values[:], b.values if isinstance(b.values, np.ndarray) else b.values[:])
    if b.mask is None:
        assert a.mask is None
    else:
        np.testing.assert_array_equal(a.mask[:], b.mask)


@pytest.mark.parametrize("dtype", ["float32", "float64", "int16", "uint8"])
def test_device_normalisation_is_the_host_one(wp, dtype):
    from warpgauss.field.analysis import normalise
    from warpgauss.field.device import normalise_on_device

    v = generate("bubbles", 18)
    if dtype.startswith(("int", "uint")):
        src = np.round(v * 200).astype(dtype)
        fill = 0.0
    else:
        src = (v * 7.5 - 2.0).astype(dtype)
        src[2, 3, 4] = np.nan
        src[5, 5, 5] = np.inf
        src[1, 1, 1] = 0.25  # a fill value as the source's own precision holds it
        fill = 0.25
    host = normalise(src, fill_value=fill)
    dev = normalise_on_device(wp.array(src, device="cpu"), fill_value=fill)
    _fields_equal(dev, host)
    assert dev.mask is not None and host.mask is not None
    idx = np.array([0, 7, 18 * 18 * 18 - 1, 1000], np.int64)
    np.testing.assert_array_equal(dev.values.take_flat(idx), host.values.reshape(-1)[idx])
    np.testing.assert_array_equal(dev.mask.take_flat(idx), host.mask.reshape(-1)[idx])


def test_a_device_array_encodes_as_its_numpy_copy(wp):
    v = generate("vortex", 20)
    ref = warpgauss.encode(v, device="cpu", **FAST)
    for src in (wp.array(v, device="cpu"), Producer(v)):
        m = warpgauss.encode(src, **FAST)  # device None: the array's own
        np.testing.assert_array_equal(m.params, ref.params)  # same seed, same device: same model
        assert m.report["input"]["on_device"] == "cpu"
        assert m.report["psnr_db"] == ref.report["psnr_db"]
    cai = CudaArrayOnly(v)  # the __cuda_array_interface__ path, pointed at host memory for the CPU device
    np.testing.assert_array_equal(warpgauss.encode(cai, device="cpu", **FAST).params, ref.params)
    cai.__cuda_array_interface__["stream"] = 1  # a producer's stream: waited for on CUDA, nothing to wait for here
    np.testing.assert_array_equal(warpgauss.encode(cai, device="cpu", **FAST).params, ref.params)
    cai.__cuda_array_interface__["stream"] = 0
    with pytest.raises(WarpgaussError, match="stream 0"):
        warpgauss.encode(cai, device="cpu", **FAST)
    padded = np.zeros((22, 22, 22), np.float32)  # a simulation array with ghost cells: a strided view
    padded[1:-1, 1:-1, 1:-1] = v
    m = warpgauss.encode(wp.array(padded, device="cpu")[1:-1, 1:-1, 1:-1], **FAST)
    np.testing.assert_array_equal(m.params, ref.params)
    strided = warpgauss.encode(wp.array(v, device="cpu"), read=ReadOptions(stride=2), **FAST)
    assert tuple(strided.shape_xyz) == (10, 10, 10)


def test_device_arrays_are_refused_in_one_line(wp):
    with pytest.raises(WarpgaussError, match="2D"):
        warpgauss.encode(wp.zeros((4, 4), dtype=float, device="cpu"), **FAST)
    with pytest.raises(WarpgaussError, match="constant"):
        warpgauss.encode(wp.ones((8, 8, 8), dtype=float, device="cpu"), **FAST)
    with pytest.raises(WarpgaussError, match="no finite value"):
        warpgauss.encode(wp.array(np.full((8, 8, 8), np.nan, np.float32), device="cpu"), **FAST)
    with pytest.raises(WarpgaussError, match="--bricks takes a file"):
        warpgauss.encode(wp.zeros((8, 8, 8), dtype=float, device="cpu"), bricks="2x1x1", **FAST)
    if not wp.is_cuda_available():
        with pytest.raises(WarpgaussError, match="not available"):
            warpgauss.encode(wp.array(generate("vortex", 8), device="cpu"), device="cuda:0", **FAST)


def test_the_encoder_warm_starts_each_call_and_keeps_its_buffers(wp):
    steps = list(generate_series("vortex", 20, 3))
    enc = warpgauss.Encoder(start="warm", **FAST)
    models = [enc.encode(wp.array(v, device="cpu")) for v in steps]
    assert [m.n for m in models] == [200, 200, 200]
    assert [m.report["encoder"]["warm_start"] for m in models] == [False, True, True]
    assert [r.call for r in enc.calls] == [0, 1, 2]
    assert all(r.iterations == 30 and r.seconds >= r.refine_seconds > 0 for r in enc.calls)
    # one normalised buffer for every call: each field was written into the same device memory
    assert enc.session.buffers.values is not None and enc.session.buffers.values.shape == (20, 20, 20)
    # the encoder gives what encode(warm_start=previous) gives, call for call
    m1 = warpgauss.encode(steps[1], device="cpu", warm_start=models[0], **FAST)
    np.testing.assert_array_equal(models[1].params, m1.params)
    assert any(s["what"] == "S1a structure statistics" for s in models[1].report["skipped"])
    enc.reset()
    again = enc.encode(wp.array(steps[0], device="cpu"))
    np.testing.assert_array_equal(again.params, models[0].params)  # cold again: the first model
    cold = warpgauss.Encoder(start="cold", **FAST)
    assert [cold.encode(v).report["encoder"]["warm_start"] for v in steps[:2]] == [False, False]
    with pytest.raises(WarpgaussError, match="start='hot'"):
        warpgauss.Encoder(start="hot", **FAST)


def test_auto_start_goes_cold_when_the_field_moved_too_far():
    enc = warpgauss.Encoder(**FAST)  # start="auto"
    turning = list(generate_series("vortex", 20, 2, turn_degrees=1.0))
    first = enc.encode(turning[0])
    assert "start_choice" not in first.report  # the first call is cold anyway
    near = enc.encode(turning[1])
    choice = near.report["start_choice"]
    assert choice["warm"] and near.report["encoder"]["warm_start"]
    assert choice["warm_start_psnr_db"] >= choice["last_cold_start_psnr_db"]
    far = enc.encode(generate("bubbles", 20))  # another field on the same grid: the old model is no head start
    choice = far.report["start_choice"]
    assert not choice["warm"] and not far.report["encoder"]["warm_start"]
    assert choice["warm_start_psnr_db"] < choice["last_cold_start_psnr_db"]
    assert far.report["allocation"].get("warm_start") is None  # allocated afresh
    np.testing.assert_array_equal(far.params, warpgauss.encode(generate("bubbles", 20), device="cpu", **FAST).params)


def test_the_encoder_keeps_to_a_time_budget(wp, tmp_path):
    steps = list(generate_series("interface", 20, 3))
    enc = warpgauss.Encoder(budget=150, samples=256, self_test=False, format="full", time_budget=60.0)
    short = enc.encode(steps[0], time_budget=0.6, output=tmp_path / "t0.wgs")  # per-call override
    assert (tmp_path / "t0.wgs").is_file() and short.report["encoder"]["time_budget"] == 0.6
    assert short.report["refinement"]["time_budget"] is not None  # refinement was planned to the deadline
    # figures only the report would show are not paid for on a time budget: the statistics, the end estimate
    assert short.report["refinement"]["end_estimate"] == {}
    assert any(s["what"] == "end-of-training estimate" for s in short.report["skipped"])
    m = enc.encode(steps[1], time_budget=3.0)
    assert m.report["encoder"]["warm_start"] and m.report["refinement"]["time_budget"]["planned_iterations"] >= 1
    with pytest.raises(WarpgaussError, match="positive number of seconds"):
        enc.encode(steps[2], time_budget=0)
    with pytest.raises(WarpgaussError, match="budget= \\(N\\) or ratio="):
        warpgauss.Encoder()
    with pytest.raises(WarpgaussError, match="warm_start="):
        warpgauss.Encoder(budget=10, warm_start=None)


class TorchOnStream:
    """A PyTorch CUDA tensor offered only through ``__cuda_array_interface__`` version 3, naming the
    stream it was written on (as CuPy and Numba do; PyTorch's own dict names none)."""

    def __init__(self, t, stream):
        self.t = t
        self.__cuda_array_interface__ = {**t.__cuda_array_interface__, "version": 3, "stream": int(stream.cuda_stream)}


def test_a_producer_stream_is_waited_for_on_cuda(wp):
    """The field is written on a side stream behind a long GPU sleep; the encode reads it through
    __cuda_array_interface__ (which names that stream) without any host synchronisation, and must
    still see the finished field: the model equals the encode of the same field from the host."""
    torch = pytest.importorskip("torch")
    if not (wp.is_cuda_available() and torch.cuda.is_available()):
        pytest.skip("needs CUDA and PyTorch with CUDA (runs on the GPU machine, not in CI)")
    v = generate("vortex", 48)
    ref = warpgauss.encode(v, device="cuda:0", **FAST)
    src = torch.from_numpy(v).cuda()
    torch.cuda.synchronize()
    side = torch.cuda.Stream()
    with torch.cuda.stream(side):
        dst = torch.zeros_like(src)
        torch.cuda._sleep(200_000_000)  # ~0.1 s of GPU clock cycles before the field is written
        dst.copy_(src)
    arr = TorchOnStream(dst, side)
    assert arr.__cuda_array_interface__["stream"] not in (0, 1, 2)  # the side stream's handle
    m = warpgauss.encode(arr, device="cuda:0", **FAST)
    np.testing.assert_array_equal(m.params, ref.params)
