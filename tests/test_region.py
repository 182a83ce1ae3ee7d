"""A region at any resolution (issue #56 part 1): ``Model.decode(box=...)`` and ``warpgauss decode
--box`` equal the crop of a whole decode at the same sampling, sample where the float64 reference
says, apply a bounded residual only on the encoded grid, and refuse bad boxes before any work."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import random_params
from reference.field_ref import field as dense_field
from test_cli import assert_refused, cli

import warpgauss
from warpgauss.errors import WarpgaussError
from warpgauss.field.gaussians import GaussianField
from warpgauss.field.region import box_shape, check_box, parse_box, sampling, spacing_origin
from warpgauss.format.model import Model, make_header

SHAPE = (20, 16, 12)  # the model grid (x, y, z)


def _model(params, shape=SHAPE, spacing=(0.5, 2.0, 1.25), origin=(-3.0, 1.0, 7.0)) -> Model:
    h = make_header(
        shape_xyz=shape,
        spacing=spacing,
        origin=origin,
        vmin=-2.0,
        vmax=6.0,
        source_dtype="float32",
        source_itemsize=4,
        name="rho",
        encoding={},
        seed=0,
    )
    return Model(params, h)


@pytest.fixture(scope="module")
def params():
    return random_params(np.random.default_rng(11), 200, SHAPE, log_scale=(-0.3, 1.0), aniso=2.0)


def _aligned(whole_shape, voxels):
    """The box of voxels [I0, I1) per axis of a whole decode at ``whole_shape``, and its shape."""
    box = tuple((i0 * SHAPE[a] / whole_shape[a], i1 * SHAPE[a] / whole_shape[a]) for a, (i0, i1) in enumerate(voxels))
    return box, tuple(i1 - i0 for i0, i1 in voxels)


def _crop(grid, voxels):
    (x0, x1), (y0, y1), (z0, z1) = voxels
    return grid[z0:z1, y0:y1, x0:x1]


CASES = [
    ((80, 64, 48), ((17, 61), (5, 40), (30, 48))),  # 4x finer: a box reaching the far corner
    ((30, 24, 36), ((4, 25), (3, 20), (7, 30))),  # 1.5x, 1.5x, 3x: fractional bounds in model voxels
    ((13, 16, 5), ((2, 11), (0, 16), (1, 4))),  # coarser than the model along x and z
    (SHAPE, ((3, 9), (0, 1), (11, 12))),  # the encoded grid: integer bounds, a one-voxel-thin box
]


@pytest.mark.parametrize("path", ["brick lists", "cell walk"])
@pytest.mark.parametrize("whole_shape, voxels", CASES)
def test_a_box_decodes_to_the_crop_of_the_whole_decode_bit_for_bit(device, params, whole_shape, voxels, path, monkeypatch):
    """Both evaluation paths (the brick lists, and the cell walk a slab takes when its lists would
    not fit) give a box exactly the values of the whole decode at the same sampling."""
    from warpgauss.field import gaussians as wf

    if path == "cell walk":
        monkeypatch.setattr(wf, "MAX_BRICK_LIST", 0)
    gf = GaussianField(params, SHAPE, device)
    whole = gf.decode(whole_shape)
    box, shape = _aligned(whole_shape, voxels)
    got = gf.decode(shape, box=box)
    expect = _crop(whole, voxels)
    assert got.shape == expect.shape and np.count_nonzero(expect) > expect.size // 4
    np.testing.assert_array_equal(got, expect)


def test_model_decode_of_a_box_is_the_crop_in_source_units_and_its_geometry_too(params):
    m = _model(params)
    whole_shape, voxels = CASES[0]
    box, shape = _aligned(whole_shape, voxels)
    whole = m.decode(shape_xyz=whole_shape, device="cpu")
    info: dict = {}
    got = m.decode(shape_xyz=shape, box=box, device="cpu", info=info)
    np.testing.assert_array_equal(got, _crop(whole, voxels))
    assert info["residual_applied"] is False and info["bricks_evaluated_share"] is None
    nz, ny, nx = shape[::-1]
    np.testing.assert_array_equal(m.decode(shape_zyx=(nz, ny, nx), box=box, device="cpu"), got)  # the array's order
    # the box's first voxel is voxel (17, 5, 30) of the whole decode: spacing equal, origin that voxel's centre
    sp_whole, org_whole = np.array(m.decoded_spacing(whole_shape)), np.array(m.decoded_origin(whole_shape))
    np.testing.assert_allclose(m.decoded_spacing(shape, box), sp_whole, rtol=1e-12)
    np.testing.assert_allclose(m.decoded_origin(shape, box), org_whole + sp_whole * [17, 5, 30], rtol=1e-12)
    # the whole extent as a box is the whole decode, geometry included
    full = ((0, SHAPE[0]), (0, SHAPE[1]), (0, SHAPE[2]))
    np.testing.assert_array_equal(m.decode(shape_xyz=whole_shape, box=full, device="cpu"), whole)
    assert m.decoded_origin(whole_shape, full) == m.decoded_origin(whole_shape)
    np.testing.assert_allclose(m.decoded_spacing(whole_shape, full), m.decoded_spacing(whole_shape), rtol=1e-15)


def test_a_box_at_any_resolution_samples_where_the_float64_reference_says(params):
    """Fractional bounds at an unrelated resolution: output voxel i sits at
    x0 - 0.5 + (i + 0.5)(x1 - x0)/n, and its value is the dense float64 field there."""
    gf = GaussianField(params, SHAPE, "cpu")
    box = ((2.25, 13.5), (0.0, 7.75), (4.4, 11.9))
    shape = (17, 9, 11)
    got = gf.decode(shape, box=box)
    axes = [box[a][0] - 0.5 + (np.arange(shape[a]) + 0.5) * (box[a][1] - box[a][0]) / shape[a] for a in range(3)]
    z, y, x = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    ref = dense_field(params, np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1))[0]
    ref = np.clip(ref, 0.0, 1.0).reshape(got.shape)  # a decode clamps to [0, 1]
    assert np.count_nonzero(ref) > ref.size // 2
    np.testing.assert_allclose(got, ref, rtol=2e-5, atol=2e-5)


def test_the_sampling_is_the_whole_decodes_and_snaps_bounds_written_in_decimal():
    model = (20, 16, 12)
    assert sampling(None, (40, 16, 5), model) == ((0.5, 1.0, 2.4), (0.0, 0.0, 0.0))
    # one third of a voxel written in decimal: the whole 60-voxel grid's scale and an integer offset
    scale, offset = sampling(((3.3333333333333, 10.0), (0, 16), (0, 12)), (20, 16, 12), model)
    assert scale[0] == 20 / 60 and offset[0] == 10.0 and scale[1:] == (1.0, 1.0) and offset[1:] == (0.0, 0.0)
    # off any whole grid: left as given
    scale, offset = sampling(((1.05, 2.2), (0, 16), (0, 12)), (3, 16, 12), model)
    assert scale[0] == (2.2 - 1.05) / 3 and offset[0] == 1.05 / scale[0]
    # a box's geometry: the centre of its first voxel and its spacing in physical units
    h = {"grid": {"shape_xyz": [20, 16, 12], "spacing": [2.0, 1.0, 1.0], "origin": [10.0, 0.0, 0.0]}}
    sp, org = spacing_origin(h, ((4, 8), (0, 16), (0, 12)), (8, 16, 12))
    assert sp == (1.0, 1.0, 1.0) and org == (10.0 + 2.0 * (4 - 0.5 + 0.25), 0.0, 0.0)


@pytest.mark.parametrize(
    "box, says",
    [
        (((0, 4), (0, 4)), "three pairs"),
        ("0:4,0:4,0:4", "three pairs"),
        (((0, 4), (0, 4), (0, float("nan"))), "three pairs"),
        (((0, True), (0, 4), (0, 4)), "three pairs"),
        (((4, 4), (0, 4), (0, 4)), "x range 4:4 is empty"),
        (((0, 4), (5, 2), (0, 4)), "y range 5:2 is empty"),
        (((0, 4), (0, 4), (-1, 4)), "z range -1:4 reaches outside the model's extent 0:12"),
        (((0, 20.5), (0, 4), (0, 4)), "x range 0:20.5 reaches outside the model's extent 0:20"),
    ],
)
def test_a_bad_box_is_refused_in_one_line_before_any_work(params, box, says, monkeypatch):
    m = _model(params)
    monkeypatch.setattr(Model, "field", lambda *a, **k: pytest.fail("the model was evaluated"))
    with pytest.raises(WarpgaussError, match=says) as e:
        m.decode(box=box, device="cpu")
    assert "\n" not in str(e.value)


def test_a_box_needs_a_shape_unless_on_whole_voxels_and_a_shape_of_zero_is_refused(params, monkeypatch):
    m = _model(params)
    monkeypatch.setattr(Model, "field", lambda *a, **k: pytest.fail("the model was evaluated"))
    with pytest.raises(WarpgaussError, match="does not lie on the encoded grid's voxels.*give its output shape"):
        m.decode(box=((0.5, 4), (0, 4), (0, 4)), device="cpu")
    with pytest.raises(WarpgaussError, match="three positive sizes"):
        m.decode(shape_xyz=(4, 0, 4), box=((0, 4), (0, 4), (0, 4)), device="cpu")
    assert box_shape(check_box(((1, 4), (2, 4), (0, 12)), SHAPE)) == (3, 2, 12)


def test_parse_box_reads_the_command_lines_form_and_refuses_the_rest():
    assert parse_box("0:4, 2.5:8,-1:3") == ((0.0, 4.0), (2.5, 8.0), (-1.0, 3.0))
    for bad in ("0:4,0:4", "0:4,0:4,0:4,0:4", "0-4,0:4,0:4", "0:4:8,0:4,0:4", "a:4,0:4,0:4", "0:inf,0:4,0:4", ""):
        with pytest.raises(WarpgaussError, match="--box must be x0:x1,y0:y1,z0:z1"):
            parse_box(bad)


# -- a bounded residual: on the encoded grid only --------------------------------------------------
@pytest.fixture(scope="module")
def bounded(tmp_path_factory):
    d = tmp_path_factory.mktemp("region")
    rng = np.random.default_rng(3)
    z, y, x = np.meshgrid(np.linspace(-1, 1, 12), np.linspace(-1, 1, 14), np.linspace(-1, 1, 16), indexing="ij")
    vol = (800 * np.exp(-4 * (x * x + y * y + z * z)) + rng.normal(0, 5, x.shape)).astype(np.int16)
    warpgauss.encode(vol, budget=60, iterations=10, device="cpu", max_error=2.0, output=d / "b.wgs", self_test=False)
    return d, vol, Model.load(d / "b.wgs")


def test_a_box_on_the_encoded_grid_keeps_the_bound_elsewhere_the_gaussians_alone_say_so(bounded):
    _, vol, m = bounded
    box = ((3, 11), (2, 14), (5, 12))
    info: dict = {}
    got = m.decode(box=box, device="cpu", info=info)
    assert info["residual_applied"] is True and got.dtype == np.int16 and got.shape == (7, 12, 8)
    np.testing.assert_array_equal(got, m.decode(device="cpu")[5:12, 2:14, 3:11])
    assert np.abs(got.astype(int) - vol[5:12, 2:14, 3:11]).max() <= 2
    # off the encoded grid (a finer sampling, or fractional bounds): the Gaussians alone, said in info
    for shape, b in (((16, 24, 14), box), ((5, 5, 5), ((3.5, 11), (2, 14), (5, 12)))):
        info = {}
        alone = m.decode(shape_xyz=shape, box=b, device="cpu", info=info)
        assert info["residual_applied"] is False and alone.dtype == np.float32
        np.testing.assert_array_equal(alone, m.decode(shape_xyz=shape, box=b, device="cpu", residual=False))
        with pytest.raises(WarpgaussError, match="give a box of whole voxels without --shape"):
            m.decode(shape_xyz=shape, box=b, device="cpu", residual=True)
    info = {}
    assert m.decode(box=box, device="cpu", residual=False, info=info).dtype == np.float32 and info["residual_applied"] is False
    # to_pyvista says it in its field data
    assert int(m.to_pyvista(box=box, device="cpu").field_data["residual_applied"][0]) == 1
    assert int(m.to_pyvista((16, 24, 14), box, device="cpu").field_data["residual_applied"][0]) == 0


# -- the command line ---------------------------------------------------------------------------------
def test_cli_decode_box_writes_the_crop_and_its_geometry(bounded, tmp_path):
    import pyvista as pv

    d, _, m = bounded
    whole, part = tmp_path / "whole.npy", tmp_path / "part.vti"
    assert cli("decode", d / "b.wgs", "-o", whole, "--shape", "32x28x24", "--device", "cpu").exit_code == 0
    r = cli("decode", d / "b.wgs", "-o", part, "--box", "2:10,0.5:4,3:6", "--shape", "16x7x6", "--device", "cpu")
    assert r.exit_code == 0, r.output
    assert "box 2:10,0.5:4,3:6" in r.stdout and "the Gaussians alone" in r.stdout
    img = pv.read(part)
    assert tuple(img.dimensions) == (16, 7, 6)
    got = np.asarray(img.active_scalars).reshape(6, 7, 16)  # x fastest
    np.testing.assert_array_equal(got, np.load(whole)[6:12, 1:8, 4:20])
    box = ((2, 10), (0.5, 4), (3, 6))
    np.testing.assert_allclose(img.origin, m.decoded_origin((16, 7, 6), box), rtol=1e-12)
    np.testing.assert_allclose(img.spacing, m.decoded_spacing((16, 7, 6), box), rtol=1e-12)
    on_grid = tmp_path / "on_grid_8x3x3_int16.raw"
    r = cli("decode", d / "b.wgs", "-o", on_grid, "--box", "2:10,1:4,3:6", "--device", "cpu")
    assert r.exit_code == 0 and "within 2 of the source" in r.stdout, r.output
    np.testing.assert_array_equal(np.fromfile(on_grid, "<i2").reshape(3, 3, 8), m.decode(device="cpu")[3:6, 1:4, 2:10])


@pytest.mark.parametrize(
    "args, says",
    [
        (["--box", "0:4,0:4"], "--box must be x0:x1,y0:y1,z0:z1"),
        (["--box", "0:4,0:4,zero:4"], "--box must be"),
        (["--box", "0:4,0:4,0:40"], "z range 0:40 reaches outside the model's extent 0:12"),
        (["--box", "0:4,3:3,0:4"], "y range 3:3 is empty"),
        (["--box", "0:4,0:4,0.5:4"], "give its output shape"),
        (["--box", "0:4,0:4,0:4", "--shape", "4x0x4"], "--shape"),
        (["--box", "0:4,0:4,0:4", "--shape", "8x8x8", "--residual"], "give a box of whole voxels without --shape"),
    ],
)
def test_cli_decode_refuses_a_bad_box_in_one_line_before_the_decode(bounded, tmp_path, args, says, monkeypatch):
    d, _, _ = bounded
    monkeypatch.setattr(GaussianField, "decode", lambda *a, **k: pytest.fail("the model was decoded"))
    out = tmp_path / "out.npy"
    assert_refused(cli("decode", d / "b.wgs", "-o", out, *args, "--device", "cpu"), says)
    assert not out.exists()


def test_the_region_benchmark_runs_on_the_cpu_at_tiny_sizes(tmp_path):
    """benchmarks/decode/region.py (GPU sizes by default) with tiny CPU flags: a table, a JSON that
    says where and when it ran, the box at zoom 1 equal to the whole decode's crop."""
    import importlib.util
    import json
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "benchmarks" / "decode" / "region.py"
    spec = importlib.util.spec_from_file_location("_bench_region", path)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    out = tmp_path / "region.json"
    res = bench.main(["--size", "24", "--n", "400", "--box", "8", "--zoom", "2", "--repeat", "1", "--device", "cpu", "--out", str(out)])
    saved = json.loads(out.read_text())
    for key in ("device_name", "warp_version", "date", "commit", "command"):
        assert key in saved
    assert saved["command"].startswith("python benchmarks/decode/region.py --size 24") and saved["crop_equal"] is True
    whole, box = saved["rows"]
    assert whole["output_shape"] == [24, 24, 24] and box["output_shape"] == [16, 16, 16] and box["box"] == [[8, 16]] * 3
    assert saved["ratio_device"] == pytest.approx(box["device_ms"] / whole["device_ms"]) and res["n"] == 400
