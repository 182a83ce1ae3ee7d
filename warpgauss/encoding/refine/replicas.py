"""One model refined on several devices of this machine at once (issue #55 part 3).

Each device holds a whole replica of the training state (:class:`.refiner.Refiner`) and reads
the same volume (a volume in host memory is shared: registered page-locked memory is mapped into
every device); every iteration each replica draws its share of the samples from a stream of its
own, runs its pair passes, and then every replica combines all replicas' pair gradients, weighted
by their sample shares (:func:`warpgauss.kernels.replicas.mix_pair_grads`: the same sum of the
same arrays in the same order everywhere, so the replicas' Adam steps, parameters and re-bins stay
equal bit for bit with no broadcast). The gradient of the combined samples is the gradient one
device would take from as many samples drawn at once: the same estimator at the same sample count,
not the same model bit for bit (other draws). Before each fold of the error map the replicas'
error counts are summed (integers: any order gives the same), so that every replica's error
stratum follows what all the samples saw. The primary replica drives: validation, stops, the
rate control's re-plan (:meth:`silence`, mirrored here), checkpoints.

Copies between CUDA devices run on the receiving device's stream after it waited for the
sender's; a replica overwrites its own gradients only after every other replica copied them.
On the CPU device (tests) the replicas simply take turns.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from ...core.warp import warp
from ...errors import WarpgaussError

Refiner = Any  # .refiner.Refiner (which imports this module)

PEER_SEED_STRIDE = 1_000_003  # replica k draws from seed + k x this (another stream, the same every run)


def sample_shares(total: int, replicas: int) -> list[int]:
    """``total`` samples an iteration split over ``replicas`` as evenly as integers allow (the
    first ones take the remainder)."""
    base, extra = divmod(int(total), int(replicas))
    return [base + (1 if k < extra else 0) for k in range(replicas)]


class Replicas:
    """The primary :class:`Refiner` and its peers on ``devices`` (see the module docstring).

    Args:
        primary: The refiner the encode drives (made, not yet stepped, or restored).
        devices: The other devices, one replica each.
        make: ``make(dv, cfg, seed)``: a refiner of the primary's parameters on ``dv`` (a
            :class:`~warpgauss.field.analysis.DeviceVolume`) with ``cfg`` and ``seed``.
    """

    def __init__(self, primary: Refiner, devices: Sequence[str], make: Callable[[Any, Any, int], Refiner]):
        from ...field.analysis import DeviceVolume

        wp = self._wp = warp()
        cfg = primary.cfg
        if cfg.relocate_every > 0:
            raise WarpgaussError("relocation (relocate_every) does not combine with refining on several devices; set it to 0")
        if primary.state.n_train != primary.n:
            raise WarpgaussError("a refiner with frozen primitives (a brick) refines on one device")
        self.primary = primary
        self.total = int(cfg.samples)
        k = 1 + len(devices)
        shares = sample_shares(self.total, k)
        if shares[-1] < 1:
            raise WarpgaussError(f"{self.total} samples an iteration cannot be shared by {k} devices; give --samples >= {k}")
        self.shares = shares
        self.weights = [s / self.total for s in shares]
        primary.sampler.map_samples = self.total  # the error map counts what every replica drew
        primary.set_samples(shares[0])
        arrays, scalars = primary.state_arrays()
        self.peers: list[Refiner] = []
        for i, dev in enumerate(devices, 1):
            dv = DeviceVolume(primary.dv.field, dev, on_host=bool(getattr(primary.dv, "on_host", False)))
            peer_cfg = dataclasses.replace(cfg, samples=shares[i])
            peer = make(dv, peer_cfg, primary.seed + i * PEER_SEED_STRIDE)
            peer.sampler.map_samples = self.total
            peer.set_samples(shares[i])
            peer.restore(arrays, {**scalars, "samples": shares[i]})
            self.peers.append(peer)
        self.all: list[Refiner] = [primary, *self.peers]
        for r in self.all:
            r.use_graph = False  # an iteration spans devices: plain launches (no graph gained in a real encode)
            r._graph = None
        self.cuda = [wp.get_device(r.device).is_cuda for r in self.all]
        self._peer_access()
        self._recv = {(d, e): _like(r.state.pair_grads) for d, r in enumerate(self.all) for e in range(k) if e != d}  # d's copy of e's
        self._acc = [_like(r.state.pair_grads) for r in self.all]
        self._err_scratch = None

    @property
    def devices(self) -> list[str]:
        return [str(r.device) for r in self.all]

    def _peer_access(self) -> None:
        """Direct access between every two CUDA devices where the hardware allows it (copies are
        faster; they work without)."""
        wp = self._wp
        cuda = [str(r.device) for r, c in zip(self.all, self.cuda) if c]
        for a in cuda:
            for b in cuda:
                if a != b and wp.is_peer_access_supported(a, b):
                    wp.set_peer_access_enabled(a, b, True)
                    if wp.is_mempool_access_supported(a, b):
                        wp.set_mempool_access_enabled(a, b, True)

    def _wait(self, d: int, e: int) -> None:
        """Device d's stream waits for what device e's stream holds so far."""
        if self.cuda[d] and self.cuda[e] and self.all[d].device != self.all[e].device:
            wp = self._wp
            wp.get_device(self.all[d].device).stream.wait_stream(wp.get_device(self.all[e].device).stream)

    # -- one iteration -----------------------------------------------------------------------

    def step(self) -> None:
        """One iteration on every replica (the primary's :meth:`Refiner.step`)."""
        rs, p = self.all, self.primary
        it, cfg = p.iteration, p.cfg
        if it > 0 and (it % max(cfg.replan_every, 1) == 0 or it % max(cfg.rebin_every, 1) == 0):
            self.merge_errors()  # before the re-bin folds them
        replan = [r.begin_step() for r in rs][0]
        for r in rs:
            r.gradient_launches()
        self.exchange()
        for r in rs:
            r.update_launches()
        contacts = None
        if replan and cfg.touch_ref > 0:  # the contact density of every replica's samples together
            contacts = sum(float(r.pairs.numpy()[: r.m].astype(np.float64).sum()) for r in rs) / p.n
        for r in rs:
            r.end_step(replan, contacts)

    def exchange(self) -> None:
        """Every replica's pair gradients become sum_k w_k g_k (k in replica order), on every device."""
        from ...kernels import replicas as kr

        wp, rs, k = self._wp, self.all, len(self.all)
        for d in range(k):
            for e in range(k):
                if e != d:
                    self._wait(d, e)
                    for dst, src in zip(self._recv[d, e], rs[e].state.pair_grads):
                        wp.copy(dst, src)
        for d in range(k):  # nothing is overwritten before every copy of it is made
            for e in range(k):
                if e != d:
                    self._wait(d, e)
        for d, r in enumerate(rs):
            own = r.state.pair_grads
            terms = [own if e == d else self._recv[d, e] for e in range(k)]
            acc = self._acc[d]
            wp.launch(
                kr.mix_pair_grads, dim=r.n, inputs=[*terms[0], *terms[1], self.weights[0], self.weights[1]], outputs=[*acc], device=r.device
            )
            for e in range(2, k):
                wp.launch(kr.mix_pair_grads, dim=r.n, inputs=[*acc, *terms[e], 1.0, self.weights[e]], outputs=[*acc], device=r.device)
            for dst, src in zip(own, acc):
                wp.copy(dst, src)

    def merge_errors(self) -> None:
        """Every replica's error counts since the last fold become their sum."""
        from ...kernels import replicas as kr

        wp, rs = self._wp, self.all
        if rs[0].sampler.error_share <= 0:
            return
        first = rs[0].sampler.err_acc.flatten()
        if self._err_scratch is None or self._err_scratch.shape != first.shape:
            self._err_scratch = wp.empty(first.shape, dtype=wp.int64, device=rs[0].device)
        for e in range(1, len(rs)):
            self._wait(0, e)
            wp.copy(self._err_scratch, rs[e].sampler.err_acc.flatten())
            wp.launch(kr.add_counts, dim=first.shape[0], inputs=[first, self._err_scratch], device=rs[0].device)
        for e in range(1, len(rs)):
            self._wait(e, 0)
            wp.copy(rs[e].sampler.err_acc.flatten(), first)

    # -- what the primary does between steps, done on every replica --------------------------

    def silence(self, ids) -> None:
        """:meth:`Refiner.silence` on every replica (the rate control's re-plan)."""
        self.merge_errors()  # its re-bin folds them
        for r in self.all:
            r.silence_here(ids)

    def sync(self) -> None:
        """The peers restored from the primary's state (after a resume or a self-test)."""
        arrays, scalars = self.primary.state_arrays()
        for peer, share in zip(self.peers, self.shares[1:]):
            peer.restore(arrays, {**scalars, "samples": share})
            peer.use_graph = False

    def equal(self) -> bool:
        """Whether every replica holds the primary's parameters bit for bit (syncs; tests, benchmarks)."""
        first = self.primary.state.raw.numpy()
        return all(np.array_equal(first, r.state.raw.numpy()) for r in self.peers)

    def report(self) -> dict:
        return {"devices": self.devices, "samples": self.shares, "equal": self.equal()}


def _like(arrays: tuple) -> tuple:
    """Zeroed arrays shaped and typed as ``arrays``, on their device."""
    wp = warp()
    return tuple(wp.zeros_like(a) for a in arrays)
