"""`warpgauss info`: what a model file holds."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from .common import handle_errors, human_bytes, out_console, print_json


@handle_errors
def info(
    model: Annotated[Path, typer.Argument(help="Model file (.wgs)")],
    as_json: Annotated[bool, typer.Option("--json", help="Print a JSON object")] = False,
    verify: Annotated[bool, typer.Option("--verify", help="Also read the payload and check its checksum and codes")] = False,
) -> None:
    """Print N, bytes, compression ratio and the header of a model file. The header is validated
    and the payload is not read (a file of any size answers at once); --verify reads it too."""
    from warpgauss.model import Model

    h = Model.load(model).header if verify else Model.load_header(model)
    n = int(h["n"])
    size = model.stat().st_size
    payload = h.get("payload", {})
    summary = {
        "file": str(model),
        "n": n,
        "bytes": size,
        "header_bytes": size
        - (payload["payload_bytes"] if payload.get("bytes_per_primitive") is None else n * int(payload["bytes_per_primitive"])),
        "bytes_per_primitive": (payload["payload_bytes"] / n)
        if payload.get("bytes_per_primitive") is None
        else payload["bytes_per_primitive"],
        "format": payload.get("encoding"),
        "compression_ratio": int(h["source"]["bytes"]) / size,
        "source_bytes": int(h["source"]["bytes"]),
        "header": h,
    }
    if as_json:
        print_json(summary)
        return
    g, v, src = h["grid"], h["values"], h["source"]
    lines = [
        f"[bold]{model}[/]: {n} Gaussians, {payload.get('encoding')} payload ({summary['bytes_per_primitive']:.2f} B/Gaussian), {size} bytes ({human_bytes(size)})",
        f"compression ratio {summary['compression_ratio']:.2f}x against {src['bytes']} source bytes "
        f"({src['dtype']}, {src['itemsize']} B/voxel)",
        f"grid {'x'.join(map(str, g['shape_xyz']))} (x,y,z), spacing {g['spacing']}, origin {g['origin']}",
        f"values [{v['min']:g}, {v['max']:g}], name {h.get('name')!r}, seed {h.get('seed')}",
        f"encoding {h.get('encoding')}",
        f"transfer function {h.get('transfer_function', {}).get('colormap')}",
    ]
    for line in lines:
        out_console.print(line, soft_wrap=True)
