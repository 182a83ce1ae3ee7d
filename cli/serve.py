"""`warpgauss serve`: the model in a web page (trame), rendered on the server by our renderers."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from warpgauss.errors import WarpgaussError

from .common import handle_errors


@handle_errors
def serve(
    models: Annotated[
        list[str], typer.Argument(help="Model (.wgs), or several / a quoted glob such as 'rho_*.wgs' for a series (a time slider)")
    ],
    volume: Annotated[
        list[Path] | None,
        typer.Option("--volume", help="The source volume (one per model of a series): adds 'compare with volume' to the page"),
    ] = None,
    port: Annotated[int, typer.Option(help="TCP port (0: any free port; the URL is printed)")] = 8080,
    host: Annotated[
        str, typer.Option(help="Address to bind (127.0.0.1: this machine only; 0.0.0.0 exposes the page to the network)")
    ] = "127.0.0.1",
    method: Annotated[
        str,
        typer.Option(help="cached (default: decoded once, fast), march (exact), splat, or bounded (a model's decode with its residual)"),
    ] = "cached",
    cache_res: Annotated[
        int | None, typer.Option("--cache-res", help="--method cached: voxels along the cache grid's longest axis")
    ] = None,
    device: Annotated[str | None, typer.Option(help="Warp device: cpu, cuda, cuda:N")] = None,
    dataset: Annotated[str | None, typer.Option(help="HDF5 volumes: dataset path")] = None,
    variable: Annotated[str | None, typer.Option(help="netCDF volumes: variable name")] = None,
) -> None:
    """Serve a page that shows the model: orbit and zoom with the mouse, edit the colour and opacity
    curves, switch colormap, renderer, shading and density, step through a series, compare with the
    source volume."""
    from warpgauss.readers import ReadOptions
    from warpgauss.render.serve import require_trame
    from warpgauss.render.serve import serve as run
    from warpgauss.render.viewer import Viewer, load_models

    from .render import read_normalised

    require_trame()  # before any work: a missing extra is a one-line error
    if not 0 <= port <= 65535:
        raise WarpgaussError(f"--port must be 0-65535, got {port}")
    loaded, paths = load_models(models)
    vols = None
    if volume:
        if len(volume) not in (1, len(loaded)):
            raise WarpgaussError(f"{len(volume)} --volume for {len(loaded)} models: give one volume, or one per model")
        read = ReadOptions(dataset=dataset, variable=variable)
        vols = []
        for k, p in enumerate(volume if len(volume) == len(loaded) else volume * len(loaded)):
            if not Path(p).exists():
                raise WarpgaussError(f"no such file: {p}")
            _, f = read_normalised(Path(p), read, loaded[k].value_range)
            if tuple(f.shape_xyz) != tuple(loaded[k].shape_xyz):
                raise WarpgaussError(
                    f"--volume {p} is on a {'x'.join(map(str, f.shape_xyz))} grid, the model on {'x'.join(map(str, loaded[k].shape_xyz))}"
                )
            vols.append(f.values)
    viewer = Viewer(loaded, paths, vols, device=device, method=method, cache_res=cache_res)
    title = f"warpgauss - {Path(paths[0]).name}" + (f" (+{len(paths) - 1} timesteps)" if len(paths) > 1 else "")
    try:
        run(viewer, host=host, port=port, title=title)
    except KeyboardInterrupt:
        pass
