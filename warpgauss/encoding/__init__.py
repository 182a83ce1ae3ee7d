"""Encoding a volume: :func:`encode` (:mod:`.entry`) reads it (stage P), decides once whether it
is encoded whole or in bricks, and hands over to one of two paths that run side by side:

* the whole volume: the driver's stage table (:mod:`.driver`): analytic allocation S1a-S1e
  (:mod:`.allocate`), refinement S2 (:mod:`.refine`, one module a stage of an iteration), motion
  of a warm start S1m (:mod:`.motion`), rate control and the run report;
* bricks (:mod:`.scale`): the grid split with a halo, the budget split before refinement, each
  brick encoded on its own (in this process or on a Dask cluster), the primitives merged.

Beside them: what a field needs before an encode (:mod:`.stats`, ``warpgauss stats``) and the
kernels' microbenchmarks (:mod:`.bench`, ``warpgauss bench kernels``).
"""

from .driver import encode_ladder
from .entry import encode

__all__ = ["encode", "encode_ladder"]
