"""Motion compensation of a warm start: the previous timestep's primitives follow the field.

A warm start from the previous model pays off only while structures stay where its primitives are:
refinement moves a primitive only as far as its own footprint sees, so an advected blob that left
its primitives behind is refitted from scratch (measured on the rotating examples, see
``benchmarks/series/README.md``). Here the previous model, decoded on the grid, is matched to the new
timestep by block Lucas-Kanade on a pyramid (``kernels/motion.py``), and each primitive's centre
moves by the displacement found there before refinement starts. Shapes, values and weights are
kept: the structure moved, it did not change.
"""

from __future__ import annotations

import numpy as np

BLOCK = 2  # voxels per block edge at the finest level
COARSE_BLOCK = 4  # and at the coarser levels
COARSEST = 16  # voxels: no level coarser than this on its shortest side
MAX_LEVELS = 5  # 512^3: levels of 512 .. 32 voxels, a capture range of about 2 x 2^4 = 32 voxels
STEPS = 8  # Gauss-Newton steps per level (3: up to 1 dB lower start on the rotating bubbles)
# learning-rate factor of the refinement that follows. Chains of 4 warm timesteps at 512^3, N 400k,
# 375 iterations (motion_sweep512_stay_h100.json), PSNR at step 4 vortex / bubbles / interface:
# x1 70.53 / 57.81 / 43.42 dB, x0.3 69.89 / 58.13 / 42.56; at 0.1 the vortex chain fell to 64.87
# (motion_sweep512_vortex2_h100.json). On 40^3 CPU fields x0.3 was 0.1-0.4 dB ahead for one step.
WARM_LR_SCALE = 1.0
TURN = True  # turn each primitive with the local rotation (half the curl) of the motion
PASSES = 2  # decode, match, move; again from the moved model (measured: +0.7 to +2.2 dB at the start)
FINEST = 0  # the finest level that is estimated (finer levels take its displacement, interpolated)
SMOOTH = 0  # extra confidence-weighted 3^3 smoothing passes of the finest blocks' displacements
LAMBDA = 1e-6  # Tikhonov floor of a block's normal matrix (besides 1e-3 of its trace)
CONF_FLOOR = 1e-6  # weight of a textureless block in the smoothing


def levels_for(shape_xyz) -> int:
    """Pyramid levels: halve while the shortest side stays >= :data:`COARSEST` voxels."""
    side, levels = min(shape_xyz), 1
    while levels < MAX_LEVELS and side / 2**levels >= COARSEST:
        levels += 1
    return levels


def decode_on_device(params: np.ndarray, shape_xyz, device: str):
    """The model's values on its grid, as a device (nz, ny, nx) float32 array (no host copy)."""
    from ..core.warp import warp
    from ..field.gaussians import DECODE_SLAB_VOXELS, GaussianField

    wp = warp()
    gf = GaussianField(params, shape_xyz, device=device)
    nx, ny, nz = (int(s) for s in shape_xyz)
    out = wp.empty((nz, ny, nx), dtype=float, device=device)
    slab = max(1, min(nz, DECODE_SLAB_VOXELS // (nx * ny)))
    one = wp.vec3(1.0, 1.0, 1.0)
    for z0 in range(0, nz, slab):
        gf.decode_slab(out[z0 : min(nz, z0 + slab)], z0, one)
    return out


def estimate_motion(ref, cur, levels: int | None = None):
    """Block displacements (a (bz, by, bx) vec3 array, voxels, blocks of :data:`BLOCK`^3) that carry
    ``ref`` onto ``cur`` (device arrays of one shape): ref(x) ~ cur(x + d(x))."""
    from ..core.warp import warp
    from ..kernels import motion as km

    wp = warp()
    dev = ref.device
    nz, ny, nx = (int(s) for s in ref.shape)
    levels = levels or levels_for((nx, ny, nz))
    pyramid = [(ref, cur)]
    for _ in range(levels - 1):
        r, c = pyramid[-1]
        shape = tuple(-(-int(s) // 2) for s in r.shape)
        rr, cc = wp.empty(shape, dtype=float, device=dev), wp.empty(shape, dtype=float, device=dev)
        wp.launch(km.downsample2, dim=shape, inputs=[r], outputs=[rr], device=dev)
        wp.launch(km.downsample2, dim=shape, inputs=[c], outputs=[cc], device=dev)
        pyramid.append((rr, cc))
    disp, prev_block = None, None
    for level in reversed(range(levels)):
        r, c = pyramid[level]
        block = BLOCK if level == 0 else COARSE_BLOCK
        blocks = tuple(-(-int(s) // block) for s in r.shape)
        start = wp.zeros(blocks, dtype=wp.vec3, device=dev)
        if disp is not None:
            wp.launch(km.upsample_blocks, dim=blocks, inputs=[disp, prev_block, block], outputs=[start], device=dev)
        disp, prev_block = start, block
        step = wp.empty(blocks, dtype=wp.vec3, device=dev)
        conf = wp.full(blocks, 1.0, dtype=float, device=dev)
        for _ in range(STEPS if level >= FINEST else 0):
            wp.launch(km.lk_step, dim=blocks, inputs=[r, c, disp, block, LAMBDA], outputs=[step, conf], device=dev)
            wp.launch(km.smooth_blocks, dim=blocks, inputs=[step, conf, CONF_FLOOR], outputs=[disp], device=dev)
    assert disp is not None  # levels >= 1: the loop ran
    for _ in range(SMOOTH):
        wp.launch(km.smooth_blocks, dim=disp.shape, inputs=[disp, conf, CONF_FLOOR], outputs=[step], device=dev)
        disp, step = step, disp
    return disp


def compensate(params: np.ndarray, dv, levels: int | None = None) -> tuple[np.ndarray, dict]:
    """The previous model's parameters with every centre moved by the motion from the previous
    model (decoded) to the new timestep ``dv`` (:class:`warpgauss.field.analysis.DeviceVolume`).

    Returns:
        (parameters, facts for the report: levels, blocks, mean and largest move in voxels)
    """
    from ..core.warp import warp
    from ..kernels import motion as km

    wp = warp()
    dev = dv.device
    shape_xyz = dv.field.shape_xyz
    levels = levels or levels_for(shape_xyz)
    p = wp.array(np.ascontiguousarray(params, np.float32), dtype=float, device=dev)
    moved = wp.empty(p.shape[0], dtype=float, device=dev)
    total = np.zeros(p.shape[0], np.float64)
    stayed = np.zeros(p.shape[0], bool)
    size = wp.vec3(*(float(s) for s in shape_xyz))
    for _ in range(PASSES):  # each pass matches the model as moved so far
        ref = decode_on_device(p.numpy(), shape_xyz, dev)
        disp = estimate_motion(ref, dv.values, levels)
        wp.launch(km.shift_centres, dim=p.shape[0], inputs=[p, disp, BLOCK, size, int(TURN)], outputs=[moved], device=dev)
        mv = moved.numpy()
        stayed |= mv < 0.0
        total += np.maximum(mv, 0.0)
    m = total
    facts = {
        "levels": levels,
        "block": BLOCK,
        "blocks": list(disp.shape),
        "passes": PASSES,
        "mean_move_voxels": float(m.mean()) if m.size else 0.0,
        "max_move_voxels": float(m.max()) if m.size else 0.0,
        "stayed_at_edge": int(stayed.sum()),  # primitives the motion would have carried out of the grid
    }
    return p.numpy(), facts
