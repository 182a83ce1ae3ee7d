"""EWA splatting of a model: the interactive render path (kernels in :mod:`warpgauss.kernels.splat`).

Per frame: project every primitive (2D mean, conic, amplitude, shaded colour, tile rectangle), sort
by view depth, emit one (tile, primitive) pair per covered 16x16 tile in depth order, stable-sort
the pairs by tile, find each tile's range, and blend each pixel's list front to back. The
transfer function is applied per primitive, so splatting approximates the ray-marched mixture
(see the kernel module for the mapping); it does not clip primitives to the grid box as the
marcher does.
"""

from __future__ import annotations

import math
import time

from .raymarch import Camera, Image, Marcher, RenderSettings, Scene, View, count_stats, resolve_view
from .transfer import TransferFunction, make_transfer_function


class SplatRenderer(Marcher):
    """A model resident on a device, ready to splat.

    Args:
        model: A :class:`warpgauss.Model`, or (params, header).
        device: Warp device (None: CUDA when present, else CPU).
    """

    def __init__(self, model, device: str | None = None):
        from ..field.gaussians import GaussianField
        from ..kernels import field as kf
        from ..kernels import splat as ks

        params, header = (model.params, model.header) if hasattr(model, "params") else model
        super().__init__(Scene.from_header(header), device)
        wp, dev = self._wp, self.device
        wp.load_module(ks, device=dev)
        self._ks, self._kf = ks, kf
        self.header = header
        self.field = f = GaussianField(params, self.scene.shape_xyz, device=dev)
        n = self.n = f.n
        self.rho_c = wp.empty(n, dtype=float, device=dev)
        self.grad_c = wp.empty(n, dtype=wp.vec3, device=dev)
        wp.launch(ks.centre_samples, dim=n, inputs=[f.mu, f.prims], outputs=[self.rho_c, self.grad_c], device=dev)
        self.xy = wp.empty(n, dtype=wp.vec2, device=dev)
        self.conic = wp.empty(n, dtype=wp.vec3, device=dev)
        self.amp = wp.empty(n, dtype=float, device=dev)
        self.color = wp.empty(n, dtype=wp.vec3, device=dev)
        self.depth = wp.empty(2 * n, dtype=float, device=dev)
        self.order = wp.empty(2 * n, dtype=int, device=dev)
        self.rect = wp.empty(n, dtype=wp.vec4i, device=dev)
        self.count = wp.empty(n, dtype=int, device=dev)
        self.sorted_count = wp.empty(n, dtype=int, device=dev)
        self.offsets = wp.empty(n, dtype=int, device=dev)
        self.total = wp.empty(1, dtype=int, device=dev)
        self._pairs = 0
        self.pair_keys = self.pair_prims = None

    def _reserve_pairs(self, p: int) -> None:
        if p > self._pairs:
            wp = self._wp
            cap = max(p, int(self._pairs * 1.5), 1024)
            self.pair_keys = wp.empty(2 * cap, dtype=int, device=self.device)
            self.pair_prims = wp.empty(2 * cap, dtype=int, device=self.device)
            self._pairs = cap

    def render(
        self, camera: Camera | View | None = None, tf: TransferFunction | None = None, settings: RenderSettings | None = None
    ) -> Image:
        """One frame by EWA splatting (same camera, transfer function and settings as ray marching)."""
        wp, ks, dev, f, n = self._wp, self._ks, self.device, self.field, self.n
        settings = settings or RenderSettings()
        settings.validate()
        view = camera if isinstance(camera, View) else resolve_view(camera or Camera(), self.scene, settings.width, settings.height)
        lut = self.transfer_lut(tf or make_transfer_function())
        prm = self.params(settings, view)
        cam = view.struct()
        h, w = settings.height, settings.width
        tiles_x, tiles_y = math.ceil(w / 16), math.ceil(h / 16)
        image = wp.empty((h, w), dtype=wp.vec4, device=dev)
        drawn = wp.empty((h, w), dtype=int, device=dev)
        tile_start = wp.zeros(tiles_x * tiles_y, dtype=int, device=dev)
        tile_end = wp.zeros(tiles_x * tiles_y, dtype=int, device=dev)
        wp.synchronize_device(dev)
        t0 = time.perf_counter()
        wp.launch(
            ks.project,
            dim=n,
            inputs=[cam, prm, lut, tiles_x, tiles_y, f.mu, f.rot, f.inv_s2, f.a, f.w, self.rho_c, self.grad_c],
            outputs=[self.xy, self.conic, self.amp, self.color, self.depth, self.rect, self.count],
            device=dev,
        )
        wp.launch(ks.iota, dim=n, inputs=[self.order], device=dev)
        wp.utils.radix_sort_pairs(self.depth, self.order, n)
        wp.launch(ks.gather_counts, dim=n, inputs=[self.order, self.count], outputs=[self.sorted_count], device=dev)
        wp.utils.array_scan(self.sorted_count, self.offsets, inclusive=False)
        wp.launch(ks.total_pairs, dim=1, inputs=[self.offsets, self.sorted_count], outputs=[self.total], device=dev)
        pairs = int(self.total.numpy()[0])
        if pairs > 0:
            self._reserve_pairs(pairs)
            wp.launch(
                ks.emit_pairs,
                dim=n,
                inputs=[self.order, self.offsets, self.rect, self.count, tiles_x],
                outputs=[self.pair_keys, self.pair_prims],
                device=dev,
            )
            # keys are tile ids: sort only their bits (stable, so each tile keeps depth order)
            wp.utils.radix_sort_pairs(self.pair_keys, self.pair_prims, pairs, 0, max(1, (tiles_x * tiles_y - 1).bit_length()))
            wp.launch(self._kf.cell_ranges, dim=pairs, inputs=[self.pair_keys, pairs], outputs=[tile_start, tile_end], device=dev)
        prims = self.pair_prims if pairs > 0 else self.order
        wp.launch(
            ks.blend,
            dim=tiles_x * tiles_y * ks.TILE * ks.TILE,
            inputs=[cam, prm, tiles_x, tile_start, tile_end, prims, self.xy, self.conic, self.amp, self.color],
            outputs=[image, drawn],
            device=dev,
        )
        wp.synchronize_device(dev)
        seconds = time.perf_counter() - t0
        rgb8 = wp.empty((h, w, 3), dtype=wp.uint8, device=dev)
        wp.launch(self._k.to_rgb8, dim=(h, w), inputs=[image], outputs=[rgb8], device=dev)
        visible = wp.zeros(1, dtype=int, device=dev)
        wp.launch(self._k.count_positive, dim=n, inputs=[self.count], outputs=[visible], device=dev)
        per_pixel, _ = count_stats(drawn, dev)
        stats = {"pairs": pairs, "splats_per_pixel": per_pixel, "visible": int(visible.numpy()[0])}
        return Image(image, seconds, "splat", stats, rgb8_device=rgb8)
