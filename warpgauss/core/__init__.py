"""What every floor of the package stands on, and nothing of warpgauss above it: Warp's start-up
and the device choice (:mod:`.warp`), atomic file writes (:mod:`.files`), memory limits
(:mod:`.limits`), per-stage wall time and memory (:mod:`.profiling`), several jobs side by side
on one device (:mod:`.together`) and the table of moved import paths (:mod:`.moved`).

Nothing here imports Warp at import time: :func:`.warp.warp` starts it on first use.
"""
