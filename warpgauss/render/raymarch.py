"""What every renderer shares: the scene (grid, spacing, extent), the camera and its resolved view,
the render settings, the image, and the ray-marching core (:class:`Marcher`) that the exact, cached
and reference renderers use and the splatter builds on. The renderers are in :mod:`warpgauss.render.renderers`
and :mod:`warpgauss.render.splat`; the kernels in :mod:`warpgauss.kernels.render`.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass

import numpy as np

from ..core.warp import resolve_device, warp
from ..errors import WarpgaussError
from .transfer import TransferFunction

DEFAULT_DENSITY = 10.0  # extinction per world unit at opacity 1 = this / largest extent in world units
OCCUPANCY_TARGET = 128  # occupancy cells per axis at most (cells of at least 2 voxels)

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

    shape_xyz: tuple[int, ...]
    spacing: tuple[float, ...] = (1.0, 1.0, 1.0)
    origin: tuple[float, ...] = (0.0, 0.0, 0.0)

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
        from ..kernels import render as kr

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


class Image:
    """A rendered frame.

    The frame stays on the device until it is asked for: a viewer that only shows it reads back
    its 3-byte RGB8 (:meth:`rgb8`, converted on the device), not the 16-byte float RGBA.

    Attributes:
        rgba: (H, W, 4) float32: colour composited over the background, alpha = 1 - transmittance
            (read back from the device on first use).
        seconds: Render time (kernel launches to synchronisation; compilation and, for "cached",
            the one-time decode excluded).
        method: "march", "cached", "splat" or "reference".
        stats: Extra figures (field evaluations per pixel, splats drawn, the cache's shape and
            build seconds...).
    """

    def __init__(self, rgba, seconds: float = 0.0, method: str = "march", stats: dict | None = None, rgb8_device=None):
        self._rgba = rgba  # (H, W, 4) numpy, or the device's (H, W) vec4 array until read
        self.rgb8_device = rgb8_device  # the same frame as RGB8 converted on the device (numpy or device array), or None
        self.seconds = seconds
        self.method = method
        self.stats = {} if stats is None else stats

    def __repr__(self) -> str:
        return f"Image({self.method}, {self.shape[1]}x{self.shape[0]}, {1000 * self.seconds:.1f} ms)"

    @property
    def shape(self) -> tuple[int, int, int]:
        return (*tuple(self._rgba.shape[:2]), 4)

    @property
    def rgba(self) -> np.ndarray:
        if not isinstance(self._rgba, np.ndarray):
            self._rgba = self._rgba.numpy()
        return self._rgba

    @property
    def rgb(self) -> np.ndarray:
        return self.rgba[..., :3]

    def rgb8(self, alpha: bool = False) -> np.ndarray:
        """(H, W, 3) (or 4 with ``alpha``) uint8, clamped and rounded."""
        if not alpha and self.rgb8_device is not None:
            if not isinstance(self.rgb8_device, np.ndarray):
                self.rgb8_device = self.rgb8_device.numpy()
            return self.rgb8_device
        c = self.rgba if alpha else self.rgba[..., :3]
        return (np.clip(c, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def count_stats(counts, device) -> tuple[float, int]:
    """Mean and maximum of a (H, W) int device array, reduced on the device row by row (exact:
    int64 row sums), so only 12 bytes a row cross to the host."""
    wp = warp()
    from ..kernels import render as kr

    h, w = counts.shape
    sums = wp.empty(h, dtype=wp.int64, device=device)
    maxes = wp.empty(h, dtype=int, device=device)
    wp.launch(kr.row_sums_max, dim=h, inputs=[counts], outputs=[sums, maxes], device=device)
    return float(sums.numpy().sum()) / float(h * w), int(maxes.numpy().max())


# ------------------------------------------------------------------------------------------------
# The marchers
# ------------------------------------------------------------------------------------------------


CACHE_MEMORY_SHARE = 0.5  # a cache may take at most this share of the device's free memory (CPU: of RAM)
GRADIENT_GRID_BYTES = 8  # a dense source's gradient grid: (gx, gy, gz, 0) in half precision a voxel


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


class Marcher:
    """What the model and volume renderers share: transfer-function upload, occupancy, launch."""

    march_tile = 16  # pixels a side of the squares the march's threads go over (1: row by row)

    def __init__(self, scene: Scene, device: str | None):
        wp = warp()
        from ..kernels import render as kr

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
        self._tf_key: tuple[bytes, bytes] | None = None  # (rgb, opacity) bytes of the uploaded transfer function
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

    def _attach_volume(self, values, shape_xyz: tuple[int, ...]):
        """Make a device grid (nz, ny, nx) spanning the scene's extent the render source and mark
        the occupancy from its non-zero voxels.

        Shading reads the gradient from a gradient grid built here (8 bytes a voxel: one fetch of
        8 half-precision vectors a visible sample instead of six trilinear samples, 48 values) when it fits in
        ``CACHE_MEMORY_SHARE`` of the device's free memory; otherwise from central differences
        (:attr:`gradient_grid` says which)."""
        wp, kr = self._wp, self._k
        vol = kr.DenseVolume()
        vol.values = values
        vol.scale = wp.vec3(*(float(n) / float(m) for n, m in zip(shape_xyz, self.scene.shape_xyz)))
        nx, ny, nz = shape_xyz
        have = device_memory_bytes(self.device)
        self.gradient_grid = have is None or GRADIENT_GRID_BYTES * nx * ny * nz <= CACHE_MEMORY_SHARE * have
        if self.gradient_grid:
            vol.grad = wp.empty((nz, ny, nx), dtype=wp.vec4h, device=self.device)
            wp.launch(kr.central_gradient, dim=(nz, ny, nx), inputs=[values, vol.scale], outputs=[vol.grad], device=self.device)
        else:
            vol.grad = wp.zeros((1, 1, 1), dtype=wp.vec4h, device=self.device)
        vol.has_grad = int(self.gradient_grid)
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
        t = prm.tile = int(self.march_tile)
        tiles = ((w + t - 1) // t) * ((h + t - 1) // t)
        wp.launch(kr.march, dim=tiles * t * t, inputs=[src, view.struct(), prm, lut, self.occ], outputs=[image, evals], device=dev)
        wp.synchronize_device(dev)
        seconds = time.perf_counter() - t0
        rgb8 = wp.empty((h, w, 3), dtype=wp.uint8, device=dev)
        wp.launch(kr.to_rgb8, dim=(h, w), inputs=[image], outputs=[rgb8], device=dev)
        mean, most = count_stats(evals, dev)
        stats = {"evaluations_per_pixel": mean, "max_evaluations": most}
        return Image(image, seconds, method, stats, rgb8_device=rgb8)
