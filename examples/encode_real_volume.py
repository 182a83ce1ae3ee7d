# SPDX-License-Identifier: Apache-2.0
###########################################################################
# Example: encode a real volume from ../shared/data
#
# Encodes a real scan (by default the MNI ICBM152 T1 brain template, uint8
# NIfTI) at a target compression ratio, reports the structure statistics,
# PSNR and the stage timings, and decodes the model to a .vti file that
# ParaView opens. Skips cleanly when the data folder is not present.
#
#   python examples/encode_real_volume.py --ratio 200
###########################################################################

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import warpgauss

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
DEFAULT = "mni_icbm152_t1_tal_nlin_sym_09a_converted.nii.gz"


class Example:
    def __init__(self, path: Path, ratio: float, stride: int, device: str | None, iterations: int = 300):
        self.path, self.ratio, self.stride, self.device = path, ratio, stride, device
        self.iterations = iterations

    def step(self, out_dir: Path) -> dict:
        from warpgauss.readers import ReadOptions, write_volume

        model = warpgauss.encode(
            self.path,
            ratio=self.ratio,
            device=self.device,
            iterations=self.iterations,
            read=ReadOptions(stride=self.stride),
            output=out_dir / "scan.wgs",
        )
        rep = model.report
        decoded = model.decode(device=self.device)
        write_volume(out_dir / "scan_decoded.vti", decoded, spacing=model.decoded_spacing(), origin=model.decoded_origin())
        return rep


def main(argv=None) -> dict | None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--device", default=None)
    parser.add_argument("--file", default=DEFAULT, help=f"a file in {DATA}")
    parser.add_argument("--ratio", type=float, default=200.0)
    parser.add_argument("--stride", type=int, default=1)
    parser.add_argument("--iterations", type=int, default=300, help="Refinement iterations (0: analytic)")
    parser.add_argument("--headless", action="store_true")
    args = parser.parse_args(argv)
    path = DATA / args.file
    if not path.exists():
        print(f"skipped: {path} is not here (the real volumes live in ../shared/data)")
        return None
    with tempfile.TemporaryDirectory() as tmp:
        rep = Example(path, args.ratio, args.stride, args.device, args.iterations).step(Path(tmp))
    s, b, ev = rep["structure"], rep["budget"], rep["evaluation"]["final"]
    print(
        f"{args.file}: {'x'.join(map(str, rep['input']['shape_xyz']))} {rep['input']['source_dtype']}, "
        f"occupancy {100 * s['occupancy']:.1f} %, grad top-10 % {100 * s['grad_top10']:.1f} %, S1/S16 {s['s1_s16']:.3f}"
    )
    print(f"{b['n']} Gaussians, {b['bytes']} bytes, CR {b['compression_ratio']:.1f}x, PSNR {ev['psnr_db']:.2f} dB")
    return rep


if __name__ == "__main__":
    main()
