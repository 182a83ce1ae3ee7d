"""One model refined on several devices (:mod:`warpgauss.encoding.refine.replicas`): the pair
gradients of the replicas' samples combined into one, and the error maps' counts summed.

Every replica computes the same combination of the same arrays in the same order (the primary's
term first), so the replicas' parameters stay equal bit for bit without a broadcast.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.kernel
def mix_pair_grads(
    a_mu: wp.array(dtype=wp.vec3),  # [N] the first term's pair gradients (slot order)
    a_ls: wp.array(dtype=wp.vec3),
    a_rot: wp.array(dtype=wp.mat33),
    a_a: wp.array(dtype=float),
    a_w: wp.array(dtype=float),
    b_mu: wp.array(dtype=wp.vec3),  # [N] the second term's
    b_ls: wp.array(dtype=wp.vec3),
    b_rot: wp.array(dtype=wp.mat33),
    b_a: wp.array(dtype=float),
    b_w: wp.array(dtype=float),
    wa: float,
    wb: float,
    o_mu: wp.array(dtype=wp.vec3),  # [N] out: wa a + wb b (may be either input)
    o_ls: wp.array(dtype=wp.vec3),
    o_rot: wp.array(dtype=wp.mat33),
    o_a: wp.array(dtype=float),
    o_w: wp.array(dtype=float),
):
    """``wa a + wb b`` of every pair-gradient buffer, slot by slot (one thread a slot). A slot
    neither side touched stays exactly zero, so the sparse update skips it as before."""
    j = wp.tid()
    o_mu[j] = wa * a_mu[j] + wb * b_mu[j]
    o_ls[j] = wa * a_ls[j] + wb * b_ls[j]
    o_rot[j] = wa * a_rot[j] + wb * b_rot[j]
    o_a[j] = wa * a_a[j] + wb * b_a[j]
    o_w[j] = wa * a_w[j] + wb * b_w[j]


@wp.kernel
def add_counts(acc: wp.array(dtype=wp.int64), other: wp.array(dtype=wp.int64)):
    """``acc += other`` (the error maps' fixed-point sums: integers, so any order gives the same)."""
    i = wp.tid()
    acc[i] = acc[i] + other[i]
