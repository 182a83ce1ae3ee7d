"""Files that cannot hurt: a model file is refused, in one line and before any large allocation,
when what it claims cannot fit in its own size (a decompression bomb)."""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys
import time
import zlib

import numpy as np
import pytest

import warpgauss
from warpgauss.errors import WarpgaussError
from warpgauss.format.wgs import MAGIC, PREFIX, PREFIX_SIZE
from warpgauss.readers.synthetic import generate

BOMB_N = 30_000_000


def _zeros_frame(raw: int) -> bytes:
    """A Zstandard frame of ``raw`` zero bytes (its size pledged), made without holding them."""
    import zstandard

    c = zstandard.ZstdCompressor(level=3, write_checksum=True).compressobj(size=raw)
    chunk = bytes(1 << 20)
    out = []
    left = raw
    while left:
        k = min(left, len(chunk))
        out.append(c.compress(chunk[:k]))
        left -= k
    out.append(c.flush())
    return b"".join(out)


def _bomb(real: bytes, n: int) -> bytes:
    """A coded .wgs with a consistent header and checksums whose payload is a frame of zeros
    claiming ``n`` primitives (a real coded file's header, edited)."""
    _, version, hlen, _ = PREFIX.unpack(real[:PREFIX_SIZE])  # the real file's version (its layout's)
    header = json.loads(real[PREFIX_SIZE : PREFIX_SIZE + hlen])
    quant = header["payload"]["quant"]
    quant["columns"] = [[0, 1] for _ in quant["columns"]]
    quant["raw_bytes"] = len(quant["columns"]) * n
    payload = _zeros_frame(quant["raw_bytes"])
    header["n"] = n
    header["payload"]["payload_bytes"] = len(payload)
    header["payload"]["sha256"] = hashlib.sha256(payload).hexdigest()
    area = json.dumps(header).encode()
    return PREFIX.pack(MAGIC, version, len(area), zlib.crc32(area)) + area + payload


@pytest.fixture(scope="module")
def bomb(tmp_path_factory):
    d = tmp_path_factory.mktemp("crafted")
    real = d / "real.wgs"
    warpgauss.encode(generate("vortex", 16), budget=60, iterations=3, samples=64, device="cpu", self_test=False, output=real)
    path = d / "bomb.wgs"
    path.write_bytes(_bomb(real.read_bytes(), BOMB_N))
    return real, path


def test_a_crafted_coded_file_claiming_millions_is_refused_at_once(bomb):
    real, path = bomb
    assert path.stat().st_size < 64_000  # a 30-million-Gaussian claim in tens of kilobytes
    t = time.perf_counter()
    with pytest.raises(WarpgaussError, match=r"claims 30,000,000 primitives .* the file is damaged or crafted"):
        warpgauss.Model.load(path)
    assert time.perf_counter() - t < 1.0
    assert warpgauss.Model.load(real).n == 60  # the real file it was made from still loads


@pytest.mark.parametrize("command", ["info", "decode"])
def test_the_command_line_refuses_it_in_one_line_under_a_memory_limit(bomb, tmp_path, command):
    """Under a 3 GiB address-space limit (the bomb would need about 10 GB), exit 2, one line,
    no output file."""
    pytest.importorskip("resource")
    _, path = bomb
    out = tmp_path / "d.npy"
    args = [str(path)] + (["-o", str(out)] if command == "decode" else [])
    code = (
        "import resource, sys; resource.setrlimit(resource.RLIMIT_AS, (3 << 30, resource.getrlimit(resource.RLIMIT_AS)[1])); "
        "from warpgauss.cli.main import run; sys.argv = ['warpgauss', *sys.argv[1:]]; run()"
    )
    t = time.perf_counter()
    r = subprocess.run([sys.executable, "-c", code, command, *args], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2, (r.stdout, r.stderr)
    lines = [ln for ln in r.stderr.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and "claims 30,000,000 primitives" in lines[0] and "Traceback" not in r.stderr
    assert not out.exists()
    assert time.perf_counter() - t < 60


def test_parameters_that_code_below_the_floor_are_not_written(tmp_path):
    """No coded file is written that the reader would refuse: 20,000 copies of one primitive."""
    m = warpgauss.encode(generate("vortex", 16), budget=20, iterations=0, device="cpu", self_test=False, format="full")
    twins = warpgauss.Model(np.tile(m.params[:1], (20_000, 1)), m.header)
    with pytest.raises(WarpgaussError, match="save them with --format full"):
        twins.save(tmp_path / "t.wgs", encoding="coded")
    assert not (tmp_path / "t.wgs").exists()
    twins.save(tmp_path / "t.wgs", encoding="full")
    assert warpgauss.Model.load(tmp_path / "t.wgs").n == 20_000


def _with_header(real: bytes, edit) -> bytes:
    """A real file with its header edited (and its checksum made right again)."""
    _, version, hlen, _ = PREFIX.unpack(real[:PREFIX_SIZE])
    header = json.loads(real[PREFIX_SIZE : PREFIX_SIZE + hlen])
    edit(header)
    area = json.dumps(header).encode()
    return PREFIX.pack(MAGIC, version, len(area), zlib.crc32(area)) + area + real[PREFIX_SIZE + hlen :]


@pytest.mark.parametrize("spacing", [[0.0, 1.0, 1.0], [1.0, -0.5, 1.0]])
def test_a_header_with_a_spacing_of_zero_or_below_is_refused(bomb, tmp_path, spacing):
    """Checksums prove a file is as written, not that its fields make sense: a spacing that is 0
    or negative loaded and decoded before."""
    real, _ = bomb
    path = tmp_path / "s.wgs"
    path.write_bytes(_with_header(real.read_bytes(), lambda h: h["grid"].update(spacing=spacing)))
    with pytest.raises(WarpgaussError, match="grid spacing .* is not three positive numbers"):
        warpgauss.Model.load(path)


def test_info_reads_the_header_only_and_verify_reads_the_payload(bomb, tmp_path):
    """`warpgauss info` answers from the validated header (a flipped payload byte goes unseen),
    `info --verify` reads the payload and finds it."""
    from typer.testing import CliRunner

    from warpgauss.cli.main import app

    real, _ = bomb
    data = bytearray(real.read_bytes())
    data[-5] ^= 0x20
    path = tmp_path / "flipped.wgs"
    path.write_bytes(bytes(data))
    res = CliRunner().invoke(app, ["info", str(path), "--json"])
    assert res.exit_code == 0 and json.loads(res.stdout)["n"] == 60
    res = CliRunner().invoke(app, ["info", str(path), "--verify"])
    assert res.exit_code == 2 and "payload checksum mismatch" in res.output


def test_a_loaded_model_has_no_run_report_and_says_where_it_is(bomb):
    real, _ = bomb
    m = warpgauss.Model.load(real)
    assert m.report is None
    with pytest.raises(WarpgaussError, match=r"no run report: it was loaded from a file \(its report is the .report.json beside it\)"):
        _ = m.run_report


@pytest.mark.slow
def test_a_real_model_of_the_same_n_passes_under_that_limit(bomb, tmp_path):
    """The other half of the limit test: a coded file that really holds 30 million Gaussians (about
    a quarter of a gigabyte) is answered under the same 3 GiB address-space limit that refuses the
    bomb: the limit catches the claim, not a large model (info reads the header)."""
    pytest.importorskip("resource")
    from conftest import uniform_params

    real, _ = bomb
    p = uniform_params(np.random.default_rng(0), BOMB_N, centre=(0.0, 16.0), log_scale=(-1.0, 1.0), weight=(0.01, 1.0))
    big = tmp_path / "big.wgs"
    warpgauss.Model(p, warpgauss.Model.load(real).header).save(big, encoding="coded")
    del p
    assert big.stat().st_size > 100 * 2**20
    code = (
        "import resource, sys; resource.setrlimit(resource.RLIMIT_AS, (3 << 30, resource.getrlimit(resource.RLIMIT_AS)[1])); "
        "from warpgauss.cli.main import run; sys.argv = ['warpgauss', *sys.argv[1:]]; run()"
    )
    r = subprocess.run([sys.executable, "-c", code, "info", str(big), "--json"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["n"] == BOMB_N
