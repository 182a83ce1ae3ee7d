"""Rendering a model (ray marching of V~) and a dense reference volume with the same marcher.

    from warpgauss.render import Camera, RenderSettings, render_model
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
- ``"splat"`` (:class:`warpgauss.splat.SplatRenderer`): EWA splatting, an approximation.

Coordinates: "world" is the model's voxel grid scaled by spacing / min(spacing) (one world unit
is one voxel along the finest axis); explicit camera positions are physical coordinates, as
ParaView shows them (origin + voxel index x spacing). Values are the model's normalised [0, 1].

The kernels are in :mod:`warpgauss.kernels.render`; EWA splatting of the same model lives in
:mod:`warpgauss.splat`.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, field, replace

import numpy as np

from ._warp import resolve_device, warp
from .errors import WarpgaussError
from .transfer import TransferFunction, make_transfer_function

DEFAULT_DENSITY = 10.0  # extinction per world unit at opacity 1 = this / largest extent in world units
OCCUPANCY_TARGET = 128  # occupancy cells per axis at most (cells of at least 2 voxels)
METHODS = ("march", "cached", "splat")  # how a model is drawn (see the module docstring)
CACHE_MEMORY_SHARE = 0.5  # a cache may take at most this share of the device's free memory (CPU: of RAM)


# ------------------------------------------------------------------------------------------------
# Scene geometry and camera
# ------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Scene:
    """The model grid as the renderers see it.

    Attributes:
        shape_xyz: Model grid size (x, y, z) in voxels.
        spacing: Physical voxel size (x, y, z).
        origin: Physical position of voxel (0, 0, 0).
    """

    shape_xyz: tuple[int, int, int]
    spacing: tuple[float, float, float] = (1.0, 1.0, 1.0)
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)

    @classmethod
    def from_header(cls, header: dict) -> Scene:
        g = header["grid"]
        return cls(
            tuple(int(s) for s in g["shape_xyz"]),
            tuple(float(s) for s in g.get("spacing", (1.0, 1.0, 1.0))),
            tuple(float(o) for o in g.get("origin", (0.0, 0.0, 0.0))),
        )

    @property
    def unit(self) -> float:
        """Physical length of one world unit (the smallest spacing)."""
        sp = [abs(s) for s in self.spacing if s and math.isfinite(s)]
        return min(sp) if sp else 1.0

    @property
    def world_per_voxel(self) -> np.ndarray:
        sp = np.asarray([abs(s) if s and math.isfinite(s) else self.unit for s in self.spacing], np.float64)
        return sp / self.unit

    @property
    def box(self) -> tuple[np.ndarray, np.ndarray]:
        """World box of the grid: voxel edges [-0.5, n - 0.5] scaled."""
        n = np.asarray(self.shape_xyz, np.float64)
        return -0.5 * self.world_per_voxel, (n - 0.5) * self.world_per_voxel

    @property
    def extent(self) -> float:
        lo, hi = self.box
        return float(np.max(hi - lo))

    def to_world(self, physical) -> np.ndarray:
        """Physical coordinates (origin + voxel index x spacing) -> world coordinates."""
        sp = np.asarray(self.spacing, np.float64)
        sp = np.where((sp != 0) & np.isfinite(sp), sp, 1.0)
        voxel = (np.asarray(physical, np.float64) - np.asarray(self.origin, np.float64)) / sp
        return voxel * self.world_per_voxel


@dataclass
class Camera:
    """Where the image is taken from.

    Orbit mode (default): the camera looks at the grid's centre (or ``look_at``) from
    ``azimuth`` degrees around the ``up`` axis (0 on +x, 90 on +y) and ``elevation`` degrees above
    the plane normal to ``up``, at ``distance`` world units (None: the whole grid fits the view),
    divided by ``zoom``. Explicit mode: give ``position`` (and optionally ``look_at``) in physical
    coordinates.
    """

    azimuth: float = -55.0
    elevation: float = 25.0
    distance: float | None = None
    zoom: float = 1.0
    position: tuple[float, float, float] | None = None
    look_at: tuple[float, float, float] | None = None
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)
    fov: float = 30.0
    ortho: bool = False

    def validate(self) -> None:
        for name in ("azimuth", "elevation", "zoom", "fov"):
            if not math.isfinite(float(getattr(self, name))):
                raise WarpgaussError(f"camera {name} must be a finite number")
        if not self.zoom > 0:
            raise WarpgaussError(f"--zoom must be positive, got {self.zoom}")
        if not 0.1 <= self.fov <= 170:
            raise WarpgaussError(f"--fov must be between 0.1 and 170 degrees, got {self.fov}")
        if self.distance is not None and not (math.isfinite(self.distance) and self.distance > 0):
            raise WarpgaussError(f"--distance must be a positive number of voxels, got {self.distance}")
        for name in ("position", "look_at", "up"):
            v = getattr(self, name)
            if v is not None and (len(v) != 3 or not all(math.isfinite(float(c)) for c in v)):
                raise WarpgaussError(f"--{name.replace('_', '-')} must be three finite numbers x,y,z")
        if np.linalg.norm(np.asarray(self.up, np.float64)) == 0:
            raise WarpgaussError("--up must not be the zero vector")


@dataclass(frozen=True)
class View:
    """A resolved camera: world-space eye, orthonormal frame and projection."""

    eye: np.ndarray
    right: np.ndarray
    up: np.ndarray
    forward: np.ndarray
    tan_half: float
    half_height: float
    ortho: bool
    width: int
    height: int

    def struct(self):
        from .kernels import render as kr

        wp = warp()
        c = kr.Camera()
        c.eye, c.right, c.up, c.forward = (wp.vec3(*map(float, v)) for v in (self.eye, self.right, self.up, self.forward))
        c.tan_half = float(self.tan_half)
        c.half_height = float(self.half_height)
        c.ortho = int(self.ortho)
        c.width, c.height = int(self.width), int(self.height)
        return c


def resolve_view(camera: Camera, scene: Scene, width: int, height: int) -> View:
    """Turn a :class:`Camera` into a world-space :class:`View` of ``scene``."""
    camera.validate()
    lo, hi = scene.box
    centre = 0.5 * (lo + hi)
    radius = 0.5 * float(np.linalg.norm(hi - lo))
    target = centre if camera.look_at is None else scene.to_world(camera.look_at)
    up = np.asarray(camera.up, np.float64)
    up = up / np.linalg.norm(up)
    half = math.radians(camera.fov) / 2
    if camera.position is not None:
        eye = scene.to_world(camera.position)
        if np.linalg.norm(target - eye) < 1e-9:
            raise WarpgaussError("--position and --look-at coincide; the camera has no viewing direction")
    else:
        # orbit frame: e1 = x projected normal to up (or y when up is along x), e2 = up x e1
        e1 = np.array([1.0, 0.0, 0.0]) - up * up[0]
        if np.linalg.norm(e1) < 1e-6:
            e1 = np.array([0.0, 1.0, 0.0]) - up * up[1]
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(up, e1)
        az, el = math.radians(camera.azimuth), math.radians(camera.elevation)
        direction = math.cos(el) * (math.cos(az) * e1 + math.sin(az) * e2) + math.sin(el) * up
        if camera.distance is not None:
            dist = float(camera.distance)
        elif camera.ortho:
            dist = 2.0 * radius
        else:
            dist = radius / math.sin(half) * 1.02
        if not camera.ortho:
            dist /= camera.zoom
        eye = target + direction * dist
    forward = target - eye
    forward /= np.linalg.norm(forward)
    if abs(float(np.dot(forward, up))) > 0.9999:  # looking along up: borrow another axis
        up = np.array([0.0, 1.0, 0.0]) if abs(forward[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    true_up = np.cross(right, forward)
    half_height = radius * 1.02 / camera.zoom
    if camera.ortho:  # start rays outside the box
        eye = target - forward * max(float(np.dot(target - eye, forward)), 2.0 * radius)
    return View(eye, right, true_up, forward, math.tan(half), half_height, bool(camera.ortho), int(width), int(height))


# ------------------------------------------------------------------------------------------------
# Settings and results
# ------------------------------------------------------------------------------------------------


@dataclass
class RenderSettings:
    """Image, sampling and lighting options shared by both render paths.

    Attributes:
        width, height: Image size in pixels.
        step: Ray-marching step in world units (voxels of the finest axis).
        density: Extinction per world unit at transfer-function opacity 1; None:
            ``DEFAULT_DENSITY / largest extent`` (a ray through the whole grid at opacity 1 has
            optical depth about 10, whatever the resolution).
        ert: Early ray termination: a ray stops once its transmittance drops below this (0: off).
            .. note:: trades at most ``ert`` of each pixel's value for speed.
        background: RGB in [0, 1].
        shading: Blinn-Phong shading from the field's analytic gradient (headlight by default).
        skip: Empty-space skipping through the occupancy grid (exact; off for timing studies).
    """

    width: int = 512
    height: int = 512
    step: float = 0.5
    density: float | None = None
    ert: float = 1e-3
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    shading: bool = True
    ambient: float = 0.3
    diffuse: float = 0.7
    specular: float = 0.2
    shininess: float = 24.0
    light: tuple[float, float, float] | None = None
    skip: bool = True

    def validate(self) -> None:
        if not (isinstance(self.width, int) and isinstance(self.height, int)) or self.width < 1 or self.height < 1:
            raise WarpgaussError(f"image size must be positive integers, got {self.width}x{self.height}")
        if self.width * self.height > 16384 * 16384:
            raise WarpgaussError(f"image {self.width}x{self.height} is too large (at most 16384x16384 pixels)")
        if not (math.isfinite(self.step) and self.step > 0):
            raise WarpgaussError(f"--step must be a positive number of voxels, got {self.step}")
        if self.density is not None and not (math.isfinite(self.density) and self.density >= 0):
            raise WarpgaussError(f"--density must be a non-negative number, got {self.density}")
        if not (0 <= self.ert < 1):
            raise WarpgaussError(f"--ert must be in [0, 1), got {self.ert}")
        if len(self.background) != 3 or not all(0 <= c <= 1 for c in self.background):
            raise WarpgaussError(f"background must be three values in [0, 1], got {self.background}")

    def density_for(self, scene: Scene) -> float:
        return float(self.density) if self.density is not None else DEFAULT_DENSITY / scene.extent


@dataclass
class Image:
    """A rendered frame.

    Attributes:
        rgba: (H, W, 4) float32: colour composited over the background, alpha = 1 - transmittance.
        seconds: Render time (kernel launches to synchronisation; compilation and, for "cached",
            the one-time decode excluded).
        method: "march", "cached", "splat" or "reference".
        stats: Extra figures (field evaluations per pixel, splats drawn, the cache's shape and
            build seconds...).
    """

    rgba: np.ndarray
    seconds: float = 0.0
    method: str = "march"
    stats: dict = field(default_factory=dict)

    @property
    def rgb(self) -> np.ndarray:
        return self.rgba[..., :3]

    def rgb8(self, alpha: bool = False) -> np.ndarray:
        """(H, W, 3) (or 4 with ``alpha``) uint8, clamped and rounded."""
        c = self.rgba if alpha else self.rgba[..., :3]
        return (np.clip(c, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


# ------------------------------------------------------------------------------------------------
# The marchers
# ------------------------------------------------------------------------------------------------


class _Marcher:
    """What the model and volume renderers share: transfer-function upload, occupancy, launch."""

    def __init__(self, scene: Scene, device: str | None):
        wp = warp()
        from .kernels import render as kr

        self._wp, self._k = wp, kr
        self.device = resolve_device(device)
        self.scene = scene
        wp.load_module(kr, device=self.device)  # compile now, so render times exclude it
        nmax = max(scene.shape_xyz)
        self.cell = float(max(2, math.ceil(nmax / OCCUPANCY_TARGET)))
        dims = tuple(max(1, math.ceil(n / self.cell)) for n in scene.shape_xyz)
        occ = kr.Occupancy()
        occ.cell = self.cell
        occ.dims = wp.vec3i(*dims)
        occ.enabled = 1
        ncell = dims[0] * dims[1] * dims[2]
        occ.touched = wp.zeros(ncell, dtype=int, device=self.device)
        occ.max_value = wp.zeros(ncell, dtype=float, device=self.device)
        occ.state = wp.zeros(ncell, dtype=int, device=self.device)
        self.occ = occ
        self.grid_box = (np.full(3, -0.5), np.asarray(scene.shape_xyz, np.float64) - 0.5)
        self.box_voxels = self.grid_box  # where anything can be seen (narrowed by the model to its supports)
        self._tf_key = None
        self._tf = None

    def transfer_lut(self, tf: TransferFunction):
        """Upload a transfer function (cached while the same one is used)."""
        key = (tf.rgb.tobytes(), tf.opacity.tobytes())
        if key != self._tf_key:
            wp, kr = self._wp, self._k
            lut = kr.TransferLUT()
            lut.rgba = wp.array(tf.rgba, dtype=wp.vec4, device=self.device)
            lut.max_opacity = wp.array(np.maximum.accumulate(tf.opacity).astype(np.float32), dtype=float, device=self.device)
            wp.launch(kr.classify_cells, dim=self.occ.touched.shape[0], inputs=[self.occ, lut], device=self.device)
            self._tf_key, self._tf = key, lut
        return self._tf

    def params(self, settings: RenderSettings, view: View, tf: TransferFunction | None = None):
        wp, kr = self._wp, self._k
        p = kr.MarchParams()
        p.vox_per_world = wp.vec3(*(1.0 / self.scene.world_per_voxel))
        # where V~ = 0 is visible (opacity at 0 > 0) the whole grid box is; else only the supports
        lo, hi = self.grid_box if tf is not None and tf.opacity[0] > 0 else self.box_voxels
        p.box_lo = wp.vec3(*map(float, lo))
        p.box_hi = wp.vec3(*map(float, hi))
        p.step = float(settings.step)
        p.density = settings.density_for(self.scene)
        p.ert = float(settings.ert)
        p.background = wp.vec3(*map(float, settings.background))
        p.shading = int(bool(settings.shading))
        p.ambient, p.diffuse = float(settings.ambient), float(settings.diffuse)
        p.specular, p.shininess = float(settings.specular), float(settings.shininess)
        light = np.zeros(3) if settings.light is None else np.asarray(settings.light, np.float64)
        if np.linalg.norm(light) > 0:
            light = light / np.linalg.norm(light)
        p.light = wp.vec3(*map(float, light))
        return p

    def sample(self, points: np.ndarray, gradient: bool = True) -> np.ndarray:
        """(M, 4) value and gradient (model voxel units) at (M, 3) model voxel positions, as the marcher samples them."""
        wp, kr = self._wp, self._k
        pts = wp.array(np.ascontiguousarray(points, np.float32).reshape(-1, 3), dtype=wp.vec3, device=self.device)
        out = wp.empty(pts.shape[0], dtype=wp.vec4, device=self.device)
        wp.launch(kr.sample_points, dim=pts.shape[0], inputs=[self._source, pts, int(gradient)], outputs=[out], device=self.device)
        return out.numpy()

    def _attach_volume(self, values, shape_xyz: tuple[int, int, int]):
        """Make a device grid (nz, ny, nx) spanning the scene's extent the render source and mark
        the occupancy from its non-zero voxels."""
        wp, kr = self._wp, self._k
        vol = kr.DenseVolume()
        vol.values = values
        vol.scale = wp.vec3(*(float(n) / float(m) for n, m in zip(shape_xyz, self.scene.shape_xyz)))
        nx, ny, nz = shape_xyz
        wp.launch(kr.mark_voxels, dim=(nz, ny, nx), inputs=[vol, self.occ], device=self.device)
        self.volume = self._source = vol
        return vol

    def _march(self, src, view: View, tf: TransferFunction, settings: RenderSettings, method: str) -> Image:
        wp, kr, dev = self._wp, self._k, self.device
        settings.validate()
        lut = self.transfer_lut(tf)
        self.occ.enabled = int(bool(settings.skip))
        h, w = settings.height, settings.width
        image = wp.empty((h, w), dtype=wp.vec4, device=dev)
        evals = wp.empty((h, w), dtype=int, device=dev)
        prm = self.params(settings, view, tf)
        wp.synchronize_device(dev)
        t0 = time.perf_counter()
        wp.launch(kr.march, dim=(h, w), inputs=[src, view.struct(), prm, lut, self.occ], outputs=[image, evals], device=dev)
        wp.synchronize_device(dev)
        seconds = time.perf_counter() - t0
        ev = evals.numpy()
        return Image(image.numpy(), seconds, method, {"evaluations_per_pixel": float(ev.mean()), "max_evaluations": int(ev.max())})


class ModelRenderer(_Marcher):
    """Exact ray marching of a model's mixture field V~ through the binned evaluator (``method="march"``).

    Every sample visits the binned candidates near it and its shading uses the analytic gradient;
    for interactive frame rates march the decoded grid instead (:class:`CachedRenderer`).

    Args:
        model: A :class:`warpgauss.Model`, or (params, header) of one.
        device: Warp device (None: CUDA when present, else CPU).
    """

    def __init__(self, model, device: str | None = None):
        from .field import GaussianField

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

    def render(self, camera: Camera | View | None = None, tf: TransferFunction | None = None, settings: RenderSettings | None = None) -> Image:
        """One frame of the model's field by ray marching."""
        settings = settings or RenderSettings()
        view = camera if isinstance(camera, View) else resolve_view(camera or Camera(), self.scene, settings.width, settings.height)
        return self._march(self.field.prims, view, tf or make_transfer_function(), settings, "march")


class VolumeRenderer(_Marcher):
    """Ray marching of a dense normalised grid (trilinear) with the model's marcher: the reference.

    Args:
        values: (nz, ny, nx) normalised values (float32; masked voxels already 0).
        scene: The grid the camera is placed in (for a comparison, the model's; the volume is
            stretched over that grid's extent).
        device: Warp device.
    """

    def __init__(self, values: np.ndarray, scene: Scene | None = None, device: str | None = None):
        values = np.ascontiguousarray(values, dtype=np.float32)
        if values.ndim != 3 or min(values.shape) < 1:
            raise WarpgaussError(f"a reference volume must be a 3D array, got shape {values.shape}")
        nz, ny, nx = values.shape
        scene = scene or Scene((nx, ny, nz))
        super().__init__(scene, device)
        self._attach_volume(self._wp.array(values, dtype=float, device=self.device), (nx, ny, nz))

    def render(self, camera: Camera | View | None = None, tf: TransferFunction | None = None, settings: RenderSettings | None = None) -> Image:
        """One frame of the dense grid by ray marching (trilinear samples)."""
        settings = settings or RenderSettings()
        view = camera if isinstance(camera, View) else resolve_view(camera or Camera(), self.scene, settings.width, settings.height)
        return self._march(self.volume, view, tf or make_transfer_function(), settings, "reference")


def cache_grid_shape(shape_xyz, cache_res: int | None = None) -> tuple[int, int, int]:
    """The grid a cached renderer decodes onto: the model's own, or ``cache_res`` voxels along its
    longest axis with the others scaled to keep the aspect (at least 1 voxel each).

    Raises:
        WarpgaussError: ``cache_res`` is not a positive integer, or the grid exceeds the int32
            voxel indexing of the kernels.
    """
    from .analysis import MAX_VOXELS

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


def device_memory_bytes(device: str) -> int | None:
    """Memory a new allocation can use on ``device``: free GPU memory, or the machine's RAM for the
    CPU (None when unknown)."""
    wp = warp()
    d = wp.get_device(device)
    if d.is_cuda:
        return int(d.free_memory)
    try:
        return int(os.sysconf("SC_PHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (AttributeError, ValueError, OSError):
        return None


def check_cache_memory(shape_xyz, device: str) -> None:
    """Refuse a cache larger than :data:`CACHE_MEMORY_SHARE` of the device's memory, before allocating it."""
    need = 4 * math.prod(int(n) for n in shape_xyz)  # float32 voxels; the occupancy adds < 1/8 of that
    have = device_memory_bytes(device)
    if have is not None and need > CACHE_MEMORY_SHARE * have:
        raise WarpgaussError(
            f"a {'x'.join(map(str, shape_xyz))} cache needs {need / 2**30:.2f} GiB, more than {CACHE_MEMORY_SHARE:.0%} of the "
            f"{have / 2**30:.2f} GiB available on {device}; choose a smaller --cache-res"
        )


class CachedRenderer(_Marcher):
    """Ray marching of a model's V~ decoded once onto a grid kept on the device.

    The decode is the model's full-grid decode (bricks no primitive reaches are written 0 without
    evaluation, which is their exact value) straight into device memory; the grid is then marched
    as a dense volume: trilinear samples, shading from central differences of one model voxel,
    occupancy from its non-zero voxels. Only camera, transfer function and lighting change between
    frames, so the decode is paid once (:attr:`cache_seconds`).

    .. note:: trades exactness for speed: the image is the exact march's up to the trilinear
       interpolation of the cached grid (a finer ``cache_res`` is closer and costs memory, and the
       decode time grows with the voxel count); it equals :class:`VolumeRenderer` on
       ``model.decode(shape, normalised=True)`` bit for bit.

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
        from .field import DECODE_SLAB_VOXELS, GaussianField
        from .kernels import decode as kd
        from .kernels import field as kf

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
        return 4 * math.prod(self.cache_shape)

    def render(self, camera: Camera | View | None = None, tf: TransferFunction | None = None, settings: RenderSettings | None = None) -> Image:
        """One frame of the cached grid by ray marching (the decode is not repeated)."""
        settings = settings or RenderSettings()
        view = camera if isinstance(camera, View) else resolve_view(camera or Camera(), self.scene, settings.width, settings.height)
        img = self._march(self.volume, view, tf or make_transfer_function(), settings, "cached")
        img.stats.update(cache_shape=list(self.cache_shape), cache_seconds=self.cache_seconds)
        return img


def make_renderer(model, method: str = "march", device: str | None = None, *, cache_res: int | None = None):
    """The renderer of ``method`` ("march", "cached" or "splat") for a model.

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
    from .splat import SplatRenderer

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

    from ._fs import atomic_path, check_writable

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
