"""The cached ray-marching path: V~ decoded once onto a grid and marched as a dense volume.

Its frame must be (a) the dense reference marcher's frame of ``model.decode(normalised=True)``,
bit for bit (it is the same kernel on the same grid), and (b) close to the exact march of the
mixture, the gap being the grid's trilinear interpolation and the central-difference gradient.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from test_render import header
from typer.testing import CliRunner

from warpgauss.cli.main import app
from warpgauss.errors import WarpgaussError
from warpgauss.format.model import Model
from warpgauss.render.renderers import (
    CachedRenderer,
    Camera,
    ModelRenderer,
    RenderSettings,
    Scene,
    VolumeRenderer,
    cache_grid_shape,
    image_psnr,
    image_ssim,
    make_renderer,
    render_model,
    with_settings,
)
from warpgauss.render.transfer import from_header, make_transfer_function

runner = CliRunner()


@pytest.fixture(scope="module")
def vortex_model():
    """vortex 32^3 with 400 Gaussians, analytic fit only (iterations 0; ~0.5 s on the CPU)."""
    import warpgauss

    return warpgauss.encode(example="vortex", example_size=32, budget=400, iterations=0, device="cpu", evaluate=False)


def anisotropic_model() -> Model:
    """300 random primitives on a 28x20x24 grid with anisotropic spacing, two clusters (the occupancy mostly empty)."""
    rng = np.random.default_rng(7)
    n = 300
    p = np.zeros((n, 12), np.float32)
    p[:, :3] = rng.uniform(2, 9, (n, 3))
    p[::2, :3] += (16.0, 9.0, 12.0)
    p[:, 3:6] = rng.uniform(-0.3, 0.6, (n, 3))
    q = rng.normal(size=(n, 4))
    p[:, 6:10] = q / np.linalg.norm(q, axis=1, keepdims=True)
    p[:, 10] = rng.uniform(0.1, 1.0, n)
    p[:, 11] = rng.uniform(0.2, 1.0, n)
    return Model(p, header((28, 20, 24), spacing=(1.0, 1.5, 0.75)))


TFS = {
    "header": None,  # the model header's: viridis, linear ramp
    "ramp": ("magma", "0:0,0.3:0,1:1"),  # transparent below 0.3: cells skipped
    "floor": ("viridis", "0:0.05,1:1"),  # opacity at 0 > 0: the whole grid box visible, empty cells in closed form
}


def _tf(name, model):
    return from_header(model.header) if TFS[name] is None else make_transfer_function(*TFS[name])


@pytest.mark.parametrize("which, cache_res", [("vortex", None), ("vortex", 20), ("vortex", 45), ("aniso", None), ("aniso", 17)])
def test_cached_equals_the_dense_reference_on_the_decoded_grid(cpu, vortex_model, which, cache_res):
    """Bit for bit: the cached frame is the dense reference marcher's frame of the decoded grid, for
    the model grid and coarser/finer caches, anisotropic spacing, shading on/off, orthographic, and
    a transfer function with opacity at 0 (empty cells composited in closed form)."""
    model = vortex_model if which == "vortex" else anisotropic_model()
    c = CachedRenderer(model, device=cpu, cache_res=cache_res)
    shape = cache_grid_shape(model.shape_xyz, cache_res)
    assert c.cache_shape == shape and c.cache_seconds > 0
    values = model.decode(shape_xyz=shape, device=cpu, normalised=True)
    ref = VolumeRenderer(values, Scene.from_header(model.header), device=cpu)
    base = RenderSettings(width=40, height=36)
    for tf_name in TFS:
        tf = _tf(tf_name, model)
        for cam, s in (
            (Camera(azimuth=20, elevation=30), base),
            (Camera(azimuth=-70, elevation=-15, zoom=1.4), with_settings(base, shading=False)),
            (Camera(azimuth=140, elevation=60, ortho=True), with_settings(base, step=0.37, ert=0.0)),
        ):
            a, b = c.render(cam, tf, s), ref.render(cam, tf, s)
            assert a.method == "cached" and a.stats["cache_shape"] == list(shape)
            assert np.array_equal(a.rgba, b.rgba), (tf_name, cam, s)
            assert a.stats["evaluations_per_pixel"] == b.stats["evaluations_per_pixel"]
            assert a.rgb.max() > 0.05  # something is drawn


def test_cached_agrees_with_the_exact_march(cpu, vortex_model):
    """The cached frame against the exact march of the same model (48x48, default camera).

    Measured (CPU, vortex 32^3 / 400 Gaussians, cache = the 32^3 model grid), image PSNR / SSIM:
    header TF shaded 40.3 dB / 0.988, unshaded 52.8 dB / 0.9995; magma from 0.3 shaded 41.8 dB /
    0.996, unshaded 51.1 dB / 0.9992. Shading costs ~11 dB: the cached gradient is a central
    difference of one model voxel over the trilinear grid, the exact one the analytic gradient of
    V~. Without shading the gap is the trilinear interpolation and closes with a finer cache
    (measured 60.5 / 59.5 dB at 64^3, 48.2-50.1 dB at 24^3). Bounds: 35 dB shaded, 45 dB unshaded,
    and 64^3 at least 5 dB better than 32^3 unshaded.
    """
    model = vortex_model
    exact = ModelRenderer(model, device=cpu)
    cached = CachedRenderer(model, device=cpu)
    fine = CachedRenderer(model, device=cpu, cache_res=64)
    assert fine.cache_shape == (64, 64, 64)
    s = RenderSettings(width=48, height=48)
    for tf_name in ("header", "ramp"):
        tf = _tf(tf_name, model)
        for shading, bound in ((True, 35.0), (False, 45.0)):
            st = with_settings(s, shading=shading)
            e, c = exact.render(Camera(), tf, st), cached.render(Camera(), tf, st)
            psnr, ssim = image_psnr(c.rgb, e.rgb), image_ssim(c.rgb, e.rgb)
            print(f"cached vs exact march, {tf_name} TF, shading {shading}: image PSNR {psnr:.2f} dB, SSIM {ssim:.4f}")
            assert psnr >= bound and ssim >= 0.97
            assert c.seconds < e.seconds  # (not a timing claim: ~1 trilinear tap against ~100 candidates per sample)
            if not shading:
                f = fine.render(Camera(), tf, st)
                assert image_psnr(f.rgb, e.rgb) >= psnr + 5.0


def test_dense_skipping_is_exact_where_opacity_at_zero_is_visible(cpu):
    """A dense grid's cells with no non-zero voxel within reach (value and gradient stencils) are
    composited in closed form, with shading: skipping changes a frame by float rounding only, and
    saves samples."""
    vol = np.zeros((24, 28, 32), np.float32)
    z, y, x = np.meshgrid(np.arange(24), np.arange(28), np.arange(32), indexing="ij")
    vol += np.exp(-((x - 6.0) ** 2 + (y - 7.0) ** 2 + (z - 5.0) ** 2) / 8.0)
    vol[vol < 1e-3] = 0.0  # a blob in one corner, exact zeros elsewhere
    vol[18:21, 20:23, 25:28] = 0.7  # and a box in the opposite one
    r = VolumeRenderer(vol, device=cpu)
    s = RenderSettings(width=32, height=32, ert=0.0, density=0.5)
    for tf in (make_transfer_function("viridis", "0:0.05,1:1"), make_transfer_function("magma", "0:0,0.3:0,1:1")):
        for shading in (True, False):
            st = with_settings(s, shading=shading)
            on, off = r.render(Camera(azimuth=35), tf, st), r.render(Camera(azimuth=35), tf, with_settings(st, skip=False))
            np.testing.assert_allclose(on.rgba, off.rgba, atol=2e-5)
            assert on.stats["evaluations_per_pixel"] < 0.5 * off.stats["evaluations_per_pixel"]
    state = r.occ.state.numpy()
    assert (state == 0).mean() > 0.5  # most cells are empty


def test_cache_grid_shape_and_refusals(cpu, vortex_model, monkeypatch):
    assert cache_grid_shape((64, 32, 16)) == (64, 32, 16)
    assert cache_grid_shape((64, 32, 16), 32) == (32, 16, 8)
    assert cache_grid_shape((64, 32, 16), 200) == (200, 100, 50)
    assert cache_grid_shape((100, 3, 50), 10) == (10, 1, 5)  # at least one voxel an axis
    for bad in (0, -4, 2.5, True):
        with pytest.raises(WarpgaussError, match="--cache-res must be a positive"):
            cache_grid_shape((32, 32, 32), bad)
    with pytest.raises(WarpgaussError, match="voxels, more than"):
        cache_grid_shape((32, 32, 32), 2000)  # 8e9 voxels: beyond int32 indexing
    import warpgauss.render.renderers as wr

    monkeypatch.setattr(wr, "device_memory_bytes", lambda device: 2**20)  # a 1 MiB device
    with pytest.raises(WarpgaussError, match="GiB available on cpu"):
        CachedRenderer(vortex_model, device=cpu, cache_res=128)
    with pytest.raises(WarpgaussError, match="--cache-res applies to --method cached"):
        make_renderer(vortex_model, "march", cpu, cache_res=16)
    with pytest.raises(WarpgaussError, match="unknown render method"):
        make_renderer(vortex_model, "raytrace", cpu)


def test_render_model_api_cached(cpu, vortex_model):
    s = RenderSettings(width=24, height=20)
    img = render_model(vortex_model, Camera(), settings=s, method="cached", device=cpu, cache_res=16)
    assert img.method == "cached" and img.rgba.shape == (20, 24, 4) and img.stats["cache_shape"] == [16, 16, 16]
    again = make_renderer(vortex_model, "cached", cpu, cache_res=16).render(Camera(), from_header(vortex_model.header), s)
    assert np.array_equal(img.rgba, again.rgba)


# -------------------------------------------------------------------------------------------------
# CLI
# -------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def files(vortex_model, tmp_path_factory):
    from warpgauss.readers.synthetic import generate

    d = tmp_path_factory.mktemp("cached")
    vortex_model.save(d / "v.wgs")
    np.save(d / "v.npy", generate("vortex", 32))
    return d


def test_cli_render_cached(cpu, files, tmp_path):
    from PIL import Image as PILImage

    out = tmp_path / "c.png"
    r = runner.invoke(app, ["render", str(files / "v.wgs"), "--method", "cached", "-o", str(out), "--size", "40x32", "--device", cpu])
    assert r.exit_code == 0, r.output
    assert "cached" in r.stdout and "per frame" in r.stdout and "cache 32x32x32 built once in" in r.stdout
    assert PILImage.open(out).size == (40, 32)
    r = runner.invoke(
        app,
        [
            "render",
            str(files / "v.wgs"),
            "--method",
            "cached",
            "--cache-res",
            "20",
            "--compare",
            str(files / "v.npy"),
            "-o",
            str(tmp_path / "cmp.png"),
            "--size",
            "32",
            "--device",
            cpu,
            "--json",
        ],
    )
    assert r.exit_code == 0, r.output
    rep = json.loads(r.stdout)
    assert rep["method"] == "cached" and rep["cache_shape"] == [20, 20, 20] and rep["cache_seconds"] > 0
    assert rep["image_psnr_db"] > 25


@pytest.mark.parametrize(
    "args, message",
    [
        (["MODEL", "--method", "cached", "--cache-res", "0"], "--cache-res must be a positive"),
        (["MODEL", "--method", "cached", "--cache-res", "-8"], "--cache-res must be a positive"),
        (["MODEL", "--method", "cached", "--cache-res", "5000"], "choose a smaller --cache-res"),  # 1.25e11 voxels
        (["MODEL", "--method", "cached", "--cache-res", "1200"], "GiB available on cpu"),  # 6.4 GiB > the patched 1 GiB
        (["MODEL", "--method", "march", "--cache-res", "16"], "--cache-res applies to --method cached"),
        (["MODEL", "--cache-res", "1200"], "GiB available on cpu"),  # cached is the default for a model
        (["VOLUME", "--cache-res", "16"], "--cache-res applies to a model"),
        (["MODEL", "--method", "splat", "--cache-res", "16"], "--cache-res applies to --method cached"),
        (["VOLUME", "--method", "cached"], "--method cached needs a model"),
        (["MODEL", "--method", "exact"], "--method must be march, cached or splat"),
    ],
)
def test_cli_render_cached_refusals(cpu, files, tmp_path, monkeypatch, args, message):
    """Bad --cache-res values end in one line and exit 2, before anything is written."""
    import warpgauss.render.renderers as wr

    monkeypatch.setattr(wr, "device_memory_bytes", lambda device: 2**30)
    subst = {"MODEL": str(files / "v.wgs"), "VOLUME": str(files / "v.npy")}
    out = tmp_path / "out.png"
    r = runner.invoke(app, ["render", *(subst.get(a, a) for a in args), "-o", str(out), "--size", "16", "--device", cpu])
    assert r.exit_code == 2, r.output
    lines = [line for line in r.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in r.output, r.output
    assert message.lower() in lines[0].lower(), lines[0]
    assert not out.exists()


def test_cli_view_cached(cpu, files, tmp_path):
    """`view` draws with the cached grid by default; --method march and --cache-res are accepted, bad values refused."""
    from PIL import Image as PILImage

    for extra in ([], ["--method", "march", "--cache-res", "16"]):
        shot = tmp_path / f"view{len(extra)}.png"
        r = runner.invoke(app, ["view", str(files / "v.wgs"), "--screenshot", str(shot), "--size", "40x32", "--device", cpu, *extra])
        assert r.exit_code == 0, r.output
        assert (extra[1] if extra else "cached") in r.stdout
        assert np.asarray(PILImage.open(shot).convert("RGB")).mean() > 5
    for extra, message in ((["--cache-res", "0"], "--cache-res must be a positive"), (["--method", "exact"], "--method must be")):
        r = runner.invoke(app, ["view", str(files / "v.wgs"), "--screenshot", str(tmp_path / "bad.png"), "--device", cpu, *extra])
        assert r.exit_code == 2 and message in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.output


def _trilinear64(vol: np.ndarray, q: np.ndarray) -> np.ndarray:
    """float64 trilinear interpolation of vol (nz, ny, nx) at (M, 3) points (x, y, z), clamped."""
    n = np.array(vol.shape[::-1], np.float64)
    q = np.clip(q, 0.0, n - 1)
    i0 = np.minimum(np.floor(q).astype(int), (n - 1).astype(int))
    i1 = np.minimum(i0 + 1, (n - 1).astype(int))
    t = q - i0
    out = np.zeros(len(q))
    for dz in (0, 1):
        for dy in (0, 1):
            for dx in (0, 1):
                w = (t[:, 0] if dx else 1 - t[:, 0]) * (t[:, 1] if dy else 1 - t[:, 1]) * (t[:, 2] if dz else 1 - t[:, 2])
                ix, iy, iz = (i1 if dx else i0)[:, 0], (i1 if dy else i0)[:, 1], (i1 if dz else i0)[:, 2]
                out += w * vol[iz, iy, ix]
    return out


def test_the_gradient_grid_is_the_central_difference_of_the_trilinear_grid(monkeypatch):
    """Shading reads the gradient of a dense grid from a precomputed gradient grid (one fetch
    instead of six trilinear samples): between the outermost voxel centres it equals the central
    difference over one voxel of the trilinear interpolant (float64 numpy) up to its half
    precision, edge cells included;
    in the half voxel beyond them it is the edge's; without room for the grid (memory share 0)
    the marcher falls back to those central differences, the image all but the same."""
    import warpgauss.render.raymarch as rm
    from warpgauss.render.raymarch import Camera, RenderSettings

    rng = np.random.default_rng(5)
    vol = np.cumsum(np.cumsum(rng.uniform(0, 1, (9, 11, 13)), 0), 2)
    vol = (vol / vol.max()).astype(np.float32)
    r = VolumeRenderer(vol, device="cpu")
    assert r.gradient_grid
    top = np.array([12.0, 10.0, 8.0])
    pts = rng.uniform(0.0, 1.0, (400, 3)) * top
    pts[:40, 0] = rng.choice([0.0, 0.3, 11.6, 12.0], 40)  # in the edge cells
    got = r.sample(pts)
    v64 = vol.astype(np.float64)
    for a in range(3):
        e = np.zeros(3)
        e[a] = 1.0
        ref = 0.5 * (_trilinear64(v64, pts + e) - _trilinear64(v64, pts - e))
        np.testing.assert_allclose(got[:, 1 + a], ref, rtol=1e-3, atol=1e-5)  # float16: 11 significant bits a corner
    np.testing.assert_allclose(got[:, 0], _trilinear64(v64, pts), atol=1e-6)
    outside = np.array([[-0.4, 3.2, 4.1], [12.45, 0.5, 7.9], [5.5, -0.2, 8.3]])
    np.testing.assert_array_equal(r.sample(outside), r.sample(np.clip(outside, 0.0, top)))
    tf = make_transfer_function("viridis", opacity=[(0.0, 0.0), (1.0, 0.8)])
    settings = RenderSettings(width=48, height=40, shading=True)
    with_grid = r.render(Camera(), tf, settings)
    monkeypatch.setattr(rm, "CACHE_MEMORY_SHARE", 0.0)
    plain = VolumeRenderer(vol, device="cpu")
    assert not plain.gradient_grid
    without = plain.render(Camera(), tf, settings)
    print(f"gradient grid against central differences: {image_psnr(with_grid.rgb, without.rgb):.2f} dB")
    assert image_psnr(with_grid.rgb, without.rgb) >= 45.0  # they differ only in the outer half voxel (52.6 dB here)
    assert with_grid.stats["evaluations_per_pixel"] == without.stats["evaluations_per_pixel"]
