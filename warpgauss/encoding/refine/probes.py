"""What tests, the self-test and the bench read off a refiner (:class:`Probed`, a part of
:class:`.refiner.Refiner`): one forward and backward pass at the current samples, the gradient,
the raw parameters, the pair pass's load."""

from __future__ import annotations

from typing import Any

import numpy as np


class Probed:
    """Pieces of :class:`.refiner.Refiner` for tests and the self-test."""

    # the refiner's own, which these methods read
    back_pairs: Any
    forward: Any
    n_points: Any
    passes: Any
    schedule: Any
    state: Any
    updater: Any

    def forward_backward(self) -> None:
        """Forward values, per-point gradients and the pair scatter at the current samples."""
        self.schedule.begin()
        self.forward()
        self.accumulate()

    def accumulate(self, kernel=None, count: int | None = None) -> None:
        """Gradients of the first ``count`` points (all by default), with the pairs counted.

        Args:
            kernel: A point-major pair kernel (the dense reference in the self-test); None for
                the refiner's own primitive-major pass.
            count: Points to gather from, the first ``count`` of the buffers.
        """
        self.state.zero_grads()
        self.back_pairs.zero_()
        if kernel is None:
            self.passes.backward(count, count_pairs=True)
        else:
            self.passes.atomic_pairs(kernel, self.n_points if count is None else count)

    def pair_pass_stats(self) -> dict:
        """The last backward pass's load (syncs), see :meth:`.passes.PairPasses.stats`."""
        return self.passes.stats()

    def gradient(self) -> np.ndarray:
        """(N, 12) gradient of the loss w.r.t. the raw parameters, primitive order (after
        :meth:`forward_backward`)."""
        self.updater.finish_grads()
        return self.state.to_primitive_order(self.state.grad)

    def raw_params(self) -> np.ndarray:
        """(N, 12) training parameters in primitive order."""
        return self.state.to_primitive_order(self.state.raw)
