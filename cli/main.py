"""The `warpgauss` command: one sub-command per module of this package."""

from __future__ import annotations

import os

import typer

from .bench import bench_app
from .common import PanelCommand
from .decode import decode
from .encode import encode
from .evaluate import evaluate
from .example import example
from .export import export
from .info import info
from .render import render
from .serve import serve
from .stats import stats
from .view import view

app = typer.Typer(
    name="warpgauss",
    help="Compress scalar volumes into a fixed budget of anisotropic 3D Gaussians (NVIDIA Warp).",
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_show_locals=False,
    rich_markup_mode=None,
)


@app.callback()
def main(debug: bool = typer.Option(False, "--debug", help="Show the full traceback of any failure")) -> None:
    """Compress scalar volumes into a fixed budget of anisotropic 3D Gaussians (NVIDIA Warp)."""
    if debug:
        os.environ["WARPGAUSS_DEBUG"] = "1"


app.command("encode", cls=PanelCommand)(encode)
app.command("decode", cls=PanelCommand)(decode)
app.command("info", cls=PanelCommand)(info)
app.command("eval", cls=PanelCommand)(evaluate)
app.command("example", cls=PanelCommand)(example)
app.command("stats", cls=PanelCommand)(stats)
app.command("render", cls=PanelCommand)(render)
app.command("export", cls=PanelCommand)(export)
app.command("view", cls=PanelCommand)(view)
app.command("serve", cls=PanelCommand)(serve)
app.add_typer(bench_app, name="bench")


def run() -> None:
    """Console-script entry point."""
    app()


if __name__ == "__main__":
    run()
