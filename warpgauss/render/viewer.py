"""What `warpgauss serve` shows, without the web page: a view of one model (or a series of them)
that orbits, zooms, takes a transfer function and renders frames with our own renderers.

The page (:mod:`warpgauss.render.serve`) only forwards the browser's mouse and widget events here and
streams the frames back; everything a frame depends on is in :class:`ViewState`, so the same
frame can be rendered again by ``warpgauss render`` (:meth:`Viewer.render_command`) and tested on
the CPU without a browser.

    v = Viewer([warpgauss.Model.load("vortex.wgs")], device="cpu")
    v.orbit(40, 0)                      # a drag of 40 pixels to the left
    v.set_opacity([(0, 0), (0.3, 0), (1, 1)])
    rgb = v.frame()                     # (H, W, 3) uint8
"""

from __future__ import annotations

import json
import shlex
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..errors import WarpgaussError
from .transfer import LUT_SIZE, TransferFunction, colormap, colormap_names, from_header

ORBIT_DEGREES_PER_PIXEL = 0.4  # a drag across a 512-pixel view turns the camera about 200 degrees
WHEEL_ZOOM = 1.1  # one wheel notch
PRESETS = ("viridis", "magma", "inferno", "plasma", "cividis", "turbo", "coolwarm", "jet", "grayscale")
COLOR_NODES = 9  # colour nodes a preset gives the editor
HISTOGRAM_BINS = 32  # bins of the editor's histogram
TF_FILE = "view_tf.json"  # where the page's download and the render command put edited colours


@dataclass
class ViewState:
    """Everything a frame depends on (the page's state, and what ``render_command`` writes)."""

    azimuth: float = -55.0
    elevation: float = 25.0
    zoom: float = 1.0
    width: int = 512
    height: int = 512
    colormap: str = "viridis"
    colors: list | None = None  # editor colour nodes [[x, [r, g, b]], ...]; None: the colormap's
    opacity: list = field(default_factory=lambda: [[0.0, 0.0], [1.0, 1.0]])  # [[x, a], ...]
    shading: bool = True
    density_scale: float = 1.0  # times the renderer's default extinction
    method: str = "cached"
    time: int = 0
    compare: bool = False


class Viewer:
    """Frames of a model series under a :class:`ViewState` (see the module docstring).

    Args:
        models: One model, or a series (the time slider's steps), all on one grid.
        paths: The models' files (for the facts and the render command), or None.
        volume: The source volume (normalised to [0, 1], (nz, ny, nx)) for "compare with volume",
            or None; with a series, a list of one volume per model.
        device: Warp device (None: CUDA when present, else CPU).
        method: "cached" (default), "march" or "splat".
        cache_res: "cached": voxels along the cache's longest axis (None: the model grid).
    """

    def __init__(self, models, paths=None, volume=None, device: str | None = None, method: str = "cached", cache_res: int | None = None):
        from ..core.warp import resolve_device
        from .renderers import METHODS

        self.models = list(models) if isinstance(models, (list, tuple)) else [models]
        if not self.models:
            raise WarpgaussError("nothing to show: give a model (.wgs)")
        grids = {tuple(m.shape_xyz) for m in self.models}
        if len(grids) > 1:
            raise WarpgaussError(
                "a series shown together must share one grid; these models are on "
                + ", ".join("x".join(map(str, g)) for g in sorted(grids))
            )
        if method not in METHODS:
            raise WarpgaussError(f"unknown render method {method!r}; use {', '.join(METHODS)}")
        self.paths = [None] * len(self.models) if paths is None else [None if p is None else str(p) for p in paths]
        vols = volume if isinstance(volume, (list, tuple)) else [volume] * len(self.models) if volume is not None else None
        if vols is not None and len(vols) != len(self.models):
            raise WarpgaussError(f"{len(vols)} volumes for {len(self.models)} models: give one volume per timestep")
        self.volumes = vols
        self.device = resolve_device(device)
        self.cache_res = cache_res
        tf = from_header(self.models[0].header)
        self.state = ViewState(
            method=method,
            colormap=tf.name if tf.name in colormap_names() else "viridis",
            opacity=[[float(x), float(a)] for x, a in (tf.source.get("opacity") or [[0.0, 0.0], [1.0, 1.0]])],
        )
        self._renderers: dict = {}
        self._reference: dict = {}
        self._hist: dict = {}
        self._facts: dict = {}
        self.last_seconds = 0.0  # the last frame's wall time (render, RGB8, copy to the host)

    # -- interaction ------------------------------------------------------------------------
    def orbit(self, dx: float, dy: float) -> None:
        """A drag of (dx, dy) pixels (x right, y up): the camera turns around the grid."""
        s = self.state
        s.azimuth = (s.azimuth - ORBIT_DEGREES_PER_PIXEL * float(dx) + 180.0) % 360.0 - 180.0
        s.elevation = float(np.clip(s.elevation - ORBIT_DEGREES_PER_PIXEL * float(dy), -89.0, 89.0))

    def zoom_by(self, notches: float) -> None:
        """Wheel notches (positive: closer)."""
        self.state.zoom = float(np.clip(self.state.zoom * WHEEL_ZOOM ** float(notches), 0.05, 50.0))

    def set_opacity(self, points) -> None:
        pts = sorted([float(x), float(np.clip(a, 0.0, 1.0))] for x, a in points)
        if len(pts) < 2:
            raise WarpgaussError("an opacity curve needs at least two points")
        self.state.opacity = pts

    def set_colors(self, nodes) -> None:
        """Editor colour nodes [[x, [r, g, b]], ...] (None: back to the colormap)."""
        self.state.colors = None if nodes is None else sorted([float(x), [float(c) for c in rgb]] for x, rgb in nodes)

    def set_colormap(self, name: str) -> None:
        colormap(name)  # refuses an unknown name
        self.state.colormap, self.state.colors = name, None

    def resize(self, width: int, height: int) -> None:
        self.state.width, self.state.height = max(16, int(width)), max(16, int(height))

    def color_nodes(self) -> list:
        """The editor's colour nodes: the state's, or :data:`COLOR_NODES` samples of the colormap."""
        if self.state.colors is not None:
            return self.state.colors
        lut = colormap(self.state.colormap)
        xs = np.linspace(0.0, 1.0, COLOR_NODES)
        idx = np.round(xs * (len(lut) - 1)).astype(int)
        return [[float(x), [float(c) for c in lut[i]]] for x, i in zip(xs, idx)]

    # -- rendering ----------------------------------------------------------------------------
    def transfer_function(self, state: ViewState | None = None) -> TransferFunction:
        s = state or self.state
        if s.colors is None:
            tf = TransferFunction(colormap(s.colormap), np.zeros(LUT_SIZE), s.colormap, {"colormap": s.colormap})
        else:
            x = np.linspace(0.0, 1.0, LUT_SIZE)
            xs = np.array([c[0] for c in s.colors])
            rgb = np.array([c[1] for c in s.colors])
            tf = TransferFunction(
                np.stack([np.interp(x, xs, rgb[:, k]) for k in range(3)], 1), np.zeros(LUT_SIZE), "custom", {"colors": s.colors}
            )
        return tf.with_opacity([tuple(p) for p in s.opacity])

    def _renderer(self, s: ViewState):
        from .renderers import make_renderer

        key = (s.time, s.method)
        if key not in self._renderers:
            if len(self._renderers) >= 4:  # keep a few timesteps' caches, not a whole series
                self._renderers.pop(next(iter(self._renderers)))
            self._renderers[key] = make_renderer(
                self.models[s.time], s.method, self.device, cache_res=self.cache_res if s.method == "cached" else None
            )
        return self._renderers[key]

    def _reference_renderer(self, s: ViewState):
        from .raymarch import Scene
        from .renderers import VolumeRenderer

        t = s.time
        assert self.volumes is not None  # the comparison view exists only with the source volumes
        if t not in self._reference:
            self._reference.clear()
            self._reference[t] = VolumeRenderer(
                np.asarray(self.volumes[t], np.float32), Scene.from_header(self.models[t].header), self.device
            )
        return self._reference[t]

    def settings(self, width: int | None = None, state: ViewState | None = None):
        from .raymarch import DEFAULT_DENSITY, RenderSettings, Scene

        s = state or self.state
        scene = Scene.from_header(self.models[s.time].header)
        return RenderSettings(
            width=width or s.width, height=s.height, shading=s.shading, density=s.density_scale * DEFAULT_DENSITY / scene.extent
        )

    def camera(self, state: ViewState | None = None):
        from .raymarch import Camera

        s = state or self.state
        return Camera(azimuth=s.azimuth, elevation=s.elevation, zoom=s.zoom)

    def snapshot(self) -> ViewState:
        """A copy of the current state (what a frame rendered elsewhere, e.g. in a thread, draws)."""
        return replace(
            self.state,
            colors=None if self.state.colors is None else [list(c) for c in self.state.colors],
            opacity=[list(p) for p in self.state.opacity],
        )

    def frame(self, state: ViewState | None = None) -> np.ndarray:
        """The view as (H, W, 3) uint8 (``state``: a :meth:`snapshot`, default the current state);
        with ``compare`` (and a volume) the model's half beside the volume's, each half the width."""
        t0 = time.perf_counter()
        s = state or self.state
        tf = self.transfer_function(s)
        cam = self.camera(s)
        if s.compare and self.volumes is not None:
            half = max(8, s.width // 2)
            a = self._renderer(s).render(cam, tf, self.settings(half, s)).rgb8()
            b = self._reference_renderer(s).render(cam, tf, self.settings(s.width - half, s)).rgb8()
            img = np.concatenate([a, b], axis=1)
        else:
            img = self._renderer(s).render(cam, tf, self.settings(None, s)).rgb8()
        self.last_seconds = time.perf_counter() - t0
        return np.ascontiguousarray(img)

    # -- what the page shows beside the frame -----------------------------------------------------
    def histogram(self, bins: int = HISTOGRAM_BINS) -> list:
        """The editor's histogram: [[x, log-scaled share], ...] of the normalised values of the
        source volume if given, else of the model decoded at up to 64 voxels along its longest axis."""
        t = self.state.time
        if t not in self._hist:
            if self.volumes is not None:
                v = np.asarray(self.volumes[t], np.float32)
            else:
                m = self.models[t]
                k = min(1.0, 64.0 / max(m.shape_xyz))
                v = m.decode(shape_xyz=tuple(max(1, round(n * k)) for n in m.shape_xyz), device=self.device, normalised=True)
            counts, _ = np.histogram(np.clip(v, 0.0, 1.0), bins=bins, range=(0.0, 1.0))
            h = np.log1p(counts.astype(np.float64))
            h = h / h.max() if h.max() > 0 else h
            self._hist[t] = [[float((i + 0.5) / bins), float(c)] for i, c in enumerate(h)]
        return self._hist[t]

    def facts(self) -> dict:
        """N, file bytes, compression ratio and PSNR (from the model's report file, if beside it)."""
        t = self.state.time
        if t not in self._facts:
            self._facts[t] = self._read_facts(t)
        return self._facts[t]

    def _read_facts(self, t: int) -> dict:
        m = self.models[t]
        path = self.paths[t]
        src = m.source_bytes
        size = Path(path).stat().st_size if path and Path(path).is_file() else None
        psnr = None
        if path and Path(path + ".report.json").is_file():
            try:
                psnr = json.loads(Path(path + ".report.json").read_text()).get("psnr_db")
            except (OSError, ValueError):
                psnr = None
        return {
            "n": int(m.n),
            "bytes": size,
            "ratio": None if not size else src / size,
            "psnr_db": psnr,
            "grid": "x".join(str(int(v)) for v in m.shape_xyz),
            "steps": len(self.models),
        }

    def tf_json(self) -> str:
        """The current transfer function as our ``.json`` (what ``warpgauss render --tf`` reads)."""
        s = self.state
        colors = [[x, *rgb] for x, rgb in self.color_nodes()]
        return json.dumps({"name": "warpgauss serve view", "colors": colors, "opacity": s.opacity})

    def render_command(self, output: str = "view.png", tf_file: str = TF_FILE) -> str:
        """The ``warpgauss render`` command that draws the current view (model half only); with
        edited colours it reads them from ``tf_file`` (write :meth:`tf_json` there)."""
        s = self.state
        path = self.paths[s.time] or "MODEL.wgs"
        args = ["warpgauss", "render", path, "-o", output, "--method", s.method, "--size", f"{s.width}x{s.height}"]
        args += ["--azimuth", f"{s.azimuth:.4f}", "--elevation", f"{s.elevation:.4f}", "--zoom", f"{s.zoom:.6f}"]
        if s.colors is None:
            args += ["--colormap", s.colormap, "--opacity", ",".join(f"{x:.6g}:{a:.6g}" for x, a in s.opacity)]
        else:
            args += ["--tf", tf_file]
        if s.density_scale != 1.0:
            from .raymarch import DEFAULT_DENSITY, Scene

            args += ["--density", f"{s.density_scale * DEFAULT_DENSITY / Scene.from_header(self.models[s.time].header).extent:.6g}"]
        if not s.shading:
            args.append("--no-shading")
        if self.cache_res is not None and s.method == "cached":
            args += ["--cache-res", str(self.cache_res)]
        return " ".join(shlex.quote(a) for a in args)

    def with_state(self, **changes) -> Viewer:
        """This viewer with some state changed (the renderers are shared)."""
        self.state = replace(self.state, **changes)
        return self


def load_models(paths) -> tuple[list, list[str]]:
    """Models from paths or a glob pattern (sorted), refused in one line when none match."""
    import glob

    from ..format.model import Model

    items = [paths] if isinstance(paths, (str, Path)) else list(paths)
    found: list[str] = []
    for p in items:
        p = str(p)
        if any(c in p for c in "*?["):
            hits = sorted(glob.glob(p))
            if not hits:
                raise WarpgaussError(f"no model matches {p!r}")
            found += hits
        elif not Path(p).is_file():
            raise WarpgaussError(f"no such model: {p}")
        else:
            found.append(p)
    return [Model.load(p) for p in found], found
