"""`warpgauss render`: a model (exact ray marching, ray marching of its decoded grid, or EWA splatting)
or a dense volume (the reference) to PNG."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from warpgauss.errors import WarpgaussError

from .common import err_console, handle_errors, out_console, parse_shape, print_json

_NAMED_COLOURS = {
    "black": (0.0, 0.0, 0.0),
    "white": (1.0, 1.0, 1.0),
    "gray": (0.5, 0.5, 0.5),
    "grey": (0.5, 0.5, 0.5),
    "paraview": (0.32, 0.34, 0.43),
}


def parse_colour(text: str, what: str = "--background") -> tuple[float, float, float]:
    """black, white, gray, paraview, #rrggbb, or r,g,b in [0, 1]."""
    s = text.strip().lower()
    if s in _NAMED_COLOURS:
        return _NAMED_COLOURS[s]
    if s.startswith("#") and len(s) == 7:
        try:
            return tuple(int(s[k : k + 2], 16) / 255.0 for k in (1, 3, 5))  # type: ignore[return-value]
        except ValueError:
            pass
    parts = s.split(",")
    if len(parts) == 3:
        try:
            rgb = tuple(float(p) for p in parts)
        except ValueError:
            rgb = ()
        if len(rgb) == 3 and all(0.0 <= c <= 1.0 for c in rgb):
            return rgb  # type: ignore[return-value]
    raise WarpgaussError(f"{what} must be black, white, gray, paraview, #rrggbb or r,g,b in [0, 1], got {text!r}")


def parse_vector(text: str | None, what: str) -> tuple[float, float, float] | None:
    """'x,y,z' -> three floats."""
    if text is None:
        return None
    parts = text.replace(" ", "").split(",")
    try:
        v = tuple(float(p) for p in parts)
    except ValueError:
        v = ()
    if len(v) != 3:
        raise WarpgaussError(f"{what} must be three numbers x,y,z, got {text!r}")
    return v  # type: ignore[return-value]


def parse_size(text: str) -> tuple[int, int]:
    """'512' or '640x480' -> (width, height)."""
    parts = text.lower().split("x")
    try:
        wh = tuple(int(p) for p in parts)
    except ValueError:
        wh = ()
    if len(wh) == 1:
        wh = (wh[0], wh[0])
    if len(wh) != 2 or min(wh) < 1 or max(wh) > 16384:
        raise WarpgaussError(f"--size must be N or WxH with 1..16384 pixels a side, got {text!r}")
    return wh  # type: ignore[return-value]


def is_model_file(path: Path) -> bool:
    """A .wgs file, or any file that starts with the model magic."""
    from warpgauss.format.wgs import MAGIC

    if path.suffix.lower() == ".wgs":
        return True
    try:
        with open(path, "rb") as f:
            return f.read(len(MAGIC)) == MAGIC
    except OSError:
        return False


def check_png(path: Path) -> None:
    if path.suffix.lower() != ".png":
        raise WarpgaussError(f"{path}: the image is written as PNG; give a .png file name")


@handle_errors
def render(
    input: Annotated[Path, typer.Argument(help="Model (.wgs) or volume file (the reference rendering)")],
    output: Annotated[Path, typer.Option("-o", "--output", help="Image file (.png)")],
    method: Annotated[
        str | None,
        typer.Option(
            help="cached (ray marching of V~ decoded once onto a grid: fast; the default for a model, as in serve and view), "
            "march (exact ray marching of V~: slow) or splat (EWA splatting); a volume is always ray-marched"
        ),
    ] = None,
    cache_res: Annotated[
        int | None,
        typer.Option(
            "--cache-res", help="--method cached: voxels along the cache grid's longest axis, aspect kept (default: the model's grid)"
        ),
    ] = None,
    compare: Annotated[
        Path | None, typer.Option(help="Volume the model encodes: write model | reference | |difference| and print image PSNR and SSIM")
    ] = None,
    size: Annotated[str, typer.Option(help="Image size N or WxH in pixels")] = "512",
    colormap: Annotated[
        str | None,
        typer.Option(
            help="viridis, magma, inferno, plasma, cividis, turbo, coolwarm, jet, grayscale (NAME_r reverses); default: the model's"
        ),
    ] = None,
    opacity: Annotated[
        str | None,
        typer.Option(help="Opacity curve value:opacity,... over normalised values, e.g. 0:0,0.3:0,1:1 (or linear, flat, a number)"),
    ] = None,
    tf: Annotated[Path | None, typer.Option("--tf", help="Transfer function .json (ours or a ParaView colormap/opacity export)")] = None,
    density: Annotated[float | None, typer.Option(help="Extinction per voxel at opacity 1 (default 10 / the largest grid extent)")] = None,
    step: Annotated[float, typer.Option(help="Ray-marching step in voxels")] = 0.5,
    ert: Annotated[float, typer.Option(help="Early ray termination once transmittance < this (0: off)")] = 1e-3,
    shading: Annotated[bool, typer.Option("--shading/--no-shading", help="Blinn-Phong from the analytic gradient (headlight)")] = True,
    skip: Annotated[bool, typer.Option("--skip/--no-skip", help="Empty-space skipping (exact; for timing studies)")] = True,
    azimuth: Annotated[float, typer.Option(help="Degrees around the up axis (0 on +x, 90 on +y)")] = -55.0,
    elevation: Annotated[float, typer.Option(help="Degrees above the plane normal to up")] = 25.0,
    distance: Annotated[float | None, typer.Option(help="Voxels from the look-at point (default: fit the grid)")] = None,
    zoom: Annotated[float, typer.Option(help="Magnification (> 1 comes closer)")] = 1.0,
    fov: Annotated[float, typer.Option(help="Vertical field of view in degrees")] = 30.0,
    ortho: Annotated[bool, typer.Option("--ortho", help="Orthographic projection")] = False,
    position: Annotated[str | None, typer.Option(help="Camera position x,y,z in physical units (origin + index x spacing)")] = None,
    look_at: Annotated[str | None, typer.Option("--look-at", help="Point looked at x,y,z in physical units (default: grid centre)")] = None,
    up: Annotated[str, typer.Option(help="Up direction x,y,z")] = "0,0,1",
    background: Annotated[str, typer.Option(help="black, white, gray, paraview, #rrggbb or r,g,b")] = "black",
    diff_gain: Annotated[float, typer.Option(help="--compare: the difference panel shows |model - reference| times this")] = 4.0,
    device: Annotated[str | None, typer.Option(help="Warp device: cpu, cuda, cuda:N")] = None,
    stride: Annotated[int, typer.Option(help="Volumes: take every K-th voxel")] = 1,
    shape: Annotated[str | None, typer.Option(help="Raw volumes: XxYxZ when the name does not say")] = None,
    dtype: Annotated[str | None, typer.Option(help="Raw volumes: uint8, int16, float32, ...")] = None,
    dataset: Annotated[str | None, typer.Option(help="HDF5 volumes: dataset path")] = None,
    variable: Annotated[str | None, typer.Option(help="netCDF volumes: variable name")] = None,
    fill_value: Annotated[float | None, typer.Option(help="Volumes: value marking missing data")] = None,
    residual: Annotated[
        bool,
        typer.Option("--residual", help="Models with a bounded residual: ray-march the bounded decode (Gaussians + residual) as a grid"),
    ] = False,
    as_json: Annotated[bool, typer.Option("--json", help="Print the figures as JSON")] = False,
    force: Annotated[bool, typer.Option("--force", help="Overwrite an existing image")] = False,
) -> None:
    """Render a model or a volume with a transfer function, camera and lighting; compare a model with its volume."""
    from warpgauss.core.files import check_writable
    from warpgauss.readers import ReadOptions
    from warpgauss.render.renderers import Camera, RenderSettings

    check_png(output)
    check_writable(output, force=force)
    _check_method(input, method, cache_res)
    width, height = parse_size(size)
    camera = Camera(
        azimuth=azimuth,
        elevation=elevation,
        distance=distance,
        zoom=zoom,
        fov=fov,
        ortho=ortho,
        position=parse_vector(position, "--position"),
        look_at=parse_vector(look_at, "--look-at"),
        up=parse_vector(up, "--up"),  # type: ignore[arg-type]
    )
    camera.validate()
    settings = RenderSettings(
        width=width,
        height=height,
        step=step,
        density=density,
        ert=ert,
        background=parse_colour(background),
        shading=shading,
        skip=skip,
    )
    settings.validate()
    if diff_gain <= 0:
        raise WarpgaussError(f"--diff-gain must be positive, got {diff_gain}")
    read = ReadOptions(parse_shape(shape), dtype, None, dataset, variable, stride, fill_value)
    if tf is not None and not tf.is_file():
        raise WarpgaussError(f"no such transfer-function file: {tf}")

    if residual and method not in (None, "march"):
        raise WarpgaussError(f"--residual ray-marches the bounded decode as a grid; drop --method {method}")
    if is_model_file(input):
        method = method or ("march" if residual else "cached")
        summary = _render_model(
            input, output, method, compare, camera, settings, colormap, opacity, tf, read, diff_gain, device, force, cache_res, residual
        )
    else:
        if residual:
            raise WarpgaussError("--residual applies to a model (.wgs) encoded with --max-error")
        if compare is not None:
            raise WarpgaussError("--compare takes the volume a model encodes; render the model (.wgs) with --compare VOLUME")
        if method not in (None, "march"):
            raise WarpgaussError(f"a volume is rendered by ray marching only (--method {method} needs a model)")
        if cache_res is not None:
            raise WarpgaussError("--cache-res applies to a model (.wgs): a volume is ray-marched as it is")
        summary = _render_volume(input, output, camera, settings, colormap, opacity, tf, read, device, force)
    if as_json:
        print_json(summary)
        return
    _print_render(output, summary, diff_gain)


def _check_method(input: Path, method: str | None, cache_res: int | None) -> None:
    """Refuse a missing input, an unknown --method and a --cache-res it does not take."""
    if not input.exists():
        raise WarpgaussError(f"no such file: {input}")
    if method is not None and method not in ("march", "cached", "splat"):
        raise WarpgaussError(f"--method must be march, cached or splat, got {method!r}")
    if cache_res is not None and method not in (None, "cached"):
        raise WarpgaussError(f"--cache-res applies to --method cached, not {method}")
    if cache_res is not None and cache_res < 1:
        raise WarpgaussError(f"--cache-res must be a positive number of voxels along the longest axis, got {cache_res}")


def _print_render(output: Path, summary: dict, diff_gain: float) -> None:
    """What ``render`` wrote, for people: the image, its renderer and time; a comparison's scores."""
    cache = ""
    if "cache_seconds" in summary:
        cache = f"; cache {'x'.join(map(str, summary['cache_shape']))} built once in {summary['cache_seconds']:.3f} s"
    out_console.print(
        f"wrote {output} ({summary['width']}x{summary['height']}, {summary['method']}, "
        f"{summary['seconds']:.3f} s per frame on {summary['device']}{cache})",
        soft_wrap=True,
    )
    if "image_psnr_db" in summary:
        out_console.print(
            f"model vs reference: image PSNR {summary['image_psnr_db']:.2f} dB, SSIM {summary['image_ssim']:.4f} "
            f"(panels: model | reference | |difference| x {diff_gain:g})",
            soft_wrap=True,
        )


def _transfer(header, colormap, opacity, tf_path, value_range):
    from warpgauss.render.transfer import resolve_transfer_function

    return resolve_transfer_function(header, path=tf_path, colormap_name=colormap, opacity=opacity, value_range=value_range)


def read_normalised(path: Path, read, value_range=None):
    from warpgauss.field.analysis import normalise

    vol = read.read(path)
    fill = read.fill_value if read.fill_value is not None else vol.fill_value
    f = normalise(vol.data, fill_value=fill, spacing=vol.spacing, origin=vol.origin, value_range=value_range, count_candidates=False)
    return vol, f


def _render_model(
    path, output, method, compare, camera, settings, colormap, opacity, tf_path, read, gain, device, force, cache_res=None, residual=False
) -> dict:
    from warpgauss.core.warp import resolve_device
    from warpgauss.format.model import Model
    from warpgauss.render.renderers import (
        Scene,
        VolumeRenderer,
        cache_grid_shape,
        check_cache_memory,
        image_psnr,
        image_ssim,
        make_renderer,
        resolve_view,
        save_png,
        side_by_side,
    )

    model = Model.load(path)
    if residual and model.residual is None:
        raise WarpgaussError(f"{path} has no residual (encode with --max-error for one); render without --residual")
    if compare is not None and not compare.exists():
        raise WarpgaussError(f"no such file: {compare}")
    if method == "cached":  # refuse a cache that cannot be held before anything is built
        check_cache_memory(cache_grid_shape(model.shape_xyz, cache_res), resolve_device(device))
    tf = _transfer(model.header, colormap, opacity, tf_path, model.value_range)
    with err_console.status(f"preparing {model.n} Gaussians for {method} rendering", spinner="dots") as status:
        method = "bounded" if residual else method  # the bounded decode, normalised by the header's range, as a grid
        renderer = make_renderer(model, method, device, cache_res=cache_res)
        view = resolve_view(camera, renderer.scene, settings.width, settings.height)
        status.update(f"rendering {settings.width}x{settings.height} ({method}, {model.n} Gaussians)")
        img = renderer.render(view, tf, settings)
        summary = {
            "input": str(path),
            "output": str(output),
            "method": method,
            "n": model.n,
            "width": settings.width,
            "height": settings.height,
            "seconds": img.seconds,
            "device": renderer.device,
            "transfer_function": tf.describe(),
            **img.stats,
        }
        if compare is None:
            save_png(output, img.rgb8(), force=force)
            return summary
        _, f = read_normalised(compare, read, model.value_range)
        ref = VolumeRenderer(f.values, Scene.from_header(model.header), device=renderer.device).render(view, tf, settings)
    summary.update(
        compare=str(compare),
        reference_seconds=ref.seconds,
        image_psnr_db=image_psnr(img.rgb, ref.rgb),
        image_ssim=image_ssim(img.rgb, ref.rgb),
        diff_gain=gain,
    )
    save_png(output, side_by_side(img.rgb, ref.rgb, gain), force=force)
    return summary


def _render_volume(path, output, camera, settings, colormap, opacity, tf_path, read, device, force) -> dict:
    from warpgauss.render.renderers import Scene, VolumeRenderer, save_png

    vol, f = read_normalised(path, read)
    tf = _transfer(None, colormap, opacity, tf_path, (f.vmin, f.vmax))
    nz, ny, nx = f.values.shape
    with err_console.status("rendering the volume", spinner="dots"):
        r = VolumeRenderer(f.values, Scene((nx, ny, nz), vol.spacing, vol.origin), device=device)
        img = r.render(camera, tf, settings)
    save_png(output, img.rgb8(), force=force)
    return {
        "input": str(path),
        "output": str(output),
        "method": "reference",
        "width": settings.width,
        "height": settings.height,
        "seconds": img.seconds,
        "device": r.device,
        "transfer_function": tf.describe(),
        **img.stats,
    }
