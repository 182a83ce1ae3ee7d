"""Shared settings and checks of the fuzz suites (issue #7, part 3).

The default run is derandomised (the same examples every time, so CI never flakes) and small;
``WARPGAUSS_FUZZ_EXAMPLES=N`` raises every budget to at least N examples with random draws, for a
longer local or nightly hunt (``pytest tests/fuzz -m "slow or not slow"`` also runs the long
variants). Hypothesis keeps no example database in the tree.
"""

from __future__ import annotations

import os

from hypothesis import HealthCheck, settings

from warpgauss.errors import WarpgaussError

_EXTRA = int(os.environ.get("WARPGAUSS_FUZZ_EXAMPLES", "0") or 0)


def fuzz(examples: int, **kw):
    """Hypothesis settings for one fuzz test: ``examples`` in CI, more on request."""
    opts = {
        "max_examples": max(examples, _EXTRA),
        "deadline": None,
        "database": None,
        "derandomize": _EXTRA == 0,
        "suppress_health_check": [HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.filter_too_much],
    }
    opts.update(kw)
    return settings(**opts)


def assert_clear_refusal(err: BaseException) -> None:
    """A refusal the user can read: a WarpgaussError with one non-empty line."""
    assert isinstance(err, WarpgaussError), repr(err)
    text = str(err)
    assert text.strip() and "\n" not in text.strip(), text
