"""`warpgauss eval`: PSNR of a model against a volume."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from .common import handle_errors, out_console, parse_shape, print_json


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
    """PSNR, occupied-only PSNR and max abs error on the normalised field (500,000 sampled voxel centres, or the full grid)."""
    from warpgauss.evaluate import evaluate_against
    from warpgauss.io import ReadOptions
    from warpgauss.model import Model

    m = Model.load(model)
    s = stride if stride is not None else int(m.header.get("encoding", {}).get("stride", 1))
    read = ReadOptions(parse_shape(shape), dtype, endian, dataset, variable, s, fill_value)
    r = evaluate_against(m, volume, full=full, device=device, read=read, residual=residual)
    r["bytes"] = model.stat().st_size
    r["compression_ratio"] = m.source_bytes / r["bytes"]
    if as_json:
        print_json(r)
        return
    occ = r["psnr_occupied_db"]
    out_console.print(
        f"PSNR {r['psnr_db']:.2f} dB, occupied {occ if occ is None else f'{occ:.2f}'} dB, "
        f"max abs error {r['max_abs_error']:.4g}, N {r['n']}, {r['bytes']} bytes, CR {r['compression_ratio']:.2f}x "
        f"({r['mode']})"
    )
    if "bound" in r:
        ok = "within" if r["max_abs_error_source"] <= r["bound"] else "BEYOND"
        out_console.print(f"max abs error {r['max_abs_error_source']:.6g} source units, {ok} the bound {r['bound']:.6g}")
