"""Warp kernels of warpgauss (every @wp.kernel and @wp.func lives in this package)."""
