"""What every command shares: one-line errors with exit code 2, option parsing, the console."""

from __future__ import annotations

import functools
import json
import math
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


def debugging() -> bool:
    """``warpgauss --debug ...`` or WARPGAUSS_DEBUG=1: show tracebacks instead of one-line errors."""
    return bool(os.environ.get("WARPGAUSS_DEBUG"))


def _first_line(e: BaseException) -> str:
    text = str(e).strip()
    return text.splitlines()[0] if text else type(e).__name__


def handle_errors(fn):
    """Turn every failure into one line on stderr: exit code 2, no traceback (``--debug`` shows it).

    The user's mistakes (bad input, missing files, refused options) are stated as they are; an
    unexpected exception is reported as an internal error with a hint to rerun with ``--debug``.
    Ctrl-C outside refinement (which handles it itself) exits 130 with one line.
    """

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except (typer.Exit, typer.Abort, SystemExit):
            raise
        except (WarpgaussError, FileNotFoundError, IsADirectoryError, PermissionError) as e:
            if debugging():
                raise
            msg = _first_line(e)
            if isinstance(e, FileNotFoundError) and e.filename:
                msg = f"no such file: {e.filename}"
            elif isinstance(e, PermissionError) and e.filename:
                msg = f"permission denied: {e.filename}"
            fail(msg)
        except KeyboardInterrupt:
            if debugging():
                raise
            err_console.print("[bold red]interrupted[/]", markup=True)
            raise typer.Exit(130) from None
        except Exception as e:  # noqa: BLE001 - a bug: still one line, the traceback on request
            if debugging():
                raise
            fail(f"internal error: {type(e).__name__}: {_first_line(e)} (rerun with --debug for the traceback, and please report it)")

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


def parse_int_list(text: str | None, what: str) -> tuple[int, ...] | None:
    """'2000,20000,2e5' -> (2000, 20000, 200000); None stays None; refuses empty or non-positive lists."""
    if text is None:
        return None
    try:
        values = tuple(int(float(x)) for x in text.replace("_", "").split(",") if x.strip())
    except ValueError:
        values = ()
    if not values or min(values) < 1:
        raise WarpgaussError(f"{what} must be a comma-separated list of positive integers, got {text!r}")
    return values


def _finite(obj):
    """``obj`` with every non-finite float replaced by None (JSON has no NaN or Infinity)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    return obj


def json_text(obj) -> str:
    """Standard JSON (non-finite numbers written as null) that any parser reads, newline-terminated."""
    return json.dumps(_finite(obj), indent=2, sort_keys=True, default=str, allow_nan=False) + "\n"


def print_json(obj) -> None:
    sys.stdout.write(json_text(obj))


def human_bytes(n: float | None) -> str:
    if n is None:
        return "-"
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if abs(n) < 1024 or unit == "TiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.2f} {unit}"
        n /= 1024
    return f"{n:.2f} TiB"
