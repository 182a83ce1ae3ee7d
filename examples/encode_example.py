# SPDX-License-Identifier: Apache-2.0
###########################################################################
# Example: encode a built-in volume
#
# Generates one of the built-in example fields (vortex, bubbles, turbulence,
# interface), encodes it into a fixed budget of anisotropic Gaussians with
# the Python API, writes the .wgs model, loads it back, decodes it to a grid
# and reports PSNR, bytes and compression ratio.
#
#   python examples/encode_example.py --field vortex --size 64 --budget 4000 --iterations 300
###########################################################################

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

import warpgauss
from warpgauss.readers.synthetic import generate


class Example:
    def __init__(self, field: str = "vortex", size: int = 64, budget: int = 4000, device: str | None = None, iterations: int = 300):
        self.volume = generate(field, size, seed=0)  # (nz, ny, nx) float32
        self.budget = budget
        self.device = device
        self.iterations = iterations
        self.model: warpgauss.Model | None = None

    def step(self, out_dir: Path) -> dict:
        """Encode, save, reload, decode, evaluate."""
        self.model = warpgauss.encode(self.volume, budget=self.budget, device=self.device, seed=0, iterations=self.iterations)
        path = out_dir / "model.wgs"
        size = self.model.save(path, force=True)
        loaded = warpgauss.Model.load(path)
        assert np.array_equal(loaded.params, self.model.params)
        decoded = loaded.decode(device=self.device)  # original units, (nz, ny, nx)
        an = self.model.report["evaluation"]["analytic"]["psnr_db"]
        return {
            "analytic_psnr_db": an,
            "n": loaded.n,
            "bytes": size,
            "compression_ratio": self.volume.nbytes / size,
            "psnr_db": warpgauss.psnr(loaded, self.volume, device=self.device),
            "decoded_shape": decoded.shape,
        }


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--device", default=None, help="Warp device (default: CUDA if present)")
    parser.add_argument("--field", default="vortex", help="vortex, bubbles, turbulence or interface")
    parser.add_argument("--size", type=int, default=64)
    parser.add_argument("--budget", type=int, default=4000)
    parser.add_argument("--iterations", type=int, default=300, help="Refinement iterations (0: analytic)")
    parser.add_argument("--headless", action="store_true", help="No interactive output (nothing is shown anyway)")
    args = parser.parse_args(argv)
    example = Example(args.field, args.size, args.budget, args.device, args.iterations)
    with tempfile.TemporaryDirectory() as tmp:
        result = example.step(Path(tmp))
    print(
        f"{args.field} {args.size}^3: {result['n']} Gaussians, {result['bytes']} bytes, "
        f"CR {result['compression_ratio']:.1f}x, PSNR {result['analytic_psnr_db']:.2f} dB analytic -> "
        f"{result['psnr_db']:.2f} dB refined"
    )
    return result


if __name__ == "__main__":
    main()
