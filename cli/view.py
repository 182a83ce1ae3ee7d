"""`warpgauss view`: an interactive window (pyvista/VTK) showing frames from our renderers.

VTK owns the window, the mouse (orbit, pan, zoom through its trackball camera) and the keys; every
frame is drawn by one of our renderers from VTK's camera and shown as the window's background
image, with the grid's outline drawn by VTK on top for orientation.

Methods: ``cached`` (the default: the model decoded once onto a grid, kept on the device and ray
marched as a dense volume, :class:`~warpgauss.render.renderers.CachedRenderer`), ``splat``
(:class:`~warpgauss.render.splat.SplatRenderer`) and ``march``, the exact ray marching of V~
(:class:`~warpgauss.render.renderers.ModelRenderer`): seconds per frame for large models, so while the mouse
drags the camera its frames come from the cached grid and the exact frame is drawn once the
camera stops. Keys: ``c`` next colormap, ``o`` next opacity curve, ``+``/``-`` density x/÷ 1.5,
``m`` next method (cached -> splat -> march), ``l`` shading on/off; a slider sets the density too.
``--screenshot PATH`` renders one frame off-screen and exits (what the tests run).
"""

from __future__ import annotations

import math
import os
import sys
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import typer

from warpgauss.errors import WarpgaussError

from .common import handle_errors, out_console
from .render import check_png, parse_colour, parse_size

COLORMAPS = ("viridis", "magma", "inferno", "plasma", "cividis", "turbo", "coolwarm", "grayscale")
METHODS = ("cached", "splat", "march", "bounded")  # the order the m key cycles through ("bounded": with a residual only)
OPACITIES = ("linear", "0:0,0.3:0,1:1", "0:0,0.6:0,1:1", "0:0,0.5:0.8,1:0", "0.3")


def display_available() -> bool:
    """Whether a window can be opened (an X11/Wayland display on Linux; assumed elsewhere)."""
    if sys.platform.startswith("linux") or "bsd" in sys.platform:
        return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
    return True


class Viewer:
    """A pyvista plotter whose background is our rendering of the model from VTK's camera.

    Args:
        model: The :class:`warpgauss.Model`.
        method: "cached" (ray marching of the decoded grid, interactive speed), "splat" or "march"
            (exact; frames while dragging come from the cached grid).
        size: Window (width, height).
        off_screen: Render without a window (screenshots, tests).
        cache_res: Voxels along the cache grid's longest axis (None: the model's grid).
    """

    def __init__(
        self,
        model,
        *,
        method="cached",
        size=(768, 768),
        tf=None,
        settings=None,
        camera=None,
        device=None,
        off_screen=False,
        preview_scale=0.5,
        cache_res=None,
    ):
        import pyvista as pv
        from vtkmodules.vtkCommonDataModel import vtkImageData
        from vtkmodules.vtkRenderingCore import vtkImageActor, vtkRenderer

        from warpgauss.render.renderers import Camera, RenderSettings, resolve_view
        from warpgauss.render.transfer import from_header

        if method not in METHODS:
            raise WarpgaussError(f"--method must be cached, splat, march or bounded, got {method!r}")
        if method == "bounded" and model.residual is None:
            raise WarpgaussError("--method bounded draws a model's decode with its residual; this one has none (encode with --max-error)")
        self.methods = METHODS if model.residual is not None else METHODS[:-1]
        self.model = model
        self.device = device
        self.cache_res = cache_res
        self._cache: dict = {}
        self.method = method
        self.tf = tf or from_header(model.header)
        self.cmap_index = 0 if self.tf.name not in COLORMAPS else COLORMAPS.index(self.tf.name)
        self.opacity_index = 0
        self.settings = settings or RenderSettings()
        self.preview_scale = float(preview_scale)
        self.interacting = False
        r = self.renderer()
        scene = r.scene
        self.density = self.settings.density_for(scene)

        if off_screen:  # no "bad X server connection" chatter when there is no display to connect to
            from vtkmodules.vtkCommonCore import vtkLogger

            vtkLogger.SetStderrVerbosity(vtkLogger.VERBOSITY_ERROR)
        # pyvista's annotations (Optional windows, decorated key events) do not follow its use here
        self.plotter: Any = pv.Plotter(off_screen=off_screen, window_size=list(size))
        pl: Any = self.plotter
        lo, hi = scene.box
        pl.add_mesh(pv.Box(bounds=(lo[0], hi[0], lo[1], hi[1], lo[2], hi[2])).outline(), color="white", opacity=0.35)
        view = resolve_view(camera or Camera(), scene, size[0], size[1])
        target = view.eye + view.forward * float(np.linalg.norm(0.5 * (lo + hi) - view.eye))
        pl.camera.position = tuple(view.eye)
        pl.camera.focal_point = tuple(target)
        pl.camera.up = tuple(view.up)
        pl.camera.view_angle = math.degrees(2 * math.atan(view.tan_half))
        if view.ortho:
            pl.camera.enable_parallel_projection()
            pl.camera.parallel_scale = view.half_height
        pl.renderer.ResetCameraClippingRange()

        # our frame lives in a background layer, drawn as an image actor that fills the viewport
        self._image = vtkImageData()
        self._actor = vtkImageActor()
        self._actor.GetMapper().SetInputData(self._image)
        self._bg = vtkRenderer()
        self._bg.SetLayer(0)
        self._bg.InteractiveOff()
        self._bg.AddActor(self._actor)
        pl.ren_win.SetNumberOfLayers(2)
        pl.renderer.SetLayer(1)
        pl.ren_win.AddRenderer(self._bg)
        self._text = pl.add_text("", position="upper_left", font_size=9, color="white")
        self._last = None
        pl.ren_win.AddObserver("StartEvent", self._on_start)
        pl.iren.add_observer("StartInteractionEvent", self._start_interaction)
        pl.iren.add_observer("EndInteractionEvent", self._end_interaction)
        for key in ("plus", "minus"):
            pl.clear_events_for_key(key)
        pl.add_key_event("c", self.next_colormap)
        pl.add_key_event("o", self.next_opacity)
        pl.add_key_event("plus", lambda: self.scale_density(1.5))
        pl.add_key_event("minus", lambda: self.scale_density(1 / 1.5))
        pl.add_key_event("m", self.toggle_method)
        pl.add_key_event("l", self.toggle_shading)
        if not off_screen:  # the slider is for hands; screenshots show the frame alone
            d = self.density
            pl.add_slider_widget(
                lambda v: self.set_density(10.0**v),
                [math.log10(d) - 2, math.log10(d) + 2],
                value=math.log10(d),
                title="log10 density",
                pointa=(0.55, 0.08),
                pointb=(0.95, 0.08),
                style="modern",
            )

    # -- state changes (each redraws) --------------------------------------------------------
    def renderer(self, method: str | None = None):
        """The renderer of ``method`` (default: the current one), built on first use."""
        from warpgauss.render.renderers import make_renderer

        method = method or self.method
        if method not in self._cache:
            self._cache[method] = make_renderer(self.model, method, self.device, cache_res=self.cache_res if method == "cached" else None)
        return self._cache[method]

    def frame_method(self) -> str:
        """What draws the next frame: the exact march hands frames during a drag to the cached grid."""
        return "cached" if self.method == "march" and self.interacting else self.method

    def next_colormap(self):
        self.cmap_index = (self.cmap_index + 1) % len(COLORMAPS)
        self.tf = self.tf.with_colormap(COLORMAPS[self.cmap_index])
        self.redraw()

    def next_opacity(self):
        self.opacity_index = (self.opacity_index + 1) % len(OPACITIES)
        self.tf = self.tf.with_opacity(OPACITIES[self.opacity_index])
        self.redraw()

    def scale_density(self, f: float):
        self.set_density(self.density * f)

    def set_density(self, d: float):
        self.density = float(d)
        self.redraw()

    def toggle_method(self):
        self.method = self.methods[(self.methods.index(self.method) + 1) % len(self.methods)]
        self.redraw()

    def toggle_shading(self):
        self.settings.shading = not self.settings.shading
        self.redraw()

    def redraw(self):
        self._last = None
        self.plotter.render()

    def _start_interaction(self, *_):
        self.interacting = True

    def _end_interaction(self, *_):
        self.interacting = False
        self.redraw()

    # -- drawing ------------------------------------------------------------------------------
    def vtk_view(self, width: int, height: int):
        """Our :class:`~warpgauss.render.renderers.View` from VTK's camera."""
        from warpgauss.render.renderers import View

        cam = self.plotter.camera
        eye = np.asarray(cam.position, np.float64)
        forward = np.asarray(cam.focal_point, np.float64) - eye
        forward /= np.linalg.norm(forward)
        up = np.asarray(cam.up, np.float64)
        right = np.cross(forward, up)
        right /= np.linalg.norm(right)
        up = np.cross(right, forward)
        ortho = bool(cam.parallel_projection)
        return View(eye, right, up, forward, math.tan(math.radians(cam.view_angle) / 2), float(cam.parallel_scale), ortho, width, height)

    def frame(self, width: int, height: int):
        """Render one frame of the current state at the given size (an :class:`~warpgauss.render.renderers.Image`)."""
        from warpgauss.render.renderers import with_settings

        s = with_settings(self.settings, width=int(width), height=int(height), density=self.density)
        return self.renderer(self.frame_method()).render(self.vtk_view(int(width), int(height)), self.tf, s)

    def _on_start(self, *_):
        w, h = self.plotter.ren_win.GetSize()
        if w < 1 or h < 1:
            return
        scale = self.preview_scale if self.interacting else 1.0
        fw, fh = max(1, int(w * scale)), max(1, int(h * scale))
        cam = self.plotter.camera
        key = (fw, fh, self.frame_method(), tuple(cam.position), tuple(cam.focal_point), tuple(cam.up), cam.view_angle, cam.parallel_scale)
        if key == self._last:
            return
        self._last = key
        img = self.frame(fw, fh)
        self._show(img.rgb8(), w, h)
        self._text.SetText(
            2,
            f"{img.method}  {self.tf.name}  opacity {OPACITIES[self.opacity_index]}  density {self.density:.3g}  "
            f"{'shaded' if self.settings.shading else 'flat'}  {img.seconds * 1000:.0f} ms\n"
            "c colormap  o opacity  +/- density  m cached/splat/march  l shading",
        )

    def _show(self, rgb8: np.ndarray, w: int, h: int):
        from vtkmodules.util.numpy_support import numpy_to_vtk

        fh, fw = rgb8.shape[:2]
        flipped = np.ascontiguousarray(rgb8[::-1].reshape(-1, 3))  # VTK images start at the bottom row
        self._image.SetDimensions(fw, fh, 1)
        self._image.SetSpacing(w / fw, h / fh, 1.0)
        self._image.GetPointData().SetScalars(numpy_to_vtk(flipped, deep=True))
        self._image.Modified()
        cam = self._bg.GetActiveCamera()
        cam.ParallelProjectionOn()
        cx, cy = 0.5 * (w - w / fw), 0.5 * (h - h / fh)
        cam.SetFocalPoint(cx, cy, 0.0)
        cam.SetPosition(cx, cy, 1.0)
        cam.SetViewUp(0.0, 1.0, 0.0)
        cam.SetParallelScale(0.5 * h)
        self._bg.ResetCameraClippingRange()

    def screenshot(self, path) -> None:
        """Render one frame off-screen and write it (PNG, atomic)."""
        from warpgauss.core.files import atomic_path

        self.redraw()
        with atomic_path(path) as tmp:
            self.plotter.screenshot(str(tmp))

    def show(self) -> None:
        self.plotter.show(title="warpgauss view")


@handle_errors
def view(
    model: Annotated[Path, typer.Argument(help="Model file (.wgs)")],
    method: Annotated[
        str,
        typer.Option(
            help="cached (ray marching of V~ decoded once onto a grid; interactive), splat (EWA splatting), march (exact ray marching; dragging shows the cached grid) or bounded (a model's decode with its residual)"
        ),
    ] = "cached",
    cache_res: Annotated[
        int | None, typer.Option("--cache-res", help="Voxels along the cache grid's longest axis, aspect kept (default: the model's grid)")
    ] = None,
    size: Annotated[str, typer.Option(help="Window size N or WxH")] = "768",
    colormap: Annotated[str | None, typer.Option(help="Start colormap (default: the model's)")] = None,
    opacity: Annotated[str | None, typer.Option(help="Start opacity curve value:opacity,...")] = None,
    tf: Annotated[Path | None, typer.Option("--tf", help="Transfer function .json (ours or ParaView)")] = None,
    density: Annotated[float | None, typer.Option(help="Start density (extinction per voxel at opacity 1)")] = None,
    background: Annotated[str, typer.Option(help="black, white, gray, paraview, #rrggbb or r,g,b")] = "black",
    azimuth: Annotated[float, typer.Option(help="Start azimuth in degrees")] = -55.0,
    elevation: Annotated[float, typer.Option(help="Start elevation in degrees")] = 25.0,
    zoom: Annotated[float, typer.Option(help="Start magnification")] = 1.0,
    preview_scale: Annotated[float, typer.Option(help="Resolution factor while dragging (0.1-1)")] = 0.5,
    screenshot: Annotated[Path | None, typer.Option(help="Render one frame off-screen to this .png and exit")] = None,
    device: Annotated[str | None, typer.Option(help="Warp device: cpu, cuda, cuda:N")] = None,
    force: Annotated[bool, typer.Option("--force", help="Overwrite an existing screenshot")] = False,
) -> None:
    """Open an interactive window (orbit, zoom, colormap/opacity/density keys) showing our renderer's frames."""
    from warpgauss.core.files import check_writable
    from warpgauss.format.model import Model
    from warpgauss.render.renderers import Camera, RenderSettings
    from warpgauss.render.transfer import resolve_transfer_function

    if method not in METHODS:
        raise WarpgaussError(f"--method must be cached, splat, march or bounded, got {method!r}")
    if cache_res is not None and cache_res < 1:
        raise WarpgaussError(f"--cache-res must be a positive number of voxels along the longest axis, got {cache_res}")
    if not 0.1 <= preview_scale <= 1.0:
        raise WarpgaussError(f"--preview-scale must be in [0.1, 1], got {preview_scale}")
    if screenshot is None and not display_available():
        raise WarpgaussError(
            "no display is available (DISPLAY is not set); use --screenshot PATH for an off-screen frame, or warpgauss render"
        )
    if screenshot is not None:
        check_png(screenshot)
        check_writable(screenshot, force=force)
    w, h = parse_size(size)
    m = Model.load(model)
    if method in ("cached", "march"):  # march drags on the cached grid too; refuse what cannot be held first
        from warpgauss.core.warp import resolve_device
        from warpgauss.render.renderers import cache_grid_shape, check_cache_memory

        check_cache_memory(cache_grid_shape(m.shape_xyz, cache_res), resolve_device(device))
    tfn = resolve_transfer_function(m.header, path=tf, colormap_name=colormap, opacity=opacity)
    settings = RenderSettings(density=density, background=parse_colour(background))
    settings.validate()
    camera = Camera(azimuth=azimuth, elevation=elevation, zoom=zoom)
    camera.validate()
    viewer = Viewer(
        m,
        method=method,
        size=(w, h),
        tf=tfn,
        settings=settings,
        camera=camera,
        device=device,
        off_screen=screenshot is not None,
        preview_scale=preview_scale,
        cache_res=cache_res,
    )
    if screenshot is not None:
        viewer.screenshot(screenshot)
        out_console.print(f"wrote {screenshot} ({w}x{h}, {method}, off-screen)")
        return
    viewer.show()
