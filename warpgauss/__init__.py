"""warpgauss: fixed-budget anisotropic Gaussian encoding of scientific scalar volumes.

The package imports Warp lazily: reading, validating and refusing a request costs no Warp start-up.
"""

from ._version import __version__
from .driver import encode, encode_ladder  # noqa: E402
from .encoder import Encoder  # noqa: E402
from .errors import WarpgaussError  # noqa: E402
from .model import Model  # noqa: E402
from .series import encode_series  # noqa: E402


def psnr(model: Model, volume, *, full: bool = False, device: str | None = None, fill_value: float | None = None) -> float:
    """PSNR (dB) of ``model`` against ``volume`` (a path or a 3D array), on the normalised field.

    The volume is normalised by its own finite min/max, as at encoding time. 500,000 sampled voxel
    centres with a fixed seed, or the full grid with ``full=True`` (SPEC section 7).
    """
    from .evaluate import evaluate_against

    return evaluate_against(model, volume, full=full, device=device, fill_value=fill_value)["psnr_db"]


__all__ = ["Encoder", "Model", "WarpgaussError", "__version__", "encode", "encode_ladder", "encode_series", "psnr"]
