"""The warpgauss command-line interface (typer)."""
