"""Stage "draw": the iteration's training samples (SPEC section 3) and their per-sample buffers.

35 % from V > 0.4, 40 % from occupied mid-range voxels, 25 % uniform, at voxel centres (the paper
jitters them by up to half a voxel, with trilinear targets), weighted so that the value loss
estimates the full-grid MSE, with a partner point for the smoothness term
(:func:`warpgauss.kernels.sampling.draw_samples`). The
strata are indexed once (prefix sums of per-brick counts); the uniform stratum's support (the
bricks some primitive reaches) is re-marked after every re-bin. With ``error_share`` that share of
the samples follows the model's error instead (per-brick running sums of the samples' weighted
squared errors, re-drawn at every re-bin; see :mod:`warpgauss.kernels.sampling`).
"""

from __future__ import annotations

import numpy as np

from ...core.warp import warp
from ...field.analysis import DeviceVolume

STRATA = (0.35, 0.40, 0.25)  # high (V > 0.4), occupied mid-range, uniform (SPEC section 3)
# the error stratum is drawn only where its map sees at least this many samples a 4^3 cell over
# its memory (rebin_every x samples / (1 - error_decay) / cells): below, most cells hold no error
# yet and the stratum keeps re-drawing the few that were sampled. A GPU encode's samples (one per
# 128 voxels, at most 131,072, when this was measured; now one per 64, at most 262,144) gave 16.7
# up to 256^3, 2.1 at 512^3, 0.26 at 1024^3 and 0.033 at 2048^3 (the same in each brick). Measured: the 2048^3 out-of-core field on one H200 (3x3x4
# bricks, N 4,000,000) 59.14 dB with the stratum, 62.05 without
# (bricked/out_of_core2048_err0_h200.json); float32 on the CPU, N 3,000, 400 iterations
# (accuracy/error_density_cpu.json): the interface at 192^3 -0.46 / -0.23 dB at 0.019 / 0.039,
# +1.17 at 0.15; out_of_core.py's field -0.55 / -0.38 / -0.27
ERROR_MIN_SAMPLES_A_CELL = 0.1
# True: where the cells see fewer than ERROR_POOL_SAMPLES_A_CELL samples, the quota scores blocks
# of f^3 cells (f = 2, 4 or 8, the smallest that sees that many; a block's draws spread over its
# voxels alike), and the stratum is left out only where even f = ERROR_MAX_POOL sees fewer than
# ERROR_MIN_SAMPLES_A_CELL. On the CPU (accuracy/error_density*_cpu.json, RD.md round 9) the
# interface gained 1.5-2.2 dB over the stratum left out at 0.019-0.039 samples a cell and 1.7 over
# the 4^3 cells at 0.15, the smooth field within -0.12 .. +0.22; from about 5 the 4^3 cells were
# best. Off (False): on a GPU it changes encodes from 1024^3 up and is not measured there
ERROR_POOL = False
ERROR_POOL_SAMPLES_A_CELL = 1.0
ERROR_MAX_POOL = 8
# A volume in host memory (DeviceVolume.on_host): each iteration's samples are drawn during the
# iteration before, on a second stream (Sampler.enable_ahead; the same samples), by
# DRAW_THREADS_HOST threads (thread t draws samples t, t + threads, ...; the same samples). The
# draw's reads over the bus are bound by their latency, not by the threads in flight (at 512^3,
# drawn in turn: 10.58 ms an iteration with one thread a sample, 10.79 with 4,096), and one
# thread a sample (262,144) fills the multiprocessors with waiting threads the pair passes beside
# it cannot use: the draw ahead gained nothing that way (1024^3: 51 -> 53 ms an iteration).
# Measured on an H200 with the anchor targets held (update.ANCHOR_CACHE), vortex CR 100, whole
# encodes against in core in the same run (scale/volume_on_host{512,1024}_anchors*_h200.json):
# 512^3 drawn in turn 1.07x, ahead with one thread a sample 1.07x, ahead with 4,096 threads 1.02x;
# 1024^3 drawn in turn 93.93 s (1.26x), ahead with 4,096 threads 91.63 s (1.15x of its run's in
# core). 0 threads: one a sample, as on the device
DRAW_AHEAD = True
DRAW_THREADS_HOST = 4096
# A volume in host memory may hold more than 2^31 voxels (field.analysis.MAX_HOST_VOXELS): the
# strata's and the support's prefix sums are int64, and a rank among more than RANK32_MAX voxels
# is drawn with 64 bits (kernels.sampling.rank_below); up to it, with one 32-bit draw as before
# (the same samples). The wide loads view the volume as rows of at most FLAT4_COLUMNS groups of
# four (a Warp array dimension holds fewer than 2^31 elements). Tests lower both to run the
# 64-bit draw and the split view on small volumes.
RANK32_MAX = 2**31 - 1
FLAT4_COLUMNS = 2**30


def stratum_counts(m: int, n_high: int, n_mid: int) -> tuple[int, int, int]:
    """Samples per stratum (high, mid, uniform): 35/40/25, an empty stratum's share going to the rest."""
    shares = [STRATA[0] if n_high else 0.0, STRATA[1] if n_mid else 0.0, STRATA[2]]
    total = sum(shares)
    m_high = int(round(m * shares[0] / total))
    m_mid = int(round(m * shares[1] / total))
    return m_high, m_mid, m - m_high - m_mid


# Bricks a thread of the unreached error's sum adds up (kernels.support.sum_runs): the per-brick
# array stays on the device and only its partials are read back. Read whole and summed on the host
# (as before) at 2048^3 it was 537 MB and about 0.3-0.5 s a loss record (every 25 iterations)
UNREACHED_RUN = 4096


class Sampler:
    """Draws ``m`` samples (and partners) per iteration into :attr:`points` and the targets.

    Args:
        dv: The normalised field on the device.
        uniform_support: Draw the uniform stratum over the primitives' support (see
            :class:`warpgauss.encoding.refine.config.RefineConfig`), unless ``value_empty`` is 0.
        value_empty: Value-loss weight of empty samples: at 0 the uniform stratum is drawn among
            the occupied voxels (an empty sample would add nothing to any loss term).
        partner_distance: Range of the partner offset in voxels.
        jitter: Largest offset of a sample from its voxel centre along each axis (voxels).
        importance: Weight samples so that the value loss estimates the full-grid MSE.
        error_share: Share of the samples drawn where the error is (see
            :class:`warpgauss.encoding.refine.config.RefineConfig`); 0: none. Needs ``importance``.
        error_decay: Weight of a brick's error sums at each re-bin (running sums).
        rebin_every: Iterations between re-bins (the error map's refreshes): with ``error_decay``
            and the samples, how many samples a cell of the map sees (see
            :data:`ERROR_MIN_SAMPLES_A_CELL`).
    """

    def __init__(
        self,
        dv: DeviceVolume,
        uniform_support: bool,
        value_empty: float,
        partner_distance: tuple[float, float],
        jitter: float = 0.5,
        importance: bool = False,
        error_share: float = 0.0,
        error_decay: float = 0.7,
        rebin_every: int = 10,
    ):
        self._wp = wp = warp()
        self.dv, self.device = dv, dv.device
        self.partner_distance = partner_distance
        self.jitter, self.importance = float(jitter), bool(importance)
        self.error_share = float(error_share) if importance else 0.0
        self.error_decay = float(error_decay)
        self.rebin_every = int(rebin_every)
        self._build_strata()
        self._build_errors()
        self.uniform_occupied = value_empty == 0 and self.n_high + self.n_mid > 0
        self.uniform_support = uniform_support and not self.uniform_occupied
        dev = self.device
        if self.uniform_support:
            shape = self.bricks
            # (coverage counts per brick, "everything" flag, supported voxels per brick)
            self.marks: tuple | None = (
                wp.zeros(shape, dtype=int, device=dev),
                wp.zeros(1, dtype=int, device=dev),
                wp.zeros(shape, dtype=wp.int64, device=dev),
            )
            self.support = wp.zeros(int(np.prod(shape)), dtype=wp.int64, device=dev)
        else:
            self.support = wp.zeros(1, dtype=wp.int64, device=dev)  # unused by the sampler
            unused = wp.zeros((1, 1, 1), dtype=wp.int64, device=dev)
            self.marks = None
            self._no_marks = (unused, wp.zeros(1, dtype=int, device=dev))
        self._flat4: tuple | None = None  # (wide, the volume as groups of four): _wide
        # drawing one iteration ahead (enable_ahead): what the draw reads besides the volume and
        # its stream changes only where version is bumped; a staged draw is taken only unchanged
        self.version = 0
        self.ahead = False
        self.staged: int | None = None  # the version the staging buffers were drawn at
        self._stage: tuple | None = None
        self._side = None
        self._support_read: dict = {}  # supported voxels and unreached error, read once per support (index_support)
        self.m = self.m_err = 0
        self.map_samples: int | None = None  # samples an iteration the error map counts (None: m; several replicas: all)
        self.on_host = bool(getattr(dv, "on_host", False))  # the volume read over the bus
        if self.on_host and DRAW_AHEAD:  # the draw beside the passes
            self.enable_ahead()
        self.samples_a_cell = 0.0
        self.error_pool = 1  # cells per block edge the quota scores (see ERROR_POOL)
        self.err_pooled = None

    def _build_strata(self) -> None:
        """Prefix sums of per-brick stratum counts: the index the sampler draws stratum voxels from."""
        from ...kernels import sampling as ks

        wp, dv, dev = self._wp, self.dv, self.device
        nz, ny, nx = dv.values.shape
        b = ks.BRICK
        self.bricks = shape = (-(-nz // b), -(-ny // b), -(-nx // b))  # 4^3 bricks (the strata's and the support's)
        counts = [wp.empty(shape, dtype=wp.int64, device=dev) for _ in range(2)]
        bits = [wp.empty(shape, dtype=wp.uint64, device=dev) for _ in range(2)]
        wp.launch(ks.brick_counts, dim=shape, inputs=[dv.values, dv.mask, dv.has_mask], outputs=[*counts, *bits], device=dev)
        self.high_bits, self.mid_bits = (b.flatten() for b in bits)
        self.high, self.mid = (wp.empty(int(np.prod(shape)), dtype=wp.int64, device=dev) for _ in range(2))
        for c, cum in zip(counts, (self.high, self.mid)):
            wp.utils.array_scan(c.flatten(), cum, inclusive=True)
        last = int(np.prod(shape)) - 1
        self.n_high, self.n_mid = (int(cum[last:].numpy()[0]) for cum in (self.high, self.mid))

    def _build_errors(self) -> None:
        """The error stratum's per-brick buffers (a placeholder index without one)."""
        wp, dev, shape = self._wp, self.device, self.bricks
        nb = int(np.prod(shape))
        self.err_cum = wp.zeros(nb if self.error_share > 0 else 1, dtype=int, device=dev)
        if self.error_share > 0:
            self.err_acc = wp.zeros(shape, dtype=wp.int64, device=dev)
            self.err_sum = wp.zeros(shape, dtype=float, device=dev)
            self.err_quota = wp.zeros(shape, dtype=int, device=dev)
            self.err_top = wp.zeros(1, dtype=float, device=dev)
            self.err_cap = max(1, min((2**31 - 1) // nb, 1 << 16))  # every brick's quota summed fits an int

    def resize(self, m: int) -> None:
        """(Re)allocate the buffers for ``m`` samples (points holds 2 m: samples, then partners)."""
        wp, dev = self._wp, self.device
        self.m = m
        self.points, self.target, self.weight, self.occupied = self._sample_buffers()
        self.version += 1
        self._alloc_stage()
        memory = self.rebin_every / (1.0 - self.error_decay) if self.error_decay < 1 else float("inf")
        self.samples_a_cell = d = memory * (self.map_samples or m) / int(np.prod(self.bricks))
        f = 1
        while ERROR_POOL and f < ERROR_MAX_POOL and d * f**3 < ERROR_POOL_SAMPLES_A_CELL:
            f *= 2
        drawn = self.error_share > 0 and d * f**3 >= ERROR_MIN_SAMPLES_A_CELL
        self.m_err = min(m - 1, int(round(m * self.error_share))) if drawn else 0
        self.error_pool = f if drawn else 1
        if self.error_pool > 1:
            self.err_pooled = wp.zeros(tuple(-(-b // f) for b in self.bricks), dtype=float, device=dev)
        self.strata = stratum_counts(m - self.m_err, self.n_high, self.n_mid)

    def error_report(self) -> dict:
        """What the error stratum did: its share as set and as drawn, and the samples a cell of its
        map sees (what decided)."""
        return {
            "share": self.error_share,
            "share_drawn": self.m_err / self.m if self.m else 0.0,
            "samples_a_cell": self.samples_a_cell,
            "cell_edge": 4 * self.error_pool,
        }

    def error_arrays(self) -> dict[str, np.ndarray]:
        """The error stratum's state for a checkpoint: the sums since the last re-bin and the
        running sums (empty arrays without an error stratum)."""
        if self.error_share <= 0:
            return {"errors_new": np.zeros(0, np.int64), "errors": np.zeros(0, np.float32)}
        return {"errors_new": self.err_acc.numpy().reshape(-1), "errors": self.err_sum.numpy().reshape(-1)}

    def restore_errors(self, new: np.ndarray, running: np.ndarray) -> None:
        """Continue from :meth:`error_arrays`: the running sums, the quota drawn from them at that
        re-bin (the same index), then the sums since."""
        from ...errors import WarpgaussError

        size = int(np.prod(self.bricks)) if self.error_share > 0 else 0
        if new.size != size or running.size != size:
            raise WarpgaussError(f"checkpoint holds {running.size} error-stratum bricks, this run has {size}")
        if size == 0:
            return
        self.err_sum.assign(running.reshape(self.bricks))
        self.err_acc.zero_()
        self.refresh_errors(decay=1.0)  # the running sums as they were: x 1 + 0 is x
        self.err_acc.assign(new.reshape(self.bricks))

    def record_errors(self, loss) -> None:
        """Add this iteration's weighted squared errors (``loss``: point_grads' per-sample terms)
        to their bricks' sums (nothing without an error stratum)."""
        from ...kernels import sampling as ks

        if self.m_err > 0:
            self._wp.launch(
                ks.accumulate_errors, dim=self.m, inputs=[self.points, loss, self.m], outputs=[self.err_acc], device=self.device
            )

    def refresh_errors(self, decay: float | None = None) -> None:
        """Fold the sums since the last call into the bricks' running sums (those weighted by
        ``decay``, default ``error_decay``) and re-draw the error stratum's quota from them
        (nothing without an error stratum)."""
        from ...kernels import sampling as ks

        if self.error_share <= 0 or (self.m_err == 0 and decay is None):  # nothing recorded, nothing drawn
            return
        wp, dev = self._wp, self.device
        nz, ny, nx = self.dv.values.shape
        self.version += 1
        self.err_top.zero_()
        wp.launch(
            ks.update_errors,
            dim=self.bricks,
            inputs=[self.err_acc, self.error_decay if decay is None else float(decay), nz, ny, nx],
            outputs=[self.err_sum, self.err_top],
            device=dev,
        )
        if self.err_pooled is not None and self.error_pool > 1:  # blocks of f^3 cells scored (ERROR_POOL)
            f = self.error_pool
            wp.launch(ks.pool_errors, dim=self.err_pooled.shape, inputs=[self.err_sum, f], outputs=[self.err_pooled], device=dev)
            self.err_top.zero_()
            wp.launch(ks.pooled_top, dim=self.bricks, inputs=[self.err_pooled, f, nz, ny, nx], outputs=[self.err_top], device=dev)
            wp.launch(
                ks.pooled_quota,
                dim=self.bricks,
                inputs=[self.err_pooled, self.err_top, self.err_cap, f, nz, ny, nx],
                outputs=[self.err_quota],
                device=dev,
            )
        else:
            wp.launch(
                ks.error_quota,
                dim=self.bricks,
                inputs=[self.err_sum, self.err_top, self.err_cap, nz, ny, nx],
                outputs=[self.err_quota],
                device=dev,
            )
        wp.utils.array_scan(self.err_quota.flatten(), self.err_cum, inclusive=True)

    def _wide(self) -> tuple:
        """(wide, flat4) for draw_samples: a volume in host memory viewed as groups of four values
        (a row's two corners in one load over the bus), else (0, a placeholder)."""
        if self._flat4 is None:
            wp, v = self._wp, self.dv.values
            groups = v.size // 4
            cols = max(1, min(groups, FLAT4_COLUMNS))
            self._flat4 = (
                (1, wp.array(ptr=v.ptr, dtype=wp.vec4, shape=(groups // cols, cols), device=v.device, pinned=v.pinned))
                if self.on_host and groups >= 1
                else (0, wp.zeros((1, 1), dtype=wp.vec4, device=self.device))
            )
        return self._flat4

    def draw(self, stream, into: tuple | None = None) -> None:
        """Draw this iteration's samples from the RNG stream id in ``stream`` (a device int) into
        the sample buffers (``into``: other buffers of the same shapes)."""
        from ...kernels import sampling as ks

        wp, dv = self._wp, self.dv
        m_high, m_mid, _ = self.strata
        pmin, pmax = self.partner_distance
        bricks, everything = (self.marks[2], self.marks[1]) if self.marks is not None else self._no_marks
        threads = self.m
        if self.on_host and DRAW_THREADS_HOST > 0:
            threads = min(self.m, DRAW_THREADS_HOST)
        wp.launch(
            ks.draw_samples,
            dim=threads,
            inputs=[
                dv.values,
                dv.mask,
                dv.has_mask,
                *self._wide(),
                self.high,
                self.mid,
                self.high_bits,
                self.mid_bits,
                max(self.n_high, 1),
                max(self.n_mid, 1),
                m_high,
                m_mid,
                self.n_high,
                self.n_high + self.n_mid if self.uniform_occupied else 0,
                self.support,
                int(self.uniform_support),
                stream,
                float(pmin),
                float(pmax),
                self.jitter,
                int(self.importance),
                bricks,
                everything,
                self.m_err,
                self.err_cum,
                threads,
                RANK32_MAX,
            ],
            outputs=list(into or (self.points, self.target, self.weight, self.occupied)),
            device=self.device,
        )

    # -- one iteration ahead ----------------------------------------------------------------
    # A volume in host memory makes the draw the slowest kernel of an iteration (each target's
    # corners are read over the bus). Drawn one iteration ahead into staging buffers, on a second
    # stream, it runs beside the iteration's pair passes; the next iteration copies it in. The
    # draw reads nothing those passes write, and whatever it does read from the model (support
    # marks, error quota, the sizes) bumps ``version`` when it changes: a staged draw of another
    # version is dropped and drawn again, so the samples, and the model, stay the same bit for bit.

    def enable_ahead(self) -> None:
        """Draw each iteration's samples during the one before (:meth:`stage`, :meth:`take`)."""
        wp = self._wp
        self.ahead = True
        self._side = wp.Stream(self.device) if wp.get_device(self.device).is_cuda else None
        self._alloc_stage()

    def _alloc_stage(self) -> None:
        if self.ahead and self.m:
            self._stage = self._sample_buffers()

    def _sample_buffers(self) -> tuple:
        """(points, target, weight, occupied) for :attr:`m` samples: points holds 2 m (the
        samples, then their partners)."""
        wp, m, dev = self._wp, self.m, self.device
        return (wp.zeros(2 * m, dtype=wp.vec3, device=dev), *(wp.zeros(m, dtype=float, device=dev) for _ in range(3)))

    def stage(self, stream_next) -> None:
        """Draw the next iteration's samples (its RNG stream id in ``stream_next``) into the
        staging buffers, on the second stream where there is one (:meth:`join` waits for it)."""
        assert self._stage is not None
        if self._side is None:
            self.draw(stream_next, into=self._stage)
            return
        wp = self._wp
        self._side.wait_stream(wp.get_stream(self.device))
        with wp.ScopedStream(self._side):
            self.draw(stream_next, into=self._stage)

    def join(self) -> None:
        """The device's stream waits for the staging draw."""
        if self._side is not None:
            self._wp.get_stream(self.device).wait_stream(self._side)

    def can_take(self) -> bool:
        """Whether the staging buffers hold this iteration's samples as a draw now would."""
        return self.ahead and self.staged == self.version

    def take(self) -> None:
        """Copy the staged samples into the sample buffers."""
        assert self._stage is not None
        for dst, src in zip((self.points, self.target, self.weight, self.occupied), self._stage):
            self._wp.copy(dst, src)

    def mark_support(self, mu, ext) -> None:
        """Re-mark the support bricks from prepared centres and half-extents (any order)."""
        from ...kernels import support as ksup

        if not self.uniform_support:
            return
        wp, dev = self._wp, self.device
        self.version += 1
        marks, everything, _ = self.support_marks
        marks.zero_()
        everything.zero_()
        wp.launch(ksup.mark_support, dim=mu.shape[0], inputs=[mu, ext], outputs=[marks, everything], device=dev)
        bz, by, bx = marks.shape
        for axis, lines in ((2, (bz, by)), (1, (bz, bx)), (0, (by, bx))):  # x, y, z: the order does not matter
            wp.launch(ksup.prefix_sum_axis, dim=lines, inputs=[marks, axis], device=dev)
        self.index_support()

    @property
    def support_marks(self) -> tuple:
        """(marks, everything, counts) of the uniform stratum's support (only with a support)."""
        if self.marks is None:
            raise RuntimeError("the sampler has no support marks (its uniform stratum draws from every voxel)")
        return self.marks

    def index_support(self) -> None:
        """Prefix sums of the supported voxels per brick, the index the sampler draws from."""
        from ...kernels import support as ksup

        marks, everything, counts = self.support_marks
        nz, ny, nx = self.dv.values.shape
        self._wp.launch(ksup.support_counts, dim=marks.shape, inputs=[marks, everything, nz, ny, nx], outputs=[counts], device=self.device)
        self._wp.utils.array_scan(counts.flatten(), self.support, inclusive=True)
        self._support_read = {}  # what was read back of the previous support

    def reach(self) -> int:
        """D of the importance weights (see :func:`warpgauss.kernels.sampling.sample_weight`): the
        larger of the uniform stratum's domain and the two strata together (syncs)."""
        n_occ = self.n_high + self.n_mid
        supported = self.supported_voxels()
        if self.uniform_occupied:
            n_uni = n_occ
        elif supported > 0:
            n_uni = supported
        else:
            n_uni = int(self.dv.values.size)
        return max(n_uni, n_occ)

    def unreached_error(self) -> float | None:
        """Sum of squared errors over the voxels the draw cannot reach, where the model is 0 (the
        empty voxels of unsupported bricks: their V^2); None where that is not known (the
        uniform stratum drawn among the occupied voxels: the model is not 0 off them). Syncs."""
        from ...kernels import support as ksup

        if self.uniform_occupied:
            return None
        if self.supported_voxels() == 0:
            return 0.0  # the uniform stratum reaches every voxel
        if "unreached" in self._support_read:  # the support has not changed since (nor has the volume)
            return self._support_read["unreached"]
        wp, dv = self._wp, self.dv
        counts = self.support_marks[2]
        out = wp.empty(counts.shape, dtype=float, device=self.device)
        wp.launch(
            ksup.unreached_squares, dim=counts.shape, inputs=[dv.values, dv.mask, dv.has_mask, counts], outputs=[out], device=self.device
        )
        flat = out.flatten()  # summed on the device by runs, in a fixed order: at 2048^3 the per-brick array is 537 MB
        runs = -(-flat.shape[0] // UNREACHED_RUN)
        partials = wp.empty(runs, dtype=wp.float64, device=self.device)
        wp.launch(ksup.sum_runs, dim=runs, inputs=[flat, UNREACHED_RUN], outputs=[partials], device=self.device)
        self._support_read["unreached"] = float(partials.numpy().sum())
        return self._support_read["unreached"]

    def support_share(self) -> float | None:
        """Share of the grid's voxels the uniform stratum is drawn from now (None: whole grid or
        occupied voxels); reads back from the device."""
        if not self.uniform_support:
            return None
        return self.supported_voxels() / float(self.dv.values.size)

    def supported_voxels(self) -> int:
        """Voxels of the support bricks the uniform stratum is drawn from now (0 without a
        support; reads back from the device once per support)."""
        if not self.uniform_support:
            return 0
        if "voxels" not in self._support_read:
            self._support_read["voxels"] = int(self.support[-1:].numpy()[0])
        return self._support_read["voxels"]
