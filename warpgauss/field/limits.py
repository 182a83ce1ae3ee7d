"""How many voxels an encode indexes: :data:`MAX_VOXELS` with the volume on the device (in core),
:data:`MAX_HOST_VOXELS` with it in host memory (``--volume-on-host``), and the one-line refusal
that names the way out (:func:`voxels_problem`). Plain Python: a request is refused before Warp
is imported."""

from __future__ import annotations

MAX_VOXELS = 2**31 - 1  # a volume on the device (in core): some of its kernels index voxels with int32
# a volume in host memory (DeviceVolume(on_host=True), --volume-on-host): the kernels that read it
# index voxels in int64 and 4^3 bricks in int (kernels.indexing), so fewer than 2^31 bricks (2^37
# voxels: 512 GiB of float32, beyond any host this runs on); and Warp's array strides are int32,
# so a z slice of float32 values must take less than 2 GiB (MAX_SLICE_VOXELS)
MAX_HOST_VOXELS = 64 * (2**31 - 1)  # about 2^37
MAX_SLICE_VOXELS = (2**31 - 1) // 4


def voxels_problem(shape, max_voxels: int | None = None) -> str | None:
    """Why a volume of ``shape`` (z, y, x) is too large for an encode that indexes at most
    ``max_voxels`` voxels (None: :data:`MAX_VOXELS`, in core; :data:`MAX_HOST_VOXELS` with the
    volume in host memory), or None; a one-line refusal that names the way out. The limits are
    read when called (a test lowers them)."""
    nz, ny, nx = (int(v) for v in shape)
    voxels = nz * ny * nx
    max_voxels = MAX_VOXELS if max_voxels is None else int(max_voxels)
    host = max_voxels > MAX_VOXELS
    if voxels > max_voxels:
        if host:
            return f"the volume has {voxels:,} voxels, more than the {max_voxels:,} an encode with the volume in host memory indexes; use --bricks or --stride 2"
        return (
            f"the volume has {voxels:,} voxels, more than the {max_voxels:,} an encode with the volume on the device indexes; "
            f"use --volume-on-host (on a GPU, up to {MAX_HOST_VOXELS:,} voxels), --bricks or --stride 2"
        )
    if ny * nx > MAX_SLICE_VOXELS:
        return f"a z slice of {nx}x{ny} voxels is more than the {MAX_SLICE_VOXELS:,} a Warp array's int32 strides address; use --bricks or --stride 2"
    bricks = -(-nz // 4) * -(-ny // 4) * -(-nx // 4)
    if bricks > 2**31 - 1:  # the sampler's per-brick tables are Warp arrays of one dimension
        return f"the volume's {nx}x{ny}x{nz} grid has {bricks:,} 4^3 bricks, more than the sampler indexes; use --bricks or --stride 2"
    return None
