"""Memory limits of an encode: sizes given as text (``24GiB``), the peak device and host memory a
brick's encode needs (linear models measured on an H100), and what a device may use by default.
:func:`warpgauss.encoding.scale.plan.choose_bricks` picks a bricking from them."""

from __future__ import annotations

import os

import numpy as np

from ..errors import WarpgaussError

# Peak device memory of one brick's encode, as a linear model of its box voxels and the primitives
# it refines (own, stand-ins and frozen neighbours, about 1.5 x its share of N). Measured on an
# H100 (results/bricked/out_of_core1536_h100.json): bricks of 966M voxels and about 1.5M primitives
# peaked at 5.19 GB, 3.5 B/voxel once the per-primitive part is taken off; 5 leaves a margin (the
# error stratum added since, RefineConfig.error_share: 20 B per 4^3 brick, 0.31 B/voxel).
DEVICE_BYTES_PER_VOXEL = 5.0
DEVICE_BYTES_PER_PRIMITIVE = 1024.0
DEVICE_FIXED_BYTES = 256 * 2**20
DEVICE_MARGIN = 0.9  # the default limit: this share of the free memory
# with the volume in pinned host memory (--volume-on-host) the device holds what is kept per 4^3
# block of voxels (the sampler's strata and support, the error stratum: about 1 B a voxel, by the
# arrays' sizes) beside the model and a fixed part. Measured peak (H200, the vortex at CR 100,
# scale/volume_on_host1024_h200.json, the host run first in its process): 5.88 GB at 1024^3
# with 3,459,050 Gaussians (5.91 GB with the held anchor targets and the staged draw,
# scale/volume_on_host1024_anchors_h200.json), where the brick model's fixed part and 1 KB a primitive would say
# 4.88 GB; at 512^3 (428,872) only the in-core run's 1.42 GB is known (the pool's mark is the
# process's, see core.profiling.StageRecorder), the volume's 0.54 GB in it. The host path has its
# own, above both: 1 GiB fixed and 1,280 B a primitive (6.57 and 1.75 GB there)
# Since the int64 prefix sums of a volume past 2^31 voxels (branch h2048: the strata's, the
# support's and their counts) the per-brick arrays take 88 B by their sizes (64 B before), 1.4 B a
# voxel: 12 GB at 2048^3
HOST_VOLUME_DEVICE_BYTES_PER_VOXEL = 1.4
HOST_VOLUME_FIXED_BYTES = 2**30
HOST_VOLUME_DEVICE_BYTES_PER_PRIMITIVE = 1280.0
# Peak host memory of one brick's encode per box voxel: the source's copy and the float32 values,
# the interior/halo/validity masks and their uint8 uploads, the counting passes' temporaries on
# every thread. Measured (H100 host, 16 threads, results/bricked/out_of_core1536_rss_h100.json): boxes
# of 499M voxels peaked at 11.0 GB RSS, 22 B/voxel (the first estimate, 14, let it pass an 8 GiB limit).
HOST_BYTES_PER_VOXEL = 22.0
HOST_SHARE = 0.5  # the default host limit: this share of the memory available now

_UNITS = {"": 1, "b": 1, "k": 10**3, "kb": 10**3, "kib": 2**10, "m": 10**6, "mb": 10**6, "mib": 2**20}
_UNITS.update({"g": 10**9, "gb": 10**9, "gib": 2**30, "t": 10**12, "tb": 10**12, "tib": 2**40})


def parse_memory(text, option: str = "--max-device-memory", floor: int = DEVICE_FIXED_BYTES) -> int:
    """'24GiB', '24G', '500MB', '1e9' or a number of bytes -> bytes (more than ``floor``)."""
    if isinstance(text, (int, np.integer)):
        value = int(text)
    else:
        import re

        m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+(?:e[0-9]+)?)\s*([a-zA-Z]*)\s*", str(text))
        unit = m.group(2).lower() if m else ""
        if m is None or unit not in _UNITS:
            raise WarpgaussError(f"{option} must be a size such as 24GiB, 500MB or a number of bytes, got {text!r}")
        value = int(float(m.group(1)) * _UNITS[unit])
    if value <= floor:
        raise WarpgaussError(f"{option} {text} is too small: a brick needs more than {floor / 2**20:.0f} MiB")
    return value


def brick_device_bytes(box_voxels: int, primitives: float) -> int:
    """Estimated peak device memory of a brick's encode (see :data:`DEVICE_BYTES_PER_VOXEL`)."""
    return int(DEVICE_FIXED_BYTES + DEVICE_BYTES_PER_VOXEL * box_voxels + DEVICE_BYTES_PER_PRIMITIVE * primitives)


def host_volume_device_bytes(voxels: int, primitives: float) -> int:
    """Estimated peak device memory of a whole encode whose volume stays in host memory."""
    return int(HOST_VOLUME_FIXED_BYTES + HOST_VOLUME_DEVICE_BYTES_PER_VOXEL * voxels + HOST_VOLUME_DEVICE_BYTES_PER_PRIMITIVE * primitives)


def default_device_limit(device: str) -> int | None:
    """What a brick may use on ``device``: :data:`DEVICE_MARGIN` of its free memory (None on the CPU)."""
    from .warp import warp

    d = warp().get_device(device)
    if not d.is_cuda:
        return None
    return int(DEVICE_MARGIN * d.free_memory)


def available_memory() -> int | None:
    """Bytes of physical memory available now (Linux), or None where that cannot be read."""
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return None


def host_limit(max_host_memory) -> int | None:
    """``--max-host-memory`` in bytes (None: not given)."""
    return None if max_host_memory is None else parse_memory(max_host_memory, "--max-host-memory", 2**20)
