"""`warpgauss export`: the primitives as a .vtp point cloud (ParaView) with scale, orientation, value and weight."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from .common import handle_errors, out_console


@handle_errors
def export(
    model: Annotated[Path, typer.Argument(help="Model file (.wgs)")],
    output: Annotated[Path, typer.Option("-o", "--output", help="Point cloud file (.vtp)")],
    voxel_units: Annotated[bool, typer.Option("--voxel-units", help="Model voxel coordinates instead of physical ones")] = False,
    force: Annotated[bool, typer.Option("--force", help="Overwrite an existing output file")] = False,
) -> None:
    """Write one point per Gaussian (centre) with scale (3), orientation (quaternion x,y,z,w), rotation (3x3), value and weight."""
    from warpgauss.core.files import check_writable
    from warpgauss.errors import WarpgaussError
    from warpgauss.format.export import write_vtp
    from warpgauss.format.model import Model

    if output.suffix.lower() != ".vtp":
        raise WarpgaussError(f"{output}: primitives are exported as VTK PolyData; give a .vtp file name")
    check_writable(output, force=force)
    m = Model.load(model)
    n = write_vtp(m, output, voxel_units=voxel_units, force=force)
    units = "voxel" if voxel_units else "physical"
    out_console.print(f"wrote {output} ({n} points, {units} units; arrays scale, orientation, rotation, value, value_normalised, weight)")
