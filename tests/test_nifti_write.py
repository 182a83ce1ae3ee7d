"""NIfTI-1 output (issue #57 item 7): the readers take .nii/.nii.gz, so write_volume, `decode` and
`example` write them, and what they write reads back the same (our reader, and VTK's own reader of
the header's geometry)."""

from __future__ import annotations

import gzip
import struct

import numpy as np
import pytest
from typer.testing import CliRunner

from warpgauss.cli.main import app
from warpgauss.readers import ReadOptions, write_volume


@pytest.mark.parametrize("ext", [".nii", ".nii.gz"])
@pytest.mark.parametrize("dtype", ["uint8", "int8", "int16", "uint16", "int32", "float32", "float64"])
def test_nifti_round_trip_each_dtype(tmp_path, ext, dtype):
    rng = np.random.default_rng(3)
    a = (rng.standard_normal((5, 6, 7)) * 40 + 60).astype(dtype)  # (z, y, x): x fastest in the file
    p = write_volume(tmp_path / f"v{ext}", a, spacing=(0.5, 2.0, 3.0), origin=(1.0, -2.0, 3.5), name="density")
    r = ReadOptions().read(p)
    got = np.asarray(r.data)
    assert got.dtype == a.dtype and got.shape == a.shape and np.array_equal(got, a)
    assert tuple(r.spacing) == (0.5, 2.0, 3.0)
    raw = (gzip.open if ext == ".nii.gz" else open)(p, "rb").read()
    assert len(raw) == 352 + a.nbytes and raw[344:348] == b"n+1\0" and struct.unpack_from("<i", raw)[0] == 348
    assert struct.unpack_from("<8h", raw, 40)[:4] == (3, 7, 6, 5)
    assert struct.unpack_from("<f", raw, 108)[0] == 352.0 and struct.unpack_from("<h", raw, 72)[0] == 8 * a.itemsize
    assert raw[148:155] == b"density"


def test_vtk_reads_the_origin_from_the_qform_and_sform(tmp_path):
    from vtkmodules.vtkIOImage import vtkNIFTIImageReader

    p = write_volume(tmp_path / "v.nii.gz", np.zeros((3, 4, 5), np.float32), spacing=(0.5, 2.0, 3.0), origin=(1.0, -2.0, 3.5))
    r = vtkNIFTIImageReader()
    r.SetFileName(str(p))
    r.Update()
    assert r.GetOutput().GetDimensions() == (5, 4, 3) and r.GetOutput().GetSpacing() == (0.5, 2.0, 3.0)
    for m in (r.GetQFormMatrix(), r.GetSFormMatrix()):
        assert [m.GetElement(i, 3) for i in range(3)] == [1.0, -2.0, 3.5]
        assert [m.GetElement(i, j) for i in range(3) for j in range(3)] == [1, 0, 0, 0, 1, 0, 0, 0, 1]


def test_decode_writes_nifti_that_eval_reads_back(tmp_path, cpu):
    run = CliRunner()
    vol = tmp_path / "u8.npy"
    from warpgauss.readers.synthetic import generate

    v = generate("vortex", 16, seed=0)
    np.save(vol, np.round(255 * (v - v.min()) / (v.max() - v.min())).astype(np.uint8))
    model = tmp_path / "m.wgs"
    args = ["encode", str(vol), "--max-error", "3", "--iterations", "3", "--samples", "256", "--device", "cpu", "-o", str(model)]
    assert run.invoke(app, args).exit_code == 0
    from warpgauss.format.model import Model

    m = Model.load(model)
    out = tmp_path / "bounded.nii.gz"
    r = run.invoke(app, ["decode", str(model), "-o", str(out), "--device", "cpu"])
    assert r.exit_code == 0, r.output
    got = np.asarray(ReadOptions().read(out).data)
    assert got.dtype == np.uint8 and np.array_equal(got, m.decode(device="cpu"))  # the residual applied, the source's dtype
    assert np.abs(got.astype(int) - np.load(vol).astype(int)).max() <= 3
    alone = tmp_path / "alone.nii"
    assert run.invoke(app, ["decode", str(model), "-o", str(alone), "--no-residual", "--shape", "8x9x10"]).exit_code == 0
    got = np.asarray(ReadOptions().read(alone).data)
    assert got.shape == (10, 9, 8) and np.array_equal(got, m.decode(shape_xyz=(8, 9, 10), device="cpu", residual=False))
    r = run.invoke(app, ["eval", str(model), str(out), "--json"])  # the decode scored against itself: exact
    assert r.exit_code == 0 and '"max_abs_error_source": 0.0' in r.stdout, r.output


def test_a_grid_nifti_cannot_hold_is_refused_before_the_decode(tmp_path, monkeypatch):
    model = tmp_path / "m.wgs"
    assert (
        CliRunner()
        .invoke(app, ["encode", "--example", "vortex", "--size", "12", "--budget", "10", "--iterations", "0", "-o", str(model)])
        .exit_code
        == 0
    )
    out = tmp_path / "long.nii.gz"

    def no_decode(*args, **kwargs):
        raise AssertionError("decoded before the refusal")

    monkeypatch.setattr("warpgauss.format.model.Model.decode", no_decode)
    r = CliRunner().invoke(app, ["decode", str(model), "-o", str(out), "--shape", "40000x2x2"])
    lines = [line for line in r.stderr.splitlines() if line.strip()]
    assert r.exit_code == 2 and len(lines) == 1 and "at most 32,767 voxels an axis" in lines[0] and "Traceback" not in r.output
    assert sorted(f.name for f in tmp_path.iterdir()) == ["m.wgs", "m.wgs.report.json"]  # nothing written, no temporary left


def test_example_writes_nifti(tmp_path):
    out = tmp_path / "vortex.nii.gz"
    r = CliRunner().invoke(app, ["example", "vortex", "--size", "10", "-o", str(out)])
    assert r.exit_code == 0, r.output
    from warpgauss.readers.synthetic import generate

    assert np.array_equal(np.asarray(ReadOptions().read(out).data), generate("vortex", 10, seed=0))
