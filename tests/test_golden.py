"""Golden models: the bytes of every kind of ``.wgs`` and the keys of its report, against what
the code wrote when the fixture was made (``tests/golden/models.json``), so that moving code
(the driver, the encode configuration) cannot change a model unseen. CPU only, small volumes.

The bytes depend on the machine's floating point as well as on our code (Warp's CPU kernels are
compiled for the host; numpy's reductions dispatch by CPU): a machine whose refinement alone
gives other bytes than the fixture's (the ``machine`` case: a bare Refiner run, which no driver
code touches) compares report keys only and says so. Rewrite the fixture only for a change that
means to change models:

    python tests/test_golden.py --write
"""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path

import numpy as np
import pytest

FIXTURE = Path(__file__).parent / "golden" / "models.json"
FAST = dict(iterations=20, samples=256, device="cpu", self_test=False, seed=3)


def _machine() -> str:
    """The bytes of a bare refinement (no driver code): the fingerprint of this machine's arithmetic."""
    from warpgauss.encoding.refine import RefineConfig, Refiner
    from warpgauss.field.analysis import DeviceVolume, normalise
    from warpgauss.readers.synthetic import generate

    f = normalise(generate("vortex", 16))
    rng = np.random.default_rng(0)
    p = np.zeros((40, 12), np.float32)
    p[:, :3] = rng.uniform(0, 1, (40, 3)) * (np.array(f.shape_xyz) - 1)
    p[:, 3:6], p[:, 9], p[:, 10], p[:, 11] = 0.8, 1.0, 0.5, 0.5
    r = Refiner(DeviceVolume(f, "cpu"), p, RefineConfig(iterations=15, samples=256), 0, 0.3, 4.0)
    r.run()
    return hashlib.sha256(r.model_params().tobytes()).hexdigest()


def _keys(d, prefix: str = "", depth: int = 2) -> list[str]:
    out = []
    for k, v in d.items():
        out.append(prefix + k)
        if isinstance(v, dict) and depth > 1:
            out += _keys(v, prefix + k + ".", depth - 1)
    return sorted(out)


def _cases(tmp: Path) -> dict[str, tuple[bytes, dict]]:
    """Every kind of model: (file bytes, report) by case name."""
    import warpgauss
    from warpgauss.readers.synthetic import generate, generate_series
    from warpgauss.series.steps import encode_series

    vol = generate("vortex", 40)
    out: dict[str, tuple[bytes, dict]] = {}

    def one(name: str, **kw) -> None:
        path = tmp / f"{name}.wgs"
        m = warpgauss.encode(vol, output=path, **FAST, **kw)
        out[name] = (path.read_bytes(), m.report)

    one("coded_ratio", ratio=30)
    one("coded_bytes", file_bytes=6000)
    one("full_budget", budget=150, format="full")
    one("compact_budget", budget=150, format="compact")
    one("bricked", budget=150, format="full", bricks="2x1x1", halo=2)
    one("bounded", max_error_rel=0.01, budget=80)
    one("stop_rules", budget=150, format="full", target_psnr=80.0, plateau_db=0.01, preset="fast")
    ladder = warpgauss.encode_ladder(vol, budgets=[60, 120], output_pattern=str(tmp / "l_{n}.wgs"), format="full", **FAST)
    for m in ladder:
        out[f"ladder_{m.n}"] = ((tmp / f"l_{m.n}.wgs").read_bytes(), m.report)
    steps = list(generate_series("vortex", 16, 3))
    chain = encode_series(steps, budget=60, output_pattern=str(tmp / "s_{t}.wgs"), format="full", warm_iterations=10, **FAST)
    for t, m in enumerate(chain):
        out[f"series_{t}"] = ((tmp / f"s_{t}.wgs").read_bytes(), m.report)
    return out


def _record(cases: dict[str, tuple[bytes, dict]]) -> dict:
    return {name: {"sha256": hashlib.sha256(b).hexdigest(), "bytes": len(b), "report_keys": _keys(rep)} for name, (b, rep) in cases.items()}


@pytest.mark.skipif(not FIXTURE.exists(), reason="no golden fixture (python tests/test_golden.py --write)")
def test_every_kind_of_model_is_the_golden_one(tmp_path):
    want = json.loads(FIXTURE.read_text())
    got = _record(_cases(tmp_path))
    assert sorted(got) == sorted(want["cases"])
    for name, w in want["cases"].items():
        assert got[name]["report_keys"] == w["report_keys"], name
    if _machine() != want["machine"]:
        pytest.skip("this machine's refinement gives other bytes than the fixture's (report keys compared, bytes not)")
    for name, w in want["cases"].items():
        assert (got[name]["sha256"], got[name]["bytes"]) == (w["sha256"], w["bytes"]), name


if __name__ == "__main__" and "--write" in sys.argv:
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        rec = {"machine": _machine(), "cases": _record(_cases(Path(d)))}
    FIXTURE.parent.mkdir(exist_ok=True)
    FIXTURE.write_text(json.dumps(rec, indent=1) + "\n")
    print(f"wrote {FIXTURE}: {len(rec['cases'])} cases")
