"""`warpgauss serve`: a web page (Kitware's trame) showing a model rendered on the server by our own
renderers, streamed to the browser as images (trame-rca), with ParaView's colour/opacity editor
(trame-color-opacity-editor), colormap presets, shading, density, a time slider for a series and
a "compare with volume" toggle.

Everything a frame depends on lives in a :class:`warpgauss.render.viewer.Viewer`; this module only maps
the page's widgets and mouse events onto it. The page shows the frame time, the model's facts and
the ``warpgauss render`` command that draws the same view.

The trame packages are an optional extra: ``pip install "warpgauss[serve]"``.
"""

from __future__ import annotations

import json
import time
from typing import Any

from ..errors import WarpgaussError
from .viewer import PRESETS, TF_FILE, Viewer

READY_PREFIX = "warpgauss serve: "  # the line printed once the page is served (tests read its URL)


def require_trame():
    try:
        import trame  # noqa: F401
        import trame_color_opacity_editor  # noqa: F401
        import trame_rca  # noqa: F401
        import trame_vuetify  # noqa: F401
    except ImportError as e:
        raise WarpgaussError(f'warpgauss serve needs the trame packages ({e.name} is missing): pip install "warpgauss[serve]"') from None


class Area:
    """The image source trame-rca asks for frames (its RemoteControlledAreaProtocol).

    trame-rca asks on the server's event loop; a frame that takes long (exact marching, a large
    model on the CPU) would block the page meanwhile. So after the first frame, a frame for a new
    state is rendered in a worker thread from a snapshot of the state, the last finished frame is
    shown until it is done, and then the page is told (``request_update``) to fetch it; a state
    changed meanwhile starts the next render. Mouse events turn into orbit and zoom."""

    def __init__(self, viewer: Viewer, on_frame, request_update=None):
        from concurrent.futures import ThreadPoolExecutor

        self.viewer = viewer
        self.on_frame = on_frame
        self.request_update = request_update
        self._key: str | None = None  # the state the shown frame draws
        self._failed: str | None = None  # a state whose frame failed (not retried)
        self._img: Any = None  # the shown frame (an image array)
        self._busy = False
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="warpgauss-frame")
        self._press: tuple[Any, Any] | None = None  # (x, y) of the last left-button position while dragging

    @property
    def img_cols_rows(self):
        import asyncio

        key = json.dumps(self.viewer.state.__dict__, sort_keys=True)
        if self._img is None:  # the first frame: nothing to show meanwhile
            self._img, self._key = self.viewer.frame(), key
            self.on_frame(self.viewer.last_seconds)
        elif key not in (self._key, self._failed) and not self._busy:
            try:
                loop = asyncio.get_running_loop()
            except RuntimeError:
                loop = None
            if loop is None:  # no event loop (a direct call): render here
                self._img, self._key = self.viewer.frame(), key
                self.on_frame(self.viewer.last_seconds)
            else:
                self._busy = True
                self._pool.submit(self._render, loop, key, self.viewer.snapshot())
        h, w = self._img.shape[:2]
        return self._img, w, h

    def _render(self, loop, key, state) -> None:
        try:
            img, err = self.viewer.frame(state), None
        except Exception as e:  # noqa: BLE001 - shown in one line; the page keeps the last frame
            img, err = None, e
        loop.call_soon_threadsafe(self._done, key, img, err)

    def _done(self, key, img, err) -> None:
        self._busy = False
        if img is None:
            self._failed = key
            print(f"warpgauss serve: a frame failed ({err}); the page keeps the last one", flush=True)
        else:
            self._img, self._key = img, key
            self.on_frame(self.viewer.last_seconds)
        if self.request_update is not None:
            self.request_update()  # trame-rca asks again: the new frame, or a render of a newer state

    def process_resize_event(self, width, height):
        self.viewer.resize(width, height)

    def process_interaction_event(self, event):
        kind = event.get("type", "")
        if kind == "LeftButtonPress":
            self._press = (event.get("x", 0), event.get("y", 0))
        elif kind == "LeftButtonRelease":
            self._press = None
        elif kind == "MouseMove" and self._press is not None and event.get("buttonLeft", 1):
            x, y = event.get("x", 0), event.get("y", 0)
            self.viewer.orbit(x - self._press[0], y - self._press[1])  # y counts up from the bottom
            self._press = (x, y)
            return True
        elif kind == "MouseWheel":
            self.viewer.zoom_by(-float(event.get("spinY", 0.0)))
            return True
        return False


def _controls(viewer: Viewer) -> None:
    """The page's right-hand panel (inside the layout being built): facts, frame time, renderer,
    colormap, transfer function, shading, density, time step, comparison, the command line."""
    from trame.widgets import color_opacity_editor as coe
    from trame.widgets import html
    from trame.widgets import vuetify3 as v3

    with html.Div(style="width:380px;overflow-y:auto;font-size:13px"):
        html.Div("{{ facts }}", id="facts", style="white-space:pre-line;margin-bottom:8px")
        html.Div("frame {{ frame_ms }} ms", id="frame_ms", style="margin-bottom:8px")
        v3.VSelect(
            label="renderer",
            v_model=("method",),
            items=("['cached', 'march', 'splat'" + (", 'bounded'" if any(m.residual is not None for m in viewer.models) else "") + "]",),
            density="compact",
            id="method",
        )
        v3.VSelect(
            label="colormap",
            v_model=("colormap",),
            items=("[" + ", ".join(f"'{p}'" for p in PRESETS) + "]",),
            density="compact",
            id="colormap",
        )
        coe.ColorOpacityEditor(
            v_model_colorNodes=("colors",),
            v_model_opacityNodes=("opacities",),
            scalar_range=("[0, 1]",),
            histograms=("hist",),
            histograms_range=("[0, 1]",),
            show_histograms=True,
            style="width:100%;height:200px;",
            id="coe",
        )
        v3.VSwitch(label="shading", v_model=("shading",), density="compact", hide_details=True, id="shading")
        v3.VSlider(label="density (log10)", v_model=("density_log",), min=-1.5, max=1.5, step=0.1, hide_details=True, id="density")
        v3.VSlider(
            label="time step",
            v_model=("time",),
            min=0,
            max=("steps - 1",),
            step=1,
            v_show=("steps > 1",),
            hide_details=True,
            id="time",
        )
        v3.VSwitch(
            label="compare with volume",
            v_model=("compare",),
            v_show=("has_volume",),
            density="compact",
            hide_details=True,
            id="compare",
        )
        html.Div("the same view on the command line:", style="margin-top:8px")
        html.Code("{{ command }}", id="command", style="display:block;word-break:break-all;font-size:11px")
        html.A(
            "download {{ tf_file }} (the edited colours, for --tf)",
            v_show=("custom_colors",),
            href=("'data:application/json;charset=utf-8,' + encodeURIComponent(tf_json)",),
            download=("tf_file",),
            id="tf_download",
        )


def make_app(viewer: Viewer, *, name: str = "warpgauss", title: str | None = None):
    """The trame server of a viewer's page (not started)."""
    require_trame()
    from trame.app import get_server
    from trame.ui.vuetify3 import SinglePageLayout
    from trame.widgets import html, rca

    server = get_server(name, client_type="vue3")
    state, ctrl = server.state, server.controller
    ctrl.on_server_bind.add(_bind_routes)
    s = viewer.state
    facts = viewer.facts()
    state.update(
        {
            "trame__title": title or "warpgauss",  # the browser tab's title (trame's default: "Trame")
            "method": s.method,
            "colormap": s.colormap,
            "colors": viewer.color_nodes(),
            "opacities": s.opacity,
            "shading": s.shading,
            "density_log": 0.0,
            "time": s.time,
            "steps": len(viewer.models),
            "compare": s.compare,
            "has_volume": viewer.volumes is not None,
            "frame_ms": 0.0,
            "facts": _facts_text(facts),
            "command": viewer.render_command(),
            "tf_json": viewer.tf_json(),
            "custom_colors": False,
            "tf_file": TF_FILE,
            "hist": viewer.histogram(),
        }
    )
    handler = None

    def on_frame(seconds: float) -> None:
        with state:
            state.frame_ms = round(1000.0 * seconds, 1)
            state.command = viewer.render_command()
            state.tf_json = viewer.tf_json()
            state.custom_colors = viewer.state.colors is not None
            state.facts = _facts_text(viewer.facts())

    area = Area(viewer, on_frame, lambda: handler.update() if handler is not None else None)

    class _Forward:  # mouse events re-render at once; the rest of the protocol goes to the area
        img_cols_rows = property(lambda self: area.img_cols_rows)

        def process_resize_event(self, w, h):
            area.process_resize_event(w, h)
            if handler is not None:
                handler.update()

        def process_interaction_event(self, event):
            if area.process_interaction_event(event) and handler is not None:
                handler.update()

    @state.change("method", "colormap", "shading", "density_log", "time", "compare")
    def _settings(method, colormap, shading, density_log, time, compare, **_):
        viewer.state.method = method
        if colormap != viewer.state.colormap:
            viewer.set_colormap(colormap)
            state.colors = viewer.color_nodes()
        viewer.state.shading = bool(shading)
        viewer.state.density_scale = float(10.0 ** float(density_log))
        if int(time) != viewer.state.time:
            viewer.state.time = int(time)
            state.hist = viewer.histogram()
        viewer.state.compare = bool(compare) and viewer.volumes is not None
        if handler is not None:
            handler.update()

    @state.change("opacities", "colors")
    def _tf(opacities, colors, **_):
        viewer.set_opacity(opacities)
        if colors != viewer.color_nodes():
            viewer.set_colors(colors)
        if handler is not None:
            handler.update()

    with SinglePageLayout(server) as layout:
        layout.title.set_text(title or "warpgauss")
        with layout.content:
            with html.Div(style="display:flex;gap:16px;padding:24px 8px 8px 8px;height:calc(100vh - 80px)"):
                with html.Div(id="view", style="flex:1;min-width:256px;position:relative;"):
                    view = rca.RemoteControlledArea(name="view", display="image", send_mouse_move=True, style="width:100%;height:100%;")
                    with html.Div(  # the two halves of "compare with volume", named over each
                        v_show=("compare && has_volume",),
                        id="compare_labels",
                        style="position:absolute;top:4px;left:0;right:0;display:flex;pointer-events:none;"
                        "font-size:13px;color:#fff;text-shadow:0 0 3px #000",
                    ):
                        html.Div("model (Gaussians)", style="flex:1;text-align:center")
                        html.Div("source volume", style="flex:1;text-align:center")
                _controls(viewer)
    handler = _view_handler(view, _Forward())
    ctrl.view_update = handler.update
    return server


class FrameEncoder:
    """How frames travel to the page: JPEG (quality 90) while the view moves, then, once it has
    been still for a few frame periods, the same frame again as lossless PNG (fast zlib level 1).

    trame-rca encodes a frame at its "interactive" quality and again at its "still" quality when
    nothing changed meanwhile; with one format for both, a lossless PNG of a 1024^2 frame at PIL's
    default compression took 220-250 ms on the H100 machine's CPU (JPEG 90: 4-6 ms), five to eight
    times our render, so the page could not follow a drag at 30 frames a second."""

    STILL = 100  # the still quality: PNG; anything below is a JPEG quality

    def encode(self, np_image, cols: int, rows: int, quality: int) -> tuple[bytes, dict, int]:
        import io

        from PIL import Image

        now_ms = time.time_ns() // 1_000_000
        fmt = "png" if quality >= self.STILL else "jpeg"
        buf = io.BytesIO()
        Image.fromarray(np_image).save(buf, fmt, **({"compress_level": 1} if fmt == "png" else {"quality": int(quality)}))
        meta = {"type": f"image/{fmt}", "codec": "", "w": cols, "h": rows, "st": now_ms, "key": "key", "quality": quality}
        return buf.getvalue(), meta, now_ms


def _view_handler(view, window):
    """trame-rca's view handler for our frame source, with :class:`FrameEncoder` (as
    ``create_view_handler`` builds it, which takes only one of trame-rca's own encoders)."""
    from trame_rca.rca import window_wrapper
    from trame_rca.schedulers import RcaImageRenderScheduler
    from trame_rca.view_adapter import RcaViewAdapter

    window = window_wrapper(window)
    scheduler = RcaImageRenderScheduler(window, target_fps=60.0, interactive_quality=90, still_quality=FrameEncoder.STILL)
    scheduler._rca_encoder = FrameEncoder()  # its encoder is an enum of trame-rca's formats (trame-rca 2.11, pinned)
    handler = RcaViewAdapter(window, view.name, scheduler=scheduler)
    view.add_view_handler(handler)
    return handler


def _bind_routes(wslink_server) -> None:
    """Our routes beside wslink's, and one-line logs. trame's page first asks a session launcher
    (``POST <page>/paraview/``) where to connect and falls back to ``<page>/ws`` when that fails,
    which left a 405 in the browser's console: the route answers with that same address. A request
    the server cannot handle (``GET /ws`` without an upgrade, a URL over aiohttp's 8 KiB line
    limit) logged a traceback: it logs one line."""
    import logging

    from aiohttp import web

    async def launcher(request):
        base = request.path[: -len("paraview/")] if request.path.endswith("paraview/") else "/"
        secure = request.headers.get("X-Forwarded-Proto", request.scheme) == "https"
        return web.json_response({"sessionURL": f"{'wss' if secure else 'ws'}://USE_HOST{base}ws"})

    wslink_server.app.router.add_post("/paraview/", launcher)
    log = logging.getLogger("aiohttp.server")
    if not any(isinstance(f, _OneLine) for f in log.filters):
        log.addFilter(_OneLine())


class _OneLine:
    """A logging filter: a record with an exception becomes one line naming it, no traceback."""

    def filter(self, record) -> bool:
        if record.exc_info and record.exc_info[1] is not None:
            e = record.exc_info[1]
            while e.__context__ is not None:  # the first failure, not what failed while handling it
                e = e.__context__
            text = " ".join(str(e).split())
            text = text[:120] + "..." if len(text) > 120 else text
            record.msg = f"warpgauss serve: {record.getMessage()}, not handled: {type(e).__name__} {text}".rstrip()
            record.args, record.exc_info, record.exc_text = (), None, None
        return True


def _facts_text(f: dict) -> str:
    size = "-" if f["bytes"] is None else f"{f['bytes']:,} bytes"
    ratio = "-" if f["ratio"] is None else f"{f['ratio']:.1f}:1"
    psnr = "-" if f["psnr_db"] is None else f"{f['psnr_db']:.2f} dB"
    steps = f"\ntimesteps {f['steps']}" if f["steps"] > 1 else ""
    return f"N {f['n']:,} Gaussians on {f['grid']}\nfile {size}, CR {ratio}\nPSNR {psnr}{steps}"


def serve(viewer: Viewer, *, host: str = "127.0.0.1", port: int = 8080, title: str | None = None, on_ready=None) -> None:
    """Serve a viewer's page until interrupted (``port`` 0: any free port; the URL is printed)."""
    server = make_app(viewer, title=title)
    t0 = time.perf_counter()

    @server.controller.add("on_server_ready")
    def _ready(**_):
        url = f"http://{host}:{server.port}/"
        print(f"{READY_PREFIX}{url} (ready in {time.perf_counter() - t0:.1f} s; Ctrl-C stops)", flush=True)
        if on_ready is not None:
            on_ready(url)

    server.start(host=host, port=port, open_browser=False, show_connection_info=False, disable_logging=True)
