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

    if verify:
        m = Model.load(model)
        if m.residual is not None:
            m.residual.payload()  # its checksum
        h = m.header
    else:
        h = Model.load_header(model)
    n = int(h["n"])
    size = model.stat().st_size
    payload = h.get("payload", {})
    res = h.get("residual")
    res_bytes = int(res["payload_bytes"]) if res else 0
    summary = {
        "file": str(model),
        "n": n,
        "bytes": size,
        "residual_bytes": res_bytes,
        "header_bytes": size
        - res_bytes
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
    if res:
        lines.insert(
            1,
            f"Gaussians {size - res_bytes} bytes ({human_bytes(size - res_bytes)}) + bounded residual {res_bytes} bytes "
            f"({human_bytes(res_bytes)}): every voxel within {res['bound']:.6g} of the source ({res['bound_rel']:.3g} of its range), "
            f"{res['predictor']} predictor, {res['literals']} voxels stored exactly",
        )
    for line in lines:
        out_console.print(line, soft_wrap=True)
