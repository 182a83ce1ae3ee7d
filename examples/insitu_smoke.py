# SPDX-License-Identifier: Apache-2.0
###########################################################################
# Example: in situ encoding beside a running simulation
#
# A small 3D smoke solver written with Warp (semi-Lagrangian advection of
# velocity and density, buoyancy, a swirling source, a Jacobi pressure
# projection) encodes its density every --every steps with a
# warpgauss.Encoder, straight from the solver's device array (no host copy),
# each call bounded by a time budget of --share of the simulation time since
# the last encode. Each timestep starts from the previous model (a warm
# start at the same N). It prints the PSNR of every encoded step and the
# measured overhead: encoding time over the simulation's own run time.
#
# The solver's kernels are the user's side of the coupling, so they live
# here, not in warpgauss.kernels.
#
#   python examples/insitu_smoke.py --size 256 --steps 1200 --every 200 --share 0.05
###########################################################################

from __future__ import annotations

import argparse
import json
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import warp as wp

import warpgauss


@wp.func
def sample(f: wp.array3d(dtype=Any), p: wp.vec3):
    """Trilinear value at p (x, y, z in cells), edges held (scalars or vectors)."""
    nz, ny, nx = f.shape[0], f.shape[1], f.shape[2]
    x = wp.clamp(p[0], 0.0, float(nx - 1))
    y = wp.clamp(p[1], 0.0, float(ny - 1))
    z = wp.clamp(p[2], 0.0, float(nz - 1))
    i0, j0, k0 = wp.min(int(x), nx - 2), wp.min(int(y), ny - 2), wp.min(int(z), nz - 2)
    fx, fy, fz = x - float(i0), y - float(j0), z - float(k0)
    c00 = wp.lerp(f[k0, j0, i0], f[k0, j0, i0 + 1], fx)
    c01 = wp.lerp(f[k0, j0 + 1, i0], f[k0, j0 + 1, i0 + 1], fx)
    c10 = wp.lerp(f[k0 + 1, j0, i0], f[k0 + 1, j0, i0 + 1], fx)
    c11 = wp.lerp(f[k0 + 1, j0 + 1, i0], f[k0 + 1, j0 + 1, i0 + 1], fx)
    return wp.lerp(wp.lerp(c00, c01, fy), wp.lerp(c10, c11, fy), fz)


@wp.kernel
def advect(
    vel: wp.array3d(dtype=wp.vec3),
    dens: wp.array3d(dtype=float),
    dt: float,
    decay: float,
    vel_out: wp.array3d(dtype=wp.vec3),
    dens_out: wp.array3d(dtype=float),
):
    k, j, i = wp.tid()
    p = wp.vec3(float(i), float(j), float(k))
    back = p - dt * vel[k, j, i]
    vel_out[k, j, i] = sample(vel, back)
    dens_out[k, j, i] = decay * sample(dens, back)


@wp.kernel
def forces(
    vel: wp.array3d(dtype=wp.vec3),
    dens: wp.array3d(dtype=float),
    dt: float,
    buoyancy: float,
    source: wp.vec3,
    radius: float,
    inflow: wp.vec3,
):
    k, j, i = wp.tid()
    p = wp.vec3(float(i), float(j), float(k))
    v = vel[k, j, i] + wp.vec3(0.0, 0.0, dt * buoyancy * dens[k, j, i])
    if wp.length(p - source) < radius:
        dens[k, j, i] = 1.0
        v = inflow
    vel[k, j, i] = v


@wp.kernel
def divergence(vel: wp.array3d(dtype=wp.vec3), div: wp.array3d(dtype=float)):
    k, j, i = wp.tid()
    nz, ny, nx = vel.shape[0], vel.shape[1], vel.shape[2]
    # zero normal velocity outside the box (closed walls)
    xp = wp.where(i + 1 < nx, vel[k, j, wp.min(i + 1, nx - 1)][0], 0.0)
    xm = wp.where(i > 0, vel[k, j, wp.max(i - 1, 0)][0], 0.0)
    yp = wp.where(j + 1 < ny, vel[k, wp.min(j + 1, ny - 1), i][1], 0.0)
    ym = wp.where(j > 0, vel[k, wp.max(j - 1, 0), i][1], 0.0)
    zp = wp.where(k + 1 < nz, vel[wp.min(k + 1, nz - 1), j, i][2], 0.0)
    zm = wp.where(k > 0, vel[wp.max(k - 1, 0), j, i][2], 0.0)
    div[k, j, i] = 0.5 * (xp - xm + yp - ym + zp - zm)


@wp.kernel
def jacobi(p: wp.array3d(dtype=float), div: wp.array3d(dtype=float), p_out: wp.array3d(dtype=float)):
    k, j, i = wp.tid()
    nz, ny, nx = p.shape[0], p.shape[1], p.shape[2]
    s = p[k, j, wp.min(i + 1, nx - 1)] + p[k, j, wp.max(i - 1, 0)]
    s += p[k, wp.min(j + 1, ny - 1), i] + p[k, wp.max(j - 1, 0), i]
    s += p[wp.min(k + 1, nz - 1), j, i] + p[wp.max(k - 1, 0), j, i]
    p_out[k, j, i] = (s - div[k, j, i]) / 6.0


@wp.kernel
def project(vel: wp.array3d(dtype=wp.vec3), p: wp.array3d(dtype=float)):
    k, j, i = wp.tid()
    nz, ny, nx = p.shape[0], p.shape[1], p.shape[2]
    g = wp.vec3(
        p[k, j, wp.min(i + 1, nx - 1)] - p[k, j, wp.max(i - 1, 0)],
        p[k, wp.min(j + 1, ny - 1), i] - p[k, wp.max(j - 1, 0), i],
        p[wp.min(k + 1, nz - 1), j, i] - p[wp.max(k - 1, 0), j, i],
    )
    vel[k, j, i] = vel[k, j, i] - 0.5 * g


class Smoke:
    """A buoyant plume from a source that circles near the floor of an n^3 box."""

    def __init__(self, n: int, device: str, jacobi_iterations: int = 60):
        self.n, self.device, self.jacobi_iterations = n, device, jacobi_iterations
        shape = (n, n, n)
        self.vel = wp.zeros(shape, dtype=wp.vec3, device=device)
        self.vel_tmp = wp.zeros_like(self.vel)
        self.dens = wp.zeros(shape, dtype=float, device=device)
        self.dens_tmp = wp.zeros_like(self.dens)
        self.p = wp.zeros(shape, dtype=float, device=device)
        self.p_tmp = wp.zeros_like(self.p)
        self.div = wp.zeros_like(self.p)
        self.t = 0

    def step(self, dt: float = 1.0) -> None:
        import math

        n, dev, shape = self.n, self.device, self.dens.shape
        wp.launch(advect, dim=shape, inputs=[self.vel, self.dens, dt, 0.999], outputs=[self.vel_tmp, self.dens_tmp], device=dev)
        self.vel, self.vel_tmp = self.vel_tmp, self.vel
        self.dens, self.dens_tmp = self.dens_tmp, self.dens
        a = 0.02 * self.t
        source = wp.vec3(n * (0.5 + 0.2 * math.cos(a)), n * (0.5 + 0.2 * math.sin(a)), 0.12 * n)
        inflow = wp.vec3(-0.6 * math.sin(a), 0.6 * math.cos(a), 1.0)
        wp.launch(forces, dim=shape, inputs=[self.vel, self.dens, dt, 0.05, source, 0.06 * n, inflow], device=dev)
        wp.launch(divergence, dim=shape, inputs=[self.vel], outputs=[self.div], device=dev)
        for _ in range(self.jacobi_iterations):
            wp.launch(jacobi, dim=shape, inputs=[self.p, self.div], outputs=[self.p_tmp], device=dev)
            self.p, self.p_tmp = self.p_tmp, self.p
        wp.launch(project, dim=shape, inputs=[self.vel, self.p], device=dev)
        self.t += 1


class Example:
    def __init__(self, size=64, steps=240, every=60, share=0.05, budget=None, device=None, out=None, fmt="float32", jacobi_iterations=60):
        self.device = str(wp.get_device(device))
        self.sim = Smoke(size, self.device, jacobi_iterations)
        self.steps, self.every, self.share, self.out = steps, every, share, out
        budget = budget or max(100, size**3 // 300)  # one Gaussian per 300 voxels
        self.encoder = warpgauss.Encoder(budget=budget, format=fmt, device=self.device)
        self.sim_seconds = 0.0
        self.encode_seconds = 0.0
        self.records: list[dict] = []

    def _timed_steps(self, k: int) -> float:
        wp.synchronize_device(self.device)
        t0 = time.perf_counter()
        for _ in range(k):
            self.sim.step()
        wp.synchronize_device(self.device)
        return time.perf_counter() - t0

    def run(self) -> dict:
        self.encoder.prepare()  # compile (or load) the encoder's kernels before the run
        self._timed_steps(2)  # and the solver's
        done = 0
        while done < self.steps:
            k = min(self.every, self.steps - done)
            seconds = self._timed_steps(k)
            self.sim_seconds += seconds
            done += k
            if k < self.every:
                break
            budget = self.share * seconds  # the share of the simulation time since the last encode
            out = None if self.out is None else Path(self.out) / f"density_{done:05d}.wgs"
            t0 = time.perf_counter()
            m = self.encoder.encode(self.sim.dens, time_budget=budget, output=out, force=True)
            spent = time.perf_counter() - t0
            self.encode_seconds += spent
            rec = {
                "step": done,
                "psnr_db": m.report["psnr_db"],
                "warm_start": m.report["encoder"]["warm_start"],
                "iterations": m.report["encoder"]["iterations"],
                "time_budget_s": budget,
                "encode_s": spent,
                "simulation_s": seconds,
            }
            self.records.append(rec)
            print(
                f"step {done:6d}: PSNR {rec['psnr_db']:.2f} dB, {rec['iterations']} iterations "
                f"({'warm' if rec['warm_start'] else 'cold'}), {spent:.3f} s of a {budget:.3f} s budget"
            )
        overhead = self.encode_seconds / self.sim_seconds
        per_step = 1000 * self.sim_seconds / max(self.steps, 1)
        print(
            f"simulation {self.sim_seconds:.2f} s ({per_step:.1f} ms/step), encoding {self.encode_seconds:.2f} s: overhead {100 * overhead:.1f} %"
        )
        return {
            "size": self.sim.n,
            "steps": self.steps,
            "every": self.every,
            "share": self.share,
            "budget_n": self.encoder.previous.n if self.encoder.previous else None,
            "simulation_seconds": self.sim_seconds,
            "ms_per_step": per_step,
            "device": self.device,
            "device_name": wp.get_device(self.device).name,
            "warp_version": wp.config.version,
            "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "encode_seconds": self.encode_seconds,
            "overhead": overhead,
            "encodes": self.records,
        }


if __name__ == "__main__":
    parser = argparse.ArgumentParser(formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--device", type=str, default=None, help="Override the default Warp device.")
    parser.add_argument("--size", type=int, default=64, help="Grid cells per axis.")
    parser.add_argument("--steps", type=int, default=240, help="Simulation steps.")
    parser.add_argument("--every", type=int, default=60, help="Encode every this many steps.")
    parser.add_argument("--share", type=float, default=0.05, help="Share of the simulation time an encode may take.")
    parser.add_argument("--budget", type=int, default=None, help="Gaussians per timestep (default: one per 300 voxels).")
    parser.add_argument("--jacobi", type=int, default=60, help="Pressure iterations per step.")
    parser.add_argument("--format", type=str, default="float32", help="Model file format.")
    parser.add_argument("--out", type=str, default=None, help="Write each model into this folder.")
    parser.add_argument("--json", type=str, default=None, help="Write the figures here.")
    parser.add_argument("--headless", action="store_true", help="No display (kept for the examples' common options).")
    args = parser.parse_known_args()[0]

    with wp.ScopedDevice(args.device):
        example = Example(args.size, args.steps, args.every, args.share, args.budget, args.device, args.out, args.format, args.jacobi)
        result = example.run()
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2))
