"""`warpgauss info`: what a model file holds."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from .common import handle_errors, out_console, print_json, size_text


@handle_errors
def info(
    model: Annotated[Path, typer.Argument(help="Model file (.wgs)")],
    as_json: Annotated[bool, typer.Option("--json", help="Print a JSON object")] = False,
    verify: Annotated[bool, typer.Option("--verify", help="Also read the payload and check its checksum and codes")] = False,
    verbose: Annotated[bool, typer.Option("--verbose", "-v", help="Also list every encoding setting the header records")] = False,
) -> None:
    """Print N, bytes, compression ratio and the header of a model file. The header is validated
    and the payload is not read (a file of any size answers at once); --verify reads it too."""
    from rich.table import Table

    from warpgauss.format.model import Model

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
    rows = [
        ("file", f"{model}: {size_text(size)}"),
        ("Gaussians", f"{n}, {payload.get('encoding')} payload, {summary['bytes_per_primitive']:.2f} B a Gaussian"),
        (
            "compression",
            f"{summary['compression_ratio']:.2f}x (the file's) against {size_text(int(src['bytes']))} of source ({src['dtype']}, {src['itemsize']} B a voxel)",
        ),
        ("grid", f"{' x '.join(map(str, g['shape_xyz']))} (x, y, z), spacing {_numbers(g['spacing'])}, origin {_numbers(g['origin'])}"),
        ("values", f"{v['min']:g} .. {v['max']:g}"),
        ("name", str(h.get("name"))),
        ("seed", str(h.get("seed"))),
        ("colour map", str(h.get("transfer_function", {}).get("colormap"))),
    ]
    if res:
        rows.insert(
            2,
            (
                "bounded residual",
                f"{res_bytes:,} B beside the Gaussians' {size - res_bytes:,} B (header included): every voxel within "
                f"{res['bound']:.6g} source units of the source ({res['bound_rel']:.3g} of its range), {res['predictor']} predictor, "
                f"{res['literals']} voxels stored exactly",
            ),
        )
    enc = h.get("encoding") or {}
    if enc:
        rows.append(("method", str(enc.get("method"))))
        rows.append(("refinement", f"{enc.get('iterations')} iterations x {enc.get('samples')} samples, stride {enc.get('stride')}"))
    if verbose:
        rows += [(f"encoding.{k}", str(val)) for k, val in _flat(enc) if k not in ("method",)]
    t = Table.grid(padding=(0, 2))
    t.add_column(style="bold")
    t.add_column()
    for label, value in rows:
        t.add_row(label, value)
    out_console.print(t)
    if not verbose and enc:
        out_console.print("every encoding setting: warpgauss info --verbose")


def _numbers(xs) -> str:
    return ", ".join(f"{float(x):g}" for x in xs)


def _flat(d: dict, prefix: str = ""):
    """(dotted key, value) for every leaf of a nested settings dict, in key order."""
    for k in sorted(d):
        v = d[k]
        if isinstance(v, dict):
            yield from _flat(v, f"{prefix}{k}.")
        else:
            yield f"{prefix}{k}", v
