"""`.vtp` export of the primitives: read back with pyvista, compared with the model's parameters."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import uniform_params
from test_render import header
from typer.testing import CliRunner

from warpgauss.cli.main import app
from warpgauss.format.export import matrix_to_quat, primitive_arrays, quat_to_matrix, write_vtp
from warpgauss.format.model import Model


def random_model(n=50, spacing=(1.0, 1.0, 1.0), origin=(0.0, 0.0, 0.0), seed=0) -> Model:
    p = uniform_params(np.random.default_rng(seed), n, centre=(0, 15), log_scale=(-0.5, 1.0))
    h = header((16, 16, 16), spacing, origin)
    h["values"] = {"min": -3.0, "max": 5.0}
    return Model(p, h)


def covariances(rot9: np.ndarray, scale: np.ndarray) -> np.ndarray:
    r = rot9.reshape(-1, 3, 3).astype(np.float64)
    return r @ (r.transpose(0, 2, 1) * (scale.astype(np.float64) ** 2)[:, :, None])


def test_quaternion_round_trip():
    rng = np.random.default_rng(1)
    q = rng.normal(size=(500, 4))
    q[:5] = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1], [0, 0, 0, -1]]  # each Shepperd branch
    r = quat_to_matrix(q)
    np.testing.assert_allclose(r @ r.transpose(0, 2, 1), np.broadcast_to(np.eye(3), r.shape), atol=1e-12)
    np.testing.assert_allclose(quat_to_matrix(matrix_to_quat(r)), r, atol=1e-12)


@pytest.mark.parametrize("spacing", [(1.0, 1.0, 1.0), (0.5, 0.5, 0.5), (1.0, 2.0, 0.5)])
def test_vtp_reads_back_in_paraview_terms(tmp_path, spacing):
    import pyvista as pv

    model = random_model(spacing=spacing, origin=(10.0, -2.0, 3.0))
    path = tmp_path / "prims.vtp"
    assert write_vtp(model, path) == model.n
    cloud = pv.read(path)
    assert cloud.n_points == model.n
    for key, comps in (("scale", 3), ("orientation", 4), ("rotation", 9), ("value", 1), ("value_normalised", 1), ("weight", 1)):
        assert key in cloud.point_data and (cloud.point_data[key].shape[1:] or (1,))[0] == comps
    p = model.params.astype(np.float64)
    sp, org = np.asarray(spacing), np.asarray((10.0, -2.0, 3.0))
    np.testing.assert_allclose(cloud.points, org + p[:, :3] * sp, rtol=1e-6, atol=1e-5)
    # the covariance the file describes is the model's, carried into physical units
    d = np.diag(sp)
    expected = d @ covariances(quat_to_matrix(p[:, 6:10]).reshape(-1, 9), np.exp(p[:, 3:6])) @ d
    got = covariances(np.asarray(cloud.point_data["rotation"]), np.asarray(cloud.point_data["scale"]))
    np.testing.assert_allclose(got, expected, rtol=2e-5, atol=2e-5 * np.abs(expected).max())
    np.testing.assert_allclose(quat_to_matrix(cloud.point_data["orientation"]).reshape(-1, 9), cloud.point_data["rotation"], atol=1e-5)
    np.testing.assert_allclose(cloud.point_data["value"], -3.0 + 8.0 * p[:, 10], rtol=1e-6, atol=1e-5)
    np.testing.assert_allclose(cloud.point_data["value_normalised"], p[:, 10], atol=1e-7)
    np.testing.assert_allclose(cloud.point_data["weight"], p[:, 11], atol=1e-7)


def test_voxel_units_keep_the_parameters():
    model = random_model(spacing=(1.0, 2.0, 0.5))
    a = primitive_arrays(model, voxel_units=True)
    p = model.params.astype(np.float64)
    np.testing.assert_allclose(a["points"], p[:, :3])
    np.testing.assert_allclose(a["scale"], np.exp(p[:, 3:6]))
    q = p[:, 6:10] / np.linalg.norm(p[:, 6:10], axis=1, keepdims=True)
    same = np.abs(np.sum(a["orientation"] * q, axis=1))  # q and -q are the same rotation
    np.testing.assert_allclose(same, 1.0, atol=1e-9)


def test_cli_export(tmp_path):
    import pyvista as pv

    model = random_model()
    model.save(tmp_path / "m.wgs")
    runner = CliRunner()
    out = tmp_path / "p.vtp"
    r = runner.invoke(app, ["export", str(tmp_path / "m.wgs"), "-o", str(out)])
    assert r.exit_code == 0, r.output
    assert "50 points" in r.stdout and pv.read(out).n_points == 50
    for args, msg in [
        (["-o", str(out)], "already exists"),
        (["-o", str(tmp_path / "p.ply")], ".vtp"),
    ]:
        r = runner.invoke(app, ["export", str(tmp_path / "m.wgs"), *args])
        assert r.exit_code == 2 and msg in r.stderr and len(r.stderr.strip().splitlines()) == 1
    r = runner.invoke(app, ["export", str(tmp_path / "none.wgs"), "-o", str(tmp_path / "q.vtp")])
    assert r.exit_code == 2 and not (tmp_path / "q.vtp").exists()
