"""Rendering a model (ray marching of V~) and a dense reference volume with the same marcher.

    from warpgauss.render.renderers import Camera, RenderSettings, render_model
    img = render_model(model, Camera(azimuth=30, elevation=20), settings=RenderSettings(width=512))
    save_png("vortex.png", img.rgb8())

Three ways to draw a model (``method``):

- ``"march"`` (:class:`ModelRenderer`): exact ray marching of V~; every sample evaluates the
  binned mixture (about a thousand candidate primitives at 1.4M), seconds per frame on a GPU.
- ``"cached"`` (:class:`CachedRenderer`): V~ decoded once onto a grid (the model's own by
  default, ``cache_res`` for another), kept on the device and marched as a dense volume
  (trilinear samples, central-difference gradients) by the same kernel that draws the reference.
  The decode is a one-time cost (``cache_seconds``); frames cost what a dense volume's do. It
  equals :class:`VolumeRenderer` on ``model.decode(normalised=True)`` bit for bit, and differs from
  the exact march by the grid's trilinear interpolation (measured in tests/test_render_cached.py).
- ``"splat"`` (:class:`warpgauss.render.splat.SplatRenderer`): EWA splatting, an approximation.

Coordinates: "world" is the model's voxel grid scaled by spacing / min(spacing) (one world unit
is one voxel along the finest axis); explicit camera positions are physical coordinates, as
ParaView shows them (origin + voxel index x spacing). Values are the model's normalised [0, 1].

The kernels are in :mod:`warpgauss.kernels.render`; EWA splatting of the same model lives in
:mod:`warpgauss.render.splat`.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import replace

import numpy as np

from ..core.warp import resolve_device, warp
from ..errors import WarpgaussError
from .raymarch import (  # noqa: F401 - the scene, camera and image types are part of this module's API
    CACHE_MEMORY_SHARE,
    DEFAULT_DENSITY,
    OCCUPANCY_TARGET,
    Camera,
    Image,
    Marcher,
    RenderSettings,
    Scene,
    View,
    device_memory_bytes,
    resolve_view,
)
from .splat import SplatRenderer
from .transfer import TransferFunction, make_transfer_function

METHODS = ("march", "cached", "splat", "bounded")  # how a model is drawn (see the module docstring)


class ModelRenderer(Marcher):
    """Exact ray marching of a model's mixture field V~ through the binned evaluator (``method="march"``).

    Every sample visits the binned candidates near it and its shading uses the analytic gradient;
    for interactive frame rates march the decoded grid instead (:class:`CachedRenderer`).

    Args:
        model: A :class:`warpgauss.Model`, or (params, header) of one.
        device: Warp device (None: CUDA when present, else CPU).
    """

    def __init__(self, model, device: str | None = None):
        from ..field.gaussians import GaussianField

        params, header = (model.params, model.header) if hasattr(model, "params") else model
        super().__init__(Scene.from_header(header), device)
        wp, kr = self._wp, self._k
        self.header = header
        self.field = GaussianField(params, self.scene.shape_xyz, device=self.device)
        f = self.field
        wp.launch(kr.mark_primitives, dim=f.n, inputs=[f.mu, f.ext, f.a, self.occ], device=self.device)
        big = np.float32(3.0e38)
        bounds = wp.array(np.array([big, big, big, -big, -big, -big], np.float32), dtype=float, device=self.device)
        wp.launch(kr.support_bounds, dim=f.n, inputs=[f.mu, f.ext], outputs=[bounds], device=self.device)
        b = bounds.numpy().astype(np.float64)
        lo = np.maximum(self.grid_box[0], b[:3])
        hi = np.minimum(self.grid_box[1], b[3:])
        self.box_voxels = (lo, np.maximum(hi, lo))
        self._source = self.field.prims

    def render(
        self, camera: Camera | View | None = None, tf: TransferFunction | None = None, settings: RenderSettings | None = None
    ) -> Image:
        """One frame of the model's field by ray marching."""
        settings = settings or RenderSettings()
        view = camera if isinstance(camera, View) else resolve_view(camera or Camera(), self.scene, settings.width, settings.height)
        return self._march(self.field.prims, view, tf or make_transfer_function(), settings, "march")


class VolumeRenderer(Marcher):
    """Ray marching of a dense normalised grid (trilinear) with the model's marcher: the reference.

    Args:
        values: (nz, ny, nx) normalised values (float32; masked voxels already 0).
        scene: The grid the camera is placed in (for a comparison, the model's; the volume is
            stretched over that grid's extent).
        device: Warp device.
    """

    label = "reference"  # the method its images name

    def __init__(self, values: np.ndarray, scene: Scene | None = None, device: str | None = None):
        values = np.ascontiguousarray(values, dtype=np.float32)
        if values.ndim != 3 or min(values.shape) < 1:
            raise WarpgaussError(f"a reference volume must be a 3D array, got shape {values.shape}")
        nz, ny, nx = values.shape
        scene = scene or Scene((nx, ny, nz))
        super().__init__(scene, device)
        self._attach_volume(self._wp.array(values, dtype=float, device=self.device), (nx, ny, nz))

    def render(
        self, camera: Camera | View | None = None, tf: TransferFunction | None = None, settings: RenderSettings | None = None
    ) -> Image:
        """One frame of the dense grid by ray marching (trilinear samples)."""
        settings = settings or RenderSettings()
        view = camera if isinstance(camera, View) else resolve_view(camera or Camera(), self.scene, settings.width, settings.height)
        return self._march(self.volume, view, tf or make_transfer_function(), settings, self.label)


class BoundedRenderer(VolumeRenderer):
    """Ray marching of a model's bounded decode (the Gaussians plus its residual, every voxel within
    the residual's bound of the source), normalised by the header's range, as a grid."""

    label = "bounded"

    def __init__(self, model, device: str | None = None):
        if model.residual is None:
            raise WarpgaussError("this model has no residual (encode with --max-error for one); draw it with march, cached or splat")
        lo, hi = model.value_range
        grid = (model.decode(device=device, residual=True).astype(np.float64) - lo) / (hi - lo)
        super().__init__(np.nan_to_num(np.clip(grid, 0.0, 1.0)).astype(np.float32), Scene.from_header(model.header), device)


def cache_grid_shape(shape_xyz, cache_res: int | None = None) -> tuple[int, ...]:
    """The grid a cached renderer decodes onto: the model's own, or ``cache_res`` voxels along its
    longest axis with the others scaled to keep the aspect (at least 1 voxel each).

    Raises:
        WarpgaussError: ``cache_res`` is not a positive integer, or the grid exceeds the int32
            voxel indexing of the kernels.
    """
    from ..field.analysis import MAX_VOXELS

    shape = tuple(int(n) for n in shape_xyz)
    if len(shape) != 3 or min(shape) < 1:
        raise WarpgaussError(f"a cache grid must be three positive sizes (x, y, z), got {shape_xyz!r}")
    if cache_res is not None:
        if isinstance(cache_res, bool) or not isinstance(cache_res, (int, np.integer)) or cache_res < 1:
            raise WarpgaussError(f"--cache-res must be a positive number of voxels along the longest axis, got {cache_res!r}")
        longest = max(shape)
        shape = tuple(max(1, int(round(n * int(cache_res) / longest))) for n in shape)
    voxels = math.prod(shape)
    if voxels > MAX_VOXELS:
        raise WarpgaussError(
            f"a {'x'.join(map(str, shape))} cache has {voxels:,} voxels, more than the {MAX_VOXELS:,} the kernels index; "
            "choose a smaller --cache-res"
        )
    return shape


def check_cache_memory(shape_xyz, device: str) -> None:
    """Refuse a cache larger than :data:`CACHE_MEMORY_SHARE` of the device's memory, before allocating it."""
    need = 4 * math.prod(int(n) for n in shape_xyz)  # float32 voxels; the occupancy adds < 1/8 of that
    have = device_memory_bytes(device)
    if have is not None and need > CACHE_MEMORY_SHARE * have:
        raise WarpgaussError(
            f"a {'x'.join(map(str, shape_xyz))} cache needs {need / 2**30:.2f} GiB, more than {CACHE_MEMORY_SHARE:.0%} of the "
            f"{have / 2**30:.2f} GiB available on {device}; choose a smaller --cache-res"
        )


class CachedRenderer(Marcher):
    """Ray marching of a model's V~ decoded once onto a grid kept on the device.

    The decode is the model's full-grid decode (bricks no primitive reaches are written 0 without
    evaluation, which is their exact value) straight into device memory; the grid is then marched
    as a dense volume: trilinear samples, shading from central differences of one model voxel
    (precomputed as a half-precision gradient grid where memory allows: 8 more bytes a voxel for
    frames 1.2-1.3x faster on an H100), occupancy from its non-zero voxels. Only camera, transfer function and lighting change between
    frames, so the decode is paid once (:attr:`cache_seconds`).

    .. note:: trades exactness for speed: the image is the exact march's up to the trilinear
       interpolation of the cached grid (a finer ``cache_res`` is closer and costs memory, and the
       decode time grows with the voxel count); it equals :class:`VolumeRenderer` on
       ``model.decode(shape_xyz=shape, normalised=True)`` bit for bit.

    Args:
        model: A :class:`warpgauss.Model`, or (params, header) of one.
        device: Warp device (None: CUDA when present, else CPU).
        cache_res: Voxels along the longest axis of the cache (aspect kept); None: the model grid.
        cache_shape: Explicit cache grid (x, y, z); overrides ``cache_res``.

    Attributes:
        cache_shape: The cached grid (x, y, z).
        cache_seconds: Seconds to upload and bin the primitives, decode the grid and mark the
            occupancy (synchronised; kernel compilation excluded).
    """

    def __init__(self, model, device: str | None = None, *, cache_res: int | None = None, cache_shape: tuple[int, int, int] | None = None):
        from ..field.gaussians import DECODE_SLAB_VOXELS, GaussianField
        from ..kernels import decode as kd
        from ..kernels import field as kf

        params, header = (model.params, model.header) if hasattr(model, "params") else model
        scene = Scene.from_header(header)
        if cache_shape is not None:
            shape = cache_grid_shape(cache_shape)
        else:
            shape = cache_grid_shape(scene.shape_xyz, cache_res)
        wp = warp()
        dev = resolve_device(device)
        check_cache_memory(shape, dev)
        super().__init__(scene, dev)
        self.header = header
        self.cache_shape = shape
        wp.load_module(kf, device=dev)
        wp.load_module(kd, device=dev)
        wp.synchronize_device(dev)
        t0 = time.perf_counter()
        field = GaussianField(params, scene.shape_xyz, device=dev)
        nx, ny, nz = shape
        values = wp.empty((nz, ny, nx), dtype=float, device=dev)
        scale = wp.vec3(*(scene.shape_xyz[a] / shape[a] for a in range(3)))  # as GaussianField.iter_slabs
        slab = max(1, min(nz, DECODE_SLAB_VOXELS // (nx * ny)))
        for z0 in range(0, nz, slab):
            field.decode_slab(values[z0 : min(nz, z0 + slab)], z0, scale)
        self.n = field.n
        del field  # the primitives are not needed any more: only the grid stays on the device
        self._attach_volume(values, shape)
        wp.synchronize_device(dev)
        self.cache_seconds = time.perf_counter() - t0

    @property
    def cache_bytes(self) -> int:
        """Device bytes of the cache: its values and, when built, its gradient grid."""
        from .raymarch import GRADIENT_GRID_BYTES

        return (4 + GRADIENT_GRID_BYTES * int(self.gradient_grid)) * math.prod(self.cache_shape)

    def render(
        self, camera: Camera | View | None = None, tf: TransferFunction | None = None, settings: RenderSettings | None = None
    ) -> Image:
        """One frame of the cached grid by ray marching (the decode is not repeated)."""
        settings = settings or RenderSettings()
        view = camera if isinstance(camera, View) else resolve_view(camera or Camera(), self.scene, settings.width, settings.height)
        img = self._march(self.volume, view, tf or make_transfer_function(), settings, "cached")
        img.stats.update(cache_shape=list(self.cache_shape), cache_seconds=self.cache_seconds, gradient_grid=self.gradient_grid)
        return img


def make_renderer(model, method: str = "march", device: str | None = None, *, cache_res: int | None = None):
    """The renderer of ``method`` ("march", "cached", "splat", or "bounded": the decode with a
    model's residual, see :class:`BoundedRenderer`) for a model.

    Args:
        model: The :class:`warpgauss.Model`.
        method: See the module docstring.
        device: Warp device.
        cache_res: "cached" only: voxels along the cache's longest axis (None: the model grid).
    """
    if method not in METHODS:
        raise WarpgaussError(f"unknown render method {method!r}; use {', '.join(METHODS)}")
    if cache_res is not None and method != "cached":
        raise WarpgaussError(f"--cache-res applies to --method cached, not {method}")
    if method == "march":
        return ModelRenderer(model, device)
    if method == "cached":
        return CachedRenderer(model, device, cache_res=cache_res)
    if method == "bounded":
        return BoundedRenderer(model, device)
    return SplatRenderer(model, device)


def render_model(
    model,
    camera: Camera | None = None,
    tf: TransferFunction | None = None,
    settings: RenderSettings | None = None,
    *,
    method: str = "march",
    device: str | None = None,
    cache_res: int | None = None,
) -> Image:
    """Render a model by exact ray marching (``method="march"``), ray marching of its decoded grid
    (``"cached"``) or EWA splatting (``"splat"``).

    For several frames of one model build the renderer once (:func:`make_renderer`): the cached
    path's decode is then paid once.

    Args:
        model: The :class:`warpgauss.Model`.
        camera: Camera (default orbit view).
        tf: Transfer function (default: the model header's).
        settings: Image size, step, density, lighting.
        method: "march", "cached" or "splat".
        device: Warp device.
        cache_res: "cached" only: voxels along the cache's longest axis (None: the model grid).
    """
    from .transfer import from_header

    tf = tf or from_header(model.header)
    return make_renderer(model, method, device, cache_res=cache_res).render(camera, tf, settings)


def render_image(
    model,
    camera: Camera | dict | None = None,
    *,
    size: int | tuple[int, int] | None = None,
    method: str = "cached",
    colormap: str | None = None,
    opacity=None,
    tf: TransferFunction | str | os.PathLike | None = None,
    background: tuple[float, float, float] | None = None,
    settings: RenderSettings | None = None,
    residual: bool = False,
    device: str | None = None,
    cache_res: int | None = None,
) -> np.ndarray:
    """A model rendered as an RGBA array, for a notebook (``plt.imshow(warpgauss.render_image(m))``):
    the image ``warpgauss render`` writes, with the same defaults, without the file.

    Args:
        model: A :class:`warpgauss.Model` or the path of a ``.wgs`` file.
        camera: A :class:`Camera`, or a dict of its fields (``{"azimuth": 30, "zoom": 1.5}``);
            None: the default orbit view.
        size: Image size, N or (width, height) in pixels (None: ``settings``', 512x512).
        method: "cached" (default, as the command line's), "march" or "splat" (module docstring).
        colormap: Replace the transfer function's colours by a named colormap ("magma", ...).
        opacity: Replace its opacity curve (``[(value, opacity), ...]`` over normalised values, or
            a string such as "0:0,0.3:0,1:1", "linear", "flat").
        tf: A :class:`TransferFunction`, or a transfer-function ``.json`` (ours or a ParaView
            export); None: the model header's.
        background: RGB in [0, 1] (None: ``settings``', black).
        settings: Step, density, lighting and the rest (:class:`RenderSettings`).
        residual: Ray-march the bounded decode (Gaussians + residual) of a model that has one.
        device: Warp device.
        cache_res: "cached" only: voxels along the cache's longest axis (None: the model grid).

    Returns:
        (height, width, 4) uint8: the colour composited over the background (the PNG's RGB, bit
        for bit) and alpha = 1 - the ray's transmittance.
    """
    from ..format.model import Model
    from .transfer import resolve_transfer_function

    m = model if isinstance(model, Model) else Model.load(model)
    if residual and m.residual is None:
        raise WarpgaussError("this model has no residual (encode with --max-error for one); render without residual=True")
    if residual and method not in ("cached", "march"):
        raise WarpgaussError(f"residual=True ray-marches the bounded decode as a grid; drop method={method!r}")
    if isinstance(camera, dict):
        try:
            cam = Camera(**camera)
        except TypeError:
            raise WarpgaussError(f"camera takes the fields of warpgauss.render.renderers.Camera, got {sorted(camera)}") from None
    else:
        cam = camera or Camera()
    cam.validate()
    changes: dict = {}
    if size is not None:
        wh = (size, size) if isinstance(size, int) else tuple(size)
        if len(wh) != 2:
            raise WarpgaussError(f"size must be N or (width, height) in pixels, got {size!r}")
        changes.update(width=wh[0], height=wh[1])
    if background is not None:
        changes["background"] = tuple(float(c) for c in background)
    st = with_settings(settings, **changes)
    st.validate()
    if isinstance(tf, TransferFunction):
        base = tf if colormap is None else tf.with_colormap(colormap)
        tf_ = base if opacity is None else base.with_opacity(opacity)
    else:
        tf_ = resolve_transfer_function(m.header, path=tf, colormap_name=colormap, opacity=opacity, value_range=m.value_range)
    if method == "cached" and not residual:
        check_cache_memory(cache_grid_shape(m.shape_xyz, cache_res), resolve_device(device))
    renderer = make_renderer(m, "bounded" if residual else method, device, cache_res=cache_res)
    return renderer.render(resolve_view(cam, renderer.scene, st.width, st.height), tf_, st).rgb8(alpha=True)


# ------------------------------------------------------------------------------------------------
# Image metrics, composition and PNG output
# ------------------------------------------------------------------------------------------------


def image_psnr(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR (dB) of two RGB images in [0, 1] (peak 1, mean over all channels)."""
    a = np.asarray(a, np.float64)[..., :3]
    b = np.asarray(b, np.float64)[..., :3]
    mse = float(np.mean((a - b) ** 2))
    return float(10.0 * np.log10(1.0 / max(mse, 1e-20)))


def image_ssim(a: np.ndarray, b: np.ndarray, sigma: float = 1.5) -> float:
    """Mean SSIM (Wang et al. 2004; Gaussian window sigma 1.5, K1 0.01, K2 0.03, range 1), averaged over RGB."""
    from scipy.ndimage import gaussian_filter

    a = np.asarray(a, np.float64)[..., :3]
    b = np.asarray(b, np.float64)[..., :3]
    c1, c2 = 0.01**2, 0.03**2
    vals = []
    for ch in range(a.shape[-1]):
        x, y = a[..., ch], b[..., ch]

        def blur(v):
            return gaussian_filter(v, sigma, truncate=3.5, mode="reflect")

        mx, my = blur(x), blur(y)
        sxx = blur(x * x) - mx * mx
        syy = blur(y * y) - my * my
        sxy = blur(x * y) - mx * my
        s = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))
        vals.append(float(s.mean()))
    return float(np.mean(vals))


def side_by_side(model: np.ndarray, reference: np.ndarray, gain: float = 4.0, gap: int = 4) -> np.ndarray:
    """model | reference | |model - reference| x gain (largest over channels, grayscale), RGB float."""
    a = np.asarray(model, np.float32)[..., :3]
    b = np.asarray(reference, np.float32)[..., :3]
    diff = np.clip(np.abs(a - b).max(axis=-1, keepdims=True) * gain, 0.0, 1.0).repeat(3, axis=-1)
    h = a.shape[0]
    sep = np.ones((h, gap, 3), np.float32)
    return np.concatenate([a, sep, b, sep, diff], axis=1)


def save_png(path: str | os.PathLike, image: np.ndarray, *, force: bool = False) -> None:
    """Write an (H, W, 3|4) uint8 or float [0, 1] image as PNG, atomically."""
    from PIL import Image as PILImage

    from ..core.files import atomic_path, check_writable

    check_writable(path, force=force)
    arr = np.asarray(image)
    if arr.dtype != np.uint8:
        arr = (np.clip(arr, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    mode = {3: "RGB", 4: "RGBA"}.get(arr.shape[-1] if arr.ndim == 3 else 0)
    if mode is None:
        raise WarpgaussError(f"an image must be (H, W, 3) or (H, W, 4), got {arr.shape}")
    with atomic_path(path) as tmp:
        PILImage.fromarray(np.ascontiguousarray(arr), mode).save(tmp, format="PNG")


def with_settings(settings: RenderSettings | None, **changes) -> RenderSettings:
    """A copy of ``settings`` (or the defaults) with some fields changed."""
    return replace(settings or RenderSettings(), **changes)
