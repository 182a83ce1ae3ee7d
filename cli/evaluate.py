"""`warpgauss eval`: PSNR of a model against a volume."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from .common import error_text, handle_errors, out_console, parse_shape, print_json, psnr_text, size_text


@handle_errors
def evaluate(
    model: Annotated[Path, typer.Argument(help="Model file (.wgs)")],
    volume: Annotated[Path, typer.Argument(help="The volume it encodes")],
    full: Annotated[bool, typer.Option("--full", help="Full grid instead of 500,000 sampled voxels")] = False,
    stride: Annotated[int | None, typer.Option(help="Stride (default: the model's)")] = None,
    shape: Annotated[str | None, typer.Option(help="Raw files: XxYxZ")] = None,
    dtype: Annotated[str | None, typer.Option(help="Raw files: dtype")] = None,
    endian: Annotated[str | None, typer.Option(help="Raw files: little or big")] = None,
    dataset: Annotated[str | None, typer.Option(help="HDF5 dataset path")] = None,
    variable: Annotated[str | None, typer.Option(help="netCDF variable")] = None,
    fill_value: Annotated[float | None, typer.Option(help="Source value marking missing data")] = None,
    device: Annotated[str | None, typer.Option(help="Warp device")] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print a JSON object")] = False,
    residual: Annotated[
        bool,
        typer.Option("--residual/--no-residual", help="Score the decode with the model's bounded residual, where it has one (full grid)"),
    ] = True,
) -> None:
    """PSNR, occupied-only PSNR and max abs error on the normalised field (500,000 sampled voxel centres, or the full grid).

    The max abs error is printed once, in source units and as a share of the value range (the JSON's
    ``max_abs_error_source`` and ``max_abs_error``); a model with a residual is scored as its encode
    was, against the source's own values; an exact decode reports PSNR 200 dB, the cap."""
    from warpgauss.field.evaluate import evaluate_against
    from warpgauss.format.model import Model
    from warpgauss.readers import ReadOptions

    m = Model.load(model)
    s = stride if stride is not None else int(m.header.get("encoding", {}).get("stride", 1))
    read = ReadOptions(parse_shape(shape), dtype, endian, dataset, variable, s, fill_value)
    r = evaluate_against(m, volume, full=full, device=device, read=read, residual=residual)
    r["bytes"] = model.stat().st_size
    r["compression_ratio"] = m.source_bytes / r["bytes"]
    if as_json:
        print_json(r)
        return
    out_console.print(f"{psnr_text(r['psnr_db'], r['psnr_occupied_db'])}; {r['mode']}")
    bound = ""
    if "bound" in r:
        ok = "within" if r["max_abs_error_source"] <= r["bound"] else "BEYOND"
        bound = f", {ok} the bound {r['bound']:.6g} source units"
    out_console.print(f"max abs error {error_text(r['max_abs_error'], r['max_abs_error_source'])}{bound}")
    out_console.print(
        f"{r['n']} Gaussians{' and a residual' if 'bound' in r else ''}: file {size_text(r['bytes'])}, compression {r['compression_ratio']:.2f}x"
    )
