"""Each script in examples/ runs end to end with tiny CPU options (as Warp's test_examples does)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
DATA = Path(__file__).resolve().parents[2] / "shared" / "data"

CASES = {
    "encode_example.py": ["--size", "24", "--budget", "300", "--field", "bubbles", "--iterations", "20"],
    "encode_real_volume.py": ["--file", "nAChR_M2_water.plt", "--ratio", "8", "--stride", "2", "--iterations", "20"],
    "insitu_smoke.py": ["--size", "24", "--steps", "24", "--every", "12", "--jacobi", "4", "--share", "20", "--budget", "80"],
}


@pytest.mark.parametrize("script", sorted(CASES))
def test_example_runs(script):
    cmd = [sys.executable, str(EXAMPLES / script), "--device", "cpu", "--headless", *CASES[script]]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr[-2000:]
    if script == "encode_real_volume.py" and not DATA.exists():
        assert "skipped" in p.stdout
    else:
        assert "PSNR" in p.stdout and "dB" in p.stdout


def test_every_example_is_smoke_tested():
    assert sorted(p.name for p in EXAMPLES.glob("*.py")) == sorted(CASES)
