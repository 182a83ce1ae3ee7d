"""warpgauss: fixed-budget anisotropic Gaussian encoding of scientific scalar volumes.

The package imports Warp lazily: reading, validating and refusing a request costs no Warp start-up.
"""

__version__ = "0.1.0"

from .errors import WarpgaussError  # noqa: E402

__all__ = ["WarpgaussError", "__version__"]
