"""What every command shares: one-line errors with exit code 2, option parsing, the console."""

from __future__ import annotations

import functools
import json
import os
import sys

import typer
from rich.console import Console

from warpgauss.errors import WarpgaussError

err_console = Console(stderr=True, highlight=False)
out_console = Console(highlight=False)


def fail(message: str) -> None:
    """Print a one-line error and exit 2."""
    err_console.print(f"[bold red]error:[/] {message}", soft_wrap=True, markup=True)
    raise typer.Exit(2)


def handle_errors(fn):
    """Turn the user's mistakes (bad input, missing files) into one line and exit code 2.

    Set WARPGAUSS_DEBUG=1 to see the traceback instead.
    """

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except (WarpgaussError, FileNotFoundError, IsADirectoryError, PermissionError) as e:
            if os.environ.get("WARPGAUSS_DEBUG"):
                raise
            msg = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            if isinstance(e, FileNotFoundError) and e.filename:
                msg = f"no such file: {e.filename}"
            fail(msg)

    return wrapper


def parse_shape(text: str | None, what: str = "--shape") -> tuple[int, int, int] | None:
    """'128x128x64' or '128,128,64' -> (128, 128, 64) as (x, y, z)."""
    if text is None:
        return None
    parts = text.replace(",", "x").replace("X", "x").split("x")
    try:
        shape = tuple(int(p) for p in parts)
    except ValueError:
        shape = ()
    if len(shape) != 3 or min(shape) < 1:
        raise WarpgaussError(f"{what} must be three positive integers XxYxZ (e.g. 128x128x64), got {text!r}")
    return shape


def print_json(obj) -> None:
    sys.stdout.write(json.dumps(obj, indent=2, sort_keys=True, default=str) + "\n")


def human_bytes(n: float | None) -> str:
    if n is None:
        return "-"
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if abs(n) < 1024 or unit == "TiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.2f} {unit}"
        n /= 1024
    return f"{n:.2f} TiB"
