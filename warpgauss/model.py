"""The encoded model: N primitives plus the self-describing header of the ``.wgs`` file.

``Model.params`` is an (N, 12) float32 array, one row per primitive:
``mu_x, mu_y, mu_z, log_sx, log_sy, log_sz, q_x, q_y, q_z, q_w, a, w`` (centre in voxel units
of the model grid, log-sigmas, unit quaternion in Warp's order, value in normalised units,
weight in (0, 1]). The header keeps the grid, the value range for decoding to original units,
the source's dtype and size (for the compression ratio), the encoding configuration and seed,
and a default transfer function.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from . import __version__
from .errors import WarpgaussError

# viridis at nine evenly spaced stops (RGB 0..255); the default colormap of the header's LUT
_VIRIDIS = np.array(
    [
        (68, 1, 84),
        (71, 44, 122),
        (59, 82, 139),
        (44, 113, 142),
        (33, 145, 140),
        (39, 173, 129),
        (92, 200, 99),
        (170, 220, 50),
        (253, 231, 37),
    ],
    np.float64,
)


def default_transfer_function(entries: int = 256) -> dict:
    """Viridis colour with a linear opacity ramp, as a 256-entry RGBA8 LUT (hex) over [0, 1]."""
    x = np.linspace(0.0, 1.0, entries)
    stops = np.linspace(0.0, 1.0, len(_VIRIDIS))
    rgb = np.stack([np.interp(x, stops, _VIRIDIS[:, c]) for c in range(3)], axis=1)
    alpha = 255.0 * x
    lut = np.concatenate([rgb, alpha[:, None]], axis=1).round().astype(np.uint8)
    return {"colormap": "viridis", "opacity": [[0.0, 0.0], [1.0, 1.0]], "lut_rgba8": lut.tobytes().hex()}


def make_header(
    *,
    shape_xyz,
    spacing,
    origin,
    vmin: float,
    vmax: float,
    source_dtype: str,
    source_itemsize: int,
    name: str,
    encoding: dict,
    seed: int,
) -> dict:
    """The header fields of SPEC section 6 that the caller owns (the format adds n and payload)."""
    nx, ny, nz = (int(s) for s in shape_xyz)
    return {
        "format": "warpgauss",
        "warpgauss_version": __version__,
        "name": name,
        "grid": {
            "shape_xyz": [nx, ny, nz],
            "spacing": [float(s) for s in spacing],
            "origin": [float(o) for o in origin],
        },
        "values": {"min": float(vmin), "max": float(vmax)},
        "source": {
            "dtype": source_dtype,
            "itemsize": int(source_itemsize),
            "bytes": int(nx * ny * nz * int(source_itemsize)),
        },
        "encoding": dict(encoding),
        "seed": int(seed),
        "transfer_function": default_transfer_function(),
    }


class Model:
    """A fixed-budget Gaussian model of a scalar volume.

    Args:
        params: (N, 12) float32 primitive parameters.
        header: Header dict (see :func:`make_header`).
    """

    def __init__(self, params: np.ndarray, header: dict):
        params = np.ascontiguousarray(params, dtype=np.float32)
        if params.ndim != 2 or params.shape[1] != 12 or params.shape[0] < 1:
            raise WarpgaussError(f"a model needs an (N, 12) parameter array with N >= 1, got shape {params.shape}")
        self.params = params
        self.header = header
        self.report: dict | None = None  # filled by warpgauss.encode

    # -- description -----------------------------------------------------------------------
    @property
    def n(self) -> int:
        return int(self.params.shape[0])

    @property
    def shape_xyz(self) -> tuple[int, int, int]:
        return tuple(int(s) for s in self.header["grid"]["shape_xyz"])

    @property
    def value_range(self) -> tuple[float, float]:
        v = self.header["values"]
        return float(v["min"]), float(v["max"])

    @property
    def source_bytes(self) -> int:
        return int(self.header["source"]["bytes"])

    def file_size(self, compact: bool = False) -> int:
        """Exact bytes of this model's file: 48 N + H (full precision) or 12 N + H (compact)."""
        from .wgs import header_size

        bpp = 12 if compact else 48
        return bpp * self.n + header_size(self.header, self.n, compact=compact)

    def compression_ratio(self, compact: bool = False) -> float:
        return self.source_bytes / self.file_size(compact)

    # -- file I/O --------------------------------------------------------------------------
    def save(self, path: str | os.PathLike, *, compact: bool = False, force: bool = False) -> int:
        """Write the model atomically; returns the file size in bytes."""
        from .wgs import write_wgs

        return write_wgs(path, self.params, self.header, compact=compact, force=force)

    @classmethod
    def load(cls, path: str | os.PathLike) -> Model:
        """Read and validate a ``.wgs`` file (magic, version, sizes, checksums)."""
        from .wgs import read_wgs

        p = Path(path)
        if not p.is_file():
            raise WarpgaussError(f"no such model file: {p}")
        params, header = read_wgs(p)
        for key in ("grid", "values", "source"):
            if key not in header:
                raise WarpgaussError(f"{p}: the header lacks '{key}'; the file was not written by warpgauss")
        return cls(params, header)

    # -- evaluation ------------------------------------------------------------------------
    def field(self, device: str | None = None):
        """The model resident on a Warp device, ready for evaluation (:class:`GaussianField`)."""
        from .field import GaussianField

        return GaussianField(self.params, self.shape_xyz, device=device)

    def decode(
        self,
        shape: tuple[int, int, int] | None = None,
        *,
        device: str | None = None,
        normalised: bool = False,
        progress=None,
    ) -> np.ndarray:
        """Evaluate the model on a grid spanning the model's extent.

        Args:
            shape: Output grid (x, y, z); None for the encoded grid.
            device: Warp device (None: CUDA when present, else CPU).
            normalised: Return [0, 1] values instead of the source's units.
            progress: Optional callback(done, total).

        Returns:
            (nz, ny, nx) float32 array (float64 where float32 cannot hold the value range, see
            :func:`warpgauss.analysis.denormalise`).
        """
        from .analysis import denormalise

        v = self.field(device).decode(shape, progress=progress)
        if normalised:
            return v
        lo, hi = self.value_range
        return denormalise(v, lo, hi)

    def decoded_spacing(self, shape: tuple[int, int, int] | None = None) -> tuple[float, float, float]:
        """Physical voxel spacing of a decode at ``shape`` (same extent as the encoded grid)."""
        sp = self.header["grid"]["spacing"]
        if shape is None:
            return tuple(float(s) for s in sp)
        return tuple(float(sp[a]) * self.shape_xyz[a] / int(shape[a]) for a in range(3))

    def decoded_origin(self, shape: tuple[int, int, int] | None = None) -> tuple[float, float, float]:
        """Physical position of the first voxel centre of a decode at ``shape``."""
        sp = self.header["grid"]["spacing"]
        org = self.header["grid"]["origin"]
        if shape is None:
            return tuple(float(o) for o in org)
        return tuple(
            float(org[a]) + float(sp[a]) * (0.5 * self.shape_xyz[a] / int(shape[a]) - 0.5) for a in range(3)
        )
