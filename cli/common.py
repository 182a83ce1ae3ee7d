"""What every command shares: one-line errors with exit code 2, option parsing, the console."""

from __future__ import annotations

import functools
import json
import math
import os
import sys
import time
from pathlib import Path

import typer
import typer.core
from rich.console import Console

from warpgauss.errors import WarpgaussError
from warpgauss.readers.common import parse_shape  # noqa: F401 - the commands' --shape

err_console = Console(stderr=True, highlight=False)
out_console = Console(highlight=False, soft_wrap=True)  # whole lines in a file or a pipe; tables still fit the width


def print_error(message: str) -> None:
    """``error: MESSAGE`` on stderr, the message shown as written (text in brackets such as
    ``'[x]'`` or a list is not taken for rich markup)."""
    from rich.markup import escape

    err_console.print(f"[bold red]error:[/] {escape(message)}", soft_wrap=True)


def fail(message: str) -> None:
    """Print a one-line error and exit 2."""
    print_error(message)
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


class PhaseLines:
    """An encode's progress for people: the spinner says what runs now, and each phase (the run
    report's stages grouped in plain words, :func:`warpgauss.core.profiling.phase_of`) leaves one line
    with its seconds on stderr when the next begins or :meth:`close` is called."""

    def __init__(self, status) -> None:
        self.status = status
        self.phase: str | None = None
        self.t0 = 0.0

    def stage(self, name: str, title: str) -> None:
        from warpgauss.core.profiling import phase_of

        words = phase_of(name)
        if words != self.phase:
            self.close()
            self.phase, self.t0 = words, time.perf_counter()
        self.status.update(f"{words}: {title}")

    def update(self, text: str) -> None:
        self.status.update(f"{self.phase}: {text}" if self.phase else text)

    def close(self) -> None:
        if self.phase is not None:
            self.status.console.print(f"  {self.phase:<36} {time.perf_counter() - self.t0:8.2f} s", highlight=False)
            self.phase = None


def human_bytes(n: float | None) -> str:
    if n is None:
        return "-"
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if abs(n) < 1024 or unit == "TiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.2f} {unit}"
        n /= 1024
    return f"{n:.2f} TiB"


def size_text(n: int) -> str:
    """A file's or a part's size for people, one way everywhere: exact bytes, and the binary unit
    beside them from 1 KiB (``18,651 B (18.21 KiB)``)."""
    return f"{n:,} B" if n < 1024 else f"{n:,} B ({human_bytes(n)})"


def psnr_text(db: float, occupied: float | None) -> str:
    """PSNR and occupied-only PSNR for people (``PSNR 48.12 dB, occupied 48.20 dB``); an exact
    decode (MSE 0) reports the cap, :data:`warpgauss.field.evaluate.PSNR_CAP_DB`, and says so."""
    from warpgauss.field.evaluate import PSNR_CAP_DB

    occ = "n/a" if occupied is None else f"{occupied:.2f} dB"
    cap = f" ({PSNR_CAP_DB:.0f} dB is the cap: no error)" if db >= PSNR_CAP_DB else ""
    return f"PSNR {db:.2f} dB, occupied {occ}{cap}"


def error_text(normalised: float, source: float | None = None) -> str:
    """A max abs error with its unit named: a share of the value range (what PSNR is computed on),
    and where known the same error in source units, so the two cannot be read as two errors."""
    text = f"{normalised:.4g} of the value range"
    return text if source is None else f"{source:.6g} source units ({text})"


# ---------------------------------------------------------------------------- --config FILE


def _option_names(command) -> dict[str, str]:
    """Every name a configuration file may use for ``command``'s parameters -> the parameter:
    the long option without dashes, with '-' or '_' ("bytes", "w-smooth", "w_smooth", "json"),
    and the parameter's own name."""
    names: dict[str, str] = {}
    for p in command.params:
        if p.name == "config":
            continue
        names[p.name] = p.name
        for opt in getattr(p, "opts", []) + getattr(p, "secondary_opts", []):
            if opt.startswith("--"):
                names[opt[2:]] = p.name
                names[opt[2:].replace("-", "_")] = p.name
    return names


def _long_name(param) -> str:
    longs = [o[2:] for o in getattr(param, "opts", []) if o.startswith("--")]
    return longs[0] if longs else param.name


def read_config(path: Path) -> dict:
    """The options a ``--config`` file holds: a TOML table of option names (``[encode]`` or top
    level), or a run report's ``config`` (JSON), so a run repeats from its report."""
    if not path.is_file():
        raise WarpgaussError(f"no such configuration file: {path}")
    text = path.read_bytes()
    if path.suffix.lower() == ".json":
        try:
            data = json.loads(text)
        except (ValueError, UnicodeDecodeError) as e:
            raise WarpgaussError(f"{path}: not valid JSON ({e}); give a TOML file or a run report") from None
        if not isinstance(data, dict) or not isinstance(data.get("config"), dict):
            raise WarpgaussError(f"{path}: a JSON configuration must be a run report with a 'config' table")
        return data["config"]
    try:
        import tomllib
    except ImportError:  # Python 3.10
        import tomli as tomllib  # type: ignore[no-redef]
    try:
        data = tomllib.loads(text.decode("utf-8"))
    except (ValueError, UnicodeDecodeError) as e:
        raise WarpgaussError(f"{path}: not valid TOML ({_first_line(e)})") from None
    return data


def _hint(e) -> str:
    """What to run for help, after a usage error that names no option."""
    return "" if isinstance(e, typer.BadParameter) else f" (see warpgauss {e.ctx.command.name} --help)" if e.ctx is not None else ""


def config_callback(ctx: typer.Context, param, value: Path | None):
    """Eager ``--config`` callback: the file's values become the command's defaults (click's
    ``default_map``), so options given on the command line still win. Unknown names and values of
    the wrong type are refused in one line, naming the option."""
    if value is None or ctx.resilient_parsing:
        return value
    try:
        data = read_config(Path(value))
        command = ctx.command
        if isinstance(data.get(command.name), dict):  # a [encode] table
            data = data[command.name]
        names = _option_names(command)
        params = {p.name: p for p in command.params}
        defaults: dict = {}
        for key, v in data.items():
            if isinstance(v, dict):
                continue  # other commands' tables
            if key not in names:
                raise WarpgaussError(f"{value}: unknown option {key!r} for 'warpgauss {command.name}'; see warpgauss {command.name} --help")
            p = params[names[key]]
            if v is None:
                continue
            try:
                if getattr(p, "callback", None) is None:  # the option's own conversion, here to name the file and key
                    p.process_value(ctx, v)
            except typer.BadParameter as e:
                raise WarpgaussError(f"{value}: {key} = {v!r}: {_first_line(Exception(e.format_message()))}") from None
            if isinstance(v, str) and takes_path(p) and not Path(v).expanduser().is_absolute():
                v = str(Path(value).parent / v)  # a file's relative paths are relative to the file, not to where we run
            defaults[p.name] = v  # converted and checked as a default of the option
    except WarpgaussError as e:
        if debugging():
            raise
        fail(_first_line(e))
    ctx.default_map = {**(ctx.default_map or {}), **defaults}
    return value


def takes_path(param) -> bool:
    """Whether a command parameter's value is a path (typer's annotation, or click's type)."""
    import typing

    ann = getattr(getattr(param, "type_descriptor", None), "annotation", None)
    if ann is not None:
        return ann is Path or Path in typing.get_args(ann)
    return type(getattr(param, "type", None)).__name__ == "Path"


NOT_REPEATED = ("config", "force", "resume")  # flags of one invocation: a repeat must ask again to overwrite


def resolved_config(ctx: typer.Context, folder: Path | None = None) -> dict:
    """The command's parameters as run (long option names, None and :data:`NOT_REPEATED` left
    out): a ``--config`` file of these repeats the run (and refuses to overwrite its output). Paths
    are written relative to ``folder`` (the report's, where :func:`config_callback` resolves them
    from), so the report repeats the run from any working folder."""
    out = {}
    for p in ctx.command.params:
        if p.name in NOT_REPEATED:
            continue
        v = ctx.params.get(p.name)
        if v is None:
            continue
        if isinstance(v, Path):
            v = os.path.relpath(v.absolute(), folder.absolute()) if folder is not None else str(v)
        out[_long_name(p)] = v
    return out


PANELS = (
    "Input",
    "Budget and format",
    "Error bound",
    "Refinement",
    "Loss weights",
    "Bricks and cluster",
    "Run control",
    "Output",
)  # help order


# click's usage errors, as the installed typer raises them (it vendors its own click from 0.29 on)
_UsageError = next(c for c in typer.BadParameter.__mro__ if c.__name__ == "UsageError")


class OneLineUsageError(_UsageError):  # type: ignore[misc,valid-type]
    """A usage error shown as one line (``error: ...``, exit 2), not click's usage block."""

    def show(self, file=None) -> None:
        print_error(self.format_message())


class PanelCommand(typer.core.TyperCommand):
    """A command whose plain-text help groups its options under their ``rich_help_panel`` names
    in the order of :data:`PANELS` (others after them); options without a panel (``--help``)
    close the list. A value click cannot take (``--bytes 1.5``) is refused in one line that names
    the option and the value."""

    def parse_args(self, ctx, args):
        try:
            return super().parse_args(ctx, args)
        except OneLineUsageError:
            raise
        except _UsageError as e:  # type: ignore[misc]  # click's class, as the installed typer has it
            if debugging():
                raise
            raise OneLineUsageError(_first_line(e.format_message()) + _hint(e), ctx=e.ctx) from None

    def format_options(self, ctx, formatter) -> None:
        args: list = []
        groups: dict[str, list] = {}
        for param in self.get_params(ctx):
            rv = param.get_help_record(ctx)
            if rv is None:
                continue
            if param.param_type_name == "argument":
                args.append(rv)
            else:
                groups.setdefault(getattr(param, "rich_help_panel", None) or "Other options", []).append(rv)
        if args:
            with formatter.section("Arguments"):
                formatter.write_dl(args)
        order = {t: i for i, t in enumerate(PANELS)}
        if list(groups) == ["Other options"]:  # a command without panels: click's usual heading
            groups = {"Options": groups["Other options"]}
        for title, rows in sorted(groups.items(), key=lambda kv: order.get(kv[0], len(PANELS) + (kv[0] == "Other options"))):
            with formatter.section(title):
                formatter.write_dl(rows)


def with_settings(options: dict, default_of):
    """A command whose options include one per row of ``options`` (a table of
    :class:`warpgauss.encoding.driver.config.Option`): the command is written with a keyword-only
    ``settings`` parameter, and receives there every such option's value by the row's key
    (``default_of(key)`` is the option's default). The table, not the command, spells each
    option's flags, type, panel and help."""
    import inspect
    import typing
    from typing import Annotated

    def wrap(fn):
        sig = inspect.signature(fn)
        hints = typing.get_type_hints(fn, include_extras=True)
        params = [p.replace(annotation=hints.get(p.name, p.annotation)) for p in sig.parameters.values() if p.name != "settings"]
        names: dict[str, str] = {}
        for key, opt in options.items():
            name = opt.param or key.rpartition(".")[2]
            names[name] = key
            info = typer.Option(*opt.flags, rich_help_panel=opt.panel, help=opt.help)
            params.append(
                inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY, default=default_of(key), annotation=Annotated[opt.type, info])
            )

        @functools.wraps(fn)
        def command(*args, **kwargs):
            settings = {names[k]: kwargs.pop(k) for k in list(kwargs) if k in names}
            return fn(*args, settings=settings, **kwargs)

        command.__signature__ = sig.replace(parameters=params)  # type: ignore[attr-defined]
        command.__annotations__ = {p.name: p.annotation for p in params}
        return command

    return wrap
