"""ParaView support: the ``.wgs`` reader plugin (see :mod:`warpgauss.paraview.warpgauss_reader`).

In ParaView: Tools > Manage Plugins > Load New, and pick the file :data:`PLUGIN` names::

    python -c "import warpgauss.paraview as p; print(p.PLUGIN)"

(the plugin file is named apart from this package: ParaView imports a plugin under its file's
name, and one called ``paraview`` would hide ParaView's own package).
"""

from pathlib import Path

from .warpgauss_reader import (
    PARAVIEW_PRESETS,
    ReaderError,
    WarpgaussReader,
    apply_default_transfer_function,
    decode_shape,
    file_transfer_function,
    read_header,
    transfer_function_points,
)

PLUGIN = str(Path(__file__).with_name("warpgauss_reader.py"))

__all__ = [
    "PARAVIEW_PRESETS",
    "PLUGIN",
    "ReaderError",
    "WarpgaussReader",
    "apply_default_transfer_function",
    "decode_shape",
    "file_transfer_function",
    "read_header",
    "transfer_function_points",
]
