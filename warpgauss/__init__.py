"""warpgauss: fixed-budget anisotropic Gaussian encoding of scientific scalar volumes.

The package imports Warp lazily: reading, validating and refusing a request costs no Warp start-up.
"""

from ._version import __version__
from .driver import encode, encode_ladder  # noqa: E402
from .encoder import Encoder  # noqa: E402
from .errors import WarpgaussError  # noqa: E402
from .model import Model  # noqa: E402
from .render import render_image  # noqa: E402
from .series import encode_series  # noqa: E402


def psnr(model, volume, *, full: bool = False, device: str | None = None, fill_value: float | None = None) -> float:
    """PSNR (dB) of ``model`` against ``volume`` (a path or a 3D array), on the normalised field.

    The volume is normalised by its own finite min/max, as at encoding time. 500,000 sampled voxel
    centres with a fixed seed, or the full grid with ``full=True`` (SPEC section 7). ``model`` may
    also be a decoded grid of the volume's shape (an array): then every finite voxel of the volume
    counts, both normalised by the volume's min/max.
    """
    import numpy as np

    from .evaluate import evaluate_against, psnr_from_mse

    if isinstance(model, Model):
        return evaluate_against(model, volume, full=full, device=device, fill_value=fill_value)["psnr_db"]
    if not isinstance(model, np.ndarray):
        raise WarpgaussError(
            f"psnr takes a Model (warpgauss.Model.load(path) or warpgauss.encode(...)) or a decoded array, got {type(model).__name__}"
        )
    truth = volume if isinstance(volume, np.ndarray) else None
    if truth is None:
        from .io import read_volume

        truth = read_volume(volume).data
    if model.shape != truth.shape:
        raise WarpgaussError(
            f"the grid's shape {model.shape} is not the volume's {truth.shape}; decode at the volume's shape to compare them"
        )
    t = np.asarray(truth, np.float64)
    valid = np.isfinite(t) if fill_value is None else np.isfinite(t) & (t != fill_value)
    if not valid.any():
        raise WarpgaussError("the volume has no finite voxel to compare against")
    lo, hi = float(t[valid].min()), float(t[valid].max())
    span = hi - lo if hi > lo else 1.0
    err = (np.asarray(model, np.float64)[valid] - t[valid]) / span
    return psnr_from_mse(float(np.mean(err * err)))


__all__ = ["Encoder", "Model", "WarpgaussError", "__version__", "encode", "encode_ladder", "encode_series", "psnr", "render_image"]
