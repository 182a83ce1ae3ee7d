"""Warp start-up and device choice, done once and quietly.

Importing Warp costs ~1.7 s, so modules that only read, validate or refuse input never import it;
everything that launches kernels calls :func:`warp` first.
"""

from __future__ import annotations

import contextlib
import os
import sys

from ..errors import WarpgaussError

_wp = None


@contextlib.contextmanager
def _silence_stderr():
    """Hide native start-up chatter (the CUDA-driver warning on machines without a GPU)."""
    try:
        fd = sys.stderr.fileno()
    except (AttributeError, OSError, ValueError):
        yield
        return
    sys.stderr.flush()
    saved = os.dup(fd)
    try:
        with open(os.devnull, "w") as devnull:
            os.dup2(devnull.fileno(), fd)
        yield
    finally:
        os.dup2(saved, fd)
        os.close(saved)


def warp():
    """Import and initialise Warp once; return the module."""
    global _wp
    if _wp is None:
        import warp as wp

        wp.config.log_level = 40  # errors only: no per-module compile chatter in the CLI
        if not os.environ.get("WARPGAUSS_VERBOSE_WARP"):
            with _silence_stderr():
                wp.init()
        else:
            wp.init()
        _wp = wp
    return _wp


def resolve_device(device: str | None = None) -> str:
    """Return the Warp device to use: ``device`` if given and present, else CUDA when present, else CPU."""
    wp = warp()
    if device in (None, "", "auto"):
        return "cuda:0" if wp.is_cuda_available() else "cpu"
    names = [str(d) for d in wp.get_devices()]
    if device == "cuda":
        device = "cuda:0"
    if device not in names:
        raise WarpgaussError(f"device {device!r} is not available here (available: {', '.join(names)}); use --device cpu")
    return device


def device_name(device: str) -> str:
    """Human-readable name of a Warp device (GPU model or CPU)."""
    wp = warp()
    d = wp.get_device(device)
    if d.is_cuda:
        return d.name
    import platform

    return f"CPU ({platform.processor() or platform.machine()})"
