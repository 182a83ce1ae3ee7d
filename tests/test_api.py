"""The Python API: encode -> Model -> save/load/decode/psnr, determinism, the compact format."""

from __future__ import annotations

import numpy as np
import pytest

import warpgauss
from warpgauss.readers.synthetic import generate


@pytest.fixture(scope="module")
def interface32():
    return generate("interface", 32, seed=0)


def test_encode_array_roundtrip_decode_and_psnr(tmp_path, interface32, device):
    vol = interface32 * 40.0 - 7.0  # original units differ from [0, 1]
    m = warpgauss.encode(vol, budget=500, seed=3, device=device, iterations=0)
    assert isinstance(m, warpgauss.Model) and m.n == 500 and m.params.shape == (500, 12)
    assert m.value_range == pytest.approx((-7.0, 33.0), rel=1e-6)
    rep = m.report
    assert rep["budget"]["n"] == 500 and rep["seed"] == 3
    assert rep["evaluation"]["final"]["mode"] == "full grid"  # 32^3 < 500,000 voxels
    path = tmp_path / "m.wgs"
    assert m.save(path) == path.stat().st_size == m.report["budget"]["bytes"] < 12 * 500  # coded by default
    loaded = warpgauss.Model.load(path)
    assert loaded.params.tobytes() == m.params.tobytes()  # the returned model is the stored one
    assert m.save(tmp_path / "f.wgs", encoding="float32") == 48 * 500 + 4096
    dec = loaded.decode(device=device)
    assert dec.shape == vol.shape and dec.dtype == np.float32
    # decode returns original units; PSNR is computed on the normalised field
    mse = np.mean(((dec - vol) / 40.0) ** 2, dtype=np.float64)
    assert warpgauss.psnr(loaded, vol, device=device) == pytest.approx(10 * np.log10(1 / mse), abs=0.01)
    assert rep["psnr_db"] == pytest.approx(10 * np.log10(1 / mse), abs=0.01)
    half = loaded.decode(shape_xyz=(16, 16, 16), device=device)
    assert half.shape == (16, 16, 16)


def test_same_seed_same_device_gives_the_same_model(interface32, cpu):
    device = cpu  # bit-identical on CPU; GPU atomics reorder float sums (see README)
    kw = dict(budget=400, device=device, evaluate=False, iterations=20, samples=256)
    a = warpgauss.encode(interface32, seed=7, **kw)
    b = warpgauss.encode(interface32, seed=7, **kw)
    c = warpgauss.encode(interface32, seed=8, **kw)
    assert a.params.tobytes() == b.params.tobytes()
    assert not np.array_equal(a.params, c.params)


def test_compact_file_is_12_bytes_per_primitive_and_close_in_psnr(tmp_path, interface32):
    m = warpgauss.encode(interface32, budget=600, device=None, iterations=0)
    full = tmp_path / "full.wgs"
    compact = tmp_path / "compact.wgs"
    m.save(full)
    size = m.save(compact, compact=True)
    assert size == 12 * 600 + 4096 == m.file_size(compact=True)
    mc = warpgauss.Model.load(compact)
    assert mc.header["payload"]["encoding"] == "compact96"
    p_full = warpgauss.psnr(warpgauss.Model.load(full), interface32, device=None)
    p_compact = warpgauss.psnr(mc, interface32, device=None)
    assert p_full - 0.5 < p_compact < p_full + 0.5


def test_ratio_and_stride_and_fill_value(tmp_path):
    vol = generate("bubbles", 48, seed=1).astype(np.float64)
    vol[:, :, :8] = -1.0e30  # a fill region ("land")
    m = warpgauss.encode(
        vol,
        ratio=10,
        device=None,
        iterations=60,
        samples=512,
        read=warpgauss.readers.ReadOptions(stride=2, fill_value=-1.0e30),
        format="full",
    )
    src = 24**3 * 8  # float64 source at the evaluated (strided) resolution
    assert m.report["budget"]["n"] == int(np.floor((src / 10 - 4096) / 48))
    assert m.shape_xyz == (24, 24, 24) and m.header["grid"]["spacing"] == [2.0, 2.0, 2.0]
    assert m.value_range[0] >= 0.0  # the fill value never entered the min/max
    assert m.report["input"]["masked_voxels"] == 24 * 24 * 4
    assert np.all(m.params[:, 0] > 3.5 - 0.5)  # nothing seeded on the masked columns (x < 4)


def test_iterations_zero_is_the_analytic_model_and_presets_resolve(interface32):
    m = warpgauss.encode(interface32, budget=100, iterations=0, device=None, evaluate=False)
    assert any(s["what"] == "S2 refinement" for s in m.report["skipped"])
    from warpgauss.encoding.driver import resolve_refine

    assert (resolve_refine(None, "fast", None, None).iterations, resolve_refine(None, "fast", None, None).samples) == (300, 3072)
    assert resolve_refine(None, "quality", 10, None).iterations == 10  # explicit beats the preset
    with pytest.raises(warpgauss.WarpgaussError, match="unknown preset"):
        resolve_refine(None, "best", None, None)


def test_written_files_get_the_usual_permissions(tmp_path):
    import os
    import stat

    from warpgauss.core.files import atomic_write_bytes

    old = os.umask(0o022)
    try:
        atomic_write_bytes(tmp_path / "x.json", b"{}")
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "x.json").stat().st_mode) == 0o644  # not mkstemp's 0600


def test_a_refinement_that_loses_to_the_analytic_model_is_discarded():
    """A learning rate of 1 wrecks 20 iterations: the encoder keeps the better, analytic model and
    says so in the report (a user asked for the most accurate model of this size)."""
    import numpy as np

    import warpgauss
    from warpgauss.encoding.refine import RefineConfig
    from warpgauss.readers.synthetic import generate

    vol = generate("vortex", 24)
    bad = warpgauss.encode(vol, budget=300, refine=RefineConfig(iterations=20, samples=512, lr=1.0), device="cpu", seed=0)
    ev = bad.report["evaluation"]
    assert ev["discarded_refined"]["psnr_db"] < ev["analytic"]["psnr_db"]
    assert ev["final"] == ev["analytic"] and ev["gain_db"] == 0.0
    assert any(s["what"] == "refined model" for s in bad.report["skipped"])
    analytic = warpgauss.encode(vol, budget=300, iterations=0, device="cpu", seed=0)
    np.testing.assert_array_equal(bad.params, analytic.params)


def test_large_budgets_get_more_samples_by_default_and_presets_keep_theirs(monkeypatch):
    from warpgauss.encoding.driver import resolve_refine
    from warpgauss.encoding.refine import AUTO_BATCH_PRIMITIVES, PRESETS, RefineConfig, config

    cfg = RefineConfig()
    assert cfg.for_budget(1_400_000).samples == 4 * 3072  # the measured quality setting at 1.4M
    assert cfg.for_budget(AUTO_BATCH_PRIMITIVES).samples == 3072
    assert cfg.for_budget(AUTO_BATCH_PRIMITIVES + 1).samples == 2 * 3072
    assert cfg.for_budget(10**9).samples == config.AUTO_MAX_BATCHES * 3072
    for name in ("paper", "quality"):  # these presets are exactly their settings
        assert resolve_refine(None, name, None, None).for_budget(1_400_000).samples == PRESETS[name]["samples"]
    # fast is the default's sampling for 300 iterations: raised for large budgets as the default is
    assert resolve_refine(None, "fast", None, None).for_budget(1_400_000).samples == 4 * 3072
    assert resolve_refine(None, None, None, 5000).for_budget(1_400_000).samples == 5000  # explicit samples stay
    assert resolve_refine(None, None, 0, None).for_budget(1_400_000).samples == 3072  # nothing to refine

    # the pipeline applies it (batch size lowered so a CPU test reaches it), records it in the
    # header and the report, and a --ratio budget still fits its size
    monkeypatch.setattr(config, "AUTO_BATCH_PRIMITIVES", 100)
    vol = generate("vortex", 24, seed=0)
    m = warpgauss.encode(vol, budget=250, iterations=2, device="cpu", evaluate=False, self_test=False)
    assert m.report["refinement"]["samples"] == 3 * 3072 and m.header["encoding"]["samples"] == 3 * 3072
    p = warpgauss.encode(vol, budget=250, iterations=2, device="cpu", evaluate=False, self_test=False, preset="paper")
    assert p.report["refinement"]["samples"] == 3072 and p.header["encoding"]["samples"] == 3072
    r = warpgauss.encode(vol, ratio=5, iterations=2, device="cpu", evaluate=False, self_test=False)
    assert r.report["refinement"]["samples"] > 3072 and r.report["budget"]["bytes"] <= vol.nbytes / 5


def test_save_replaces_a_file_as_numpy_does_and_refuses_only_when_asked(tmp_path):
    """Python's Model.save writes where it is told (the bounded guide's snippet after the README's,
    both saving v.wgs, lost a 142 s encode to a refusal at the end); force=False refuses, naming
    the Python way to overwrite, and leaves the file as it was."""
    m = warpgauss.encode(generate("vortex", 16), budget=40, iterations=0, device="cpu", self_test=False)
    path = tmp_path / "v.wgs"
    path.write_bytes(b"an earlier file")
    assert m.save(path) == path.stat().st_size and warpgauss.Model.load(path).n == m.n
    before = path.read_bytes()
    with pytest.raises(warpgauss.WarpgaussError, match="force=True from Python"):
        m.save(path, force=False, encoding="float32")
    assert path.read_bytes() == before


def test_psnr_of_a_decoded_grid_against_the_volume(tmp_path):
    """warpgauss.psnr(grid, volume) on two arrays used to raise a bare AttributeError: now the
    decoded grid scores as the model does on the full grid, and a wrong shape or type is one line."""
    vol = generate("vortex", 16)
    m = warpgauss.encode(vol, budget=60, iterations=0, device="cpu", self_test=False)
    grid = m.decode(device="cpu")
    assert abs(warpgauss.psnr(grid, vol) - warpgauss.psnr(m, vol, full=True, device="cpu")) < 0.05
    with pytest.raises(warpgauss.WarpgaussError, match="is not the volume's"):
        warpgauss.psnr(grid[:-1], vol)
    with pytest.raises(warpgauss.WarpgaussError, match="psnr takes a Model"):
        warpgauss.psnr([1, 2], vol)


def test_python_encodes_show_progress_where_asked_and_stay_quiet_in_logs(capsys):
    """progress=True prints refinement's progress on one line of standard error, ended when the
    encode ends; the default is quiet where no person watches (pytest's captured stream)."""
    vol = generate("vortex", 12)
    warpgauss.encode(vol, budget=30, iterations=60, samples=256, device="cpu", self_test=False, progress=True)
    err = capsys.readouterr().err
    assert "warpgauss: refining, iteration 25 of 60" in err and "iteration 60 of 60" in err and err.endswith("\n")
    assert err.count("\n") == 1  # one line, rewritten in place
    warpgauss.encode(vol, budget=30, iterations=30, samples=256, device="cpu", self_test=False)
    assert "refining" not in capsys.readouterr().err


def test_decode_takes_the_returned_arrays_shape_and_warns_on_the_old_order():
    """decode(shape_zyx=g.shape) returns an array of g's shape; shape_xyz is the command line's
    order; the positional (x, y, z) shape still works this release, with a DeprecationWarning that
    says what to write; two of them at once are refused."""
    vol = generate("vortex", (9, 7, 5))  # (x, y, z): the array is (5, 7, 9)
    m = warpgauss.encode(vol, budget=30, iterations=0, device="cpu", self_test=False)
    g = np.zeros((4, 6, 8))
    a = m.decode(shape_zyx=g.shape, device="cpu")
    assert a.shape == g.shape
    b = m.decode(shape_xyz=(8, 6, 4), device="cpu")
    np.testing.assert_array_equal(a, b)
    with pytest.warns(DeprecationWarning, match=r"write decode\(shape_zyx=\(nz, ny, nx\)\)"):
        c = m.decode((8, 6, 4), device="cpu")
    np.testing.assert_array_equal(a, c)
    with pytest.raises(warpgauss.WarpgaussError, match="give one of shape_zyx"):
        m.decode(shape_zyx=g.shape, shape_xyz=(8, 6, 4), device="cpu")
    assert m.decode(device="cpu").shape == vol.shape


def test_compression_ratio_is_a_property_as_n_is_and_the_old_call_warns(tmp_path):
    """Model.compression_ratio was a method beside the property Model.n (issue #57 item 7): now a
    property, the ratio of the file save() writes (as info reports it); the call still answers
    this release, as it did (full precision by default), with a DeprecationWarning saying what to
    write."""
    import json
    import warnings

    vol = generate("vortex", 16)
    m = warpgauss.encode(vol, budget=40, iterations=0, device="cpu", self_test=False)
    assert m.format == "coded"
    coded = m.save(tmp_path / "c.wgs")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # reading the property warns of nothing
        ratio = m.compression_ratio
    assert ratio == vol.nbytes / coded and isinstance(ratio, float) and json.loads(json.dumps({"r": ratio}))["r"] == ratio
    loaded = warpgauss.Model.load(tmp_path / "c.wgs")
    assert loaded.compression_ratio == ratio
    full = warpgauss.Model(m.params, m.header)  # no format: save() writes float32
    assert full.compression_ratio == vol.nbytes / full.save(tmp_path / "f.wgs") == vol.nbytes / (48 * 40 + 4096)
    with pytest.warns(DeprecationWarning, match=r"write model\.compression_ratio .* model\.source_bytes / model\.file_size"):
        old = m.compression_ratio()
    assert old == vol.nbytes / m.file_size(False) == full.compression_ratio  # what the call gave: full precision
    with pytest.warns(DeprecationWarning):
        assert m.compression_ratio(encoding="coded") == ratio and m.compression_ratio(True) == vol.nbytes / m.file_size(True)
