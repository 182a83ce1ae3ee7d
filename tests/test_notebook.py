"""In a notebook (issue #56 part 4): ``Model.to_pyvista`` is the decode as ``pyvista.ImageData`` in
the header's physical frame, and ``warpgauss.render_image`` is the image ``warpgauss render``
writes, as an RGBA array."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import random_params
from PIL import Image as PILImage
from test_cli import cli
from test_region import _model as model_in_frame

import warpgauss
from warpgauss.errors import WarpgaussError
from warpgauss.format.model import Model

SHAPE = (18, 14, 10)


@pytest.fixture(scope="module")
def model() -> Model:
    return model_in_frame(random_params(np.random.default_rng(21), 120, SHAPE, log_scale=(0.0, 1.0)), SHAPE)


def test_to_pyvista_holds_the_decode_in_the_headers_frame(model):
    img = model.to_pyvista(device="cpu")
    assert tuple(img.dimensions) == SHAPE and img.active_scalars_name == "rho"
    assert img.spacing == pytest.approx((0.5, 2.0, 1.25), rel=1e-12) and img.origin == pytest.approx((-3.0, 1.0, 7.0), rel=1e-12)
    grid = model.decode(device="cpu")
    np.testing.assert_array_equal(np.asarray(img.active_scalars), grid.ravel())  # x fastest, as VTK orders points
    assert int(img.field_data["residual_applied"][0]) == 0
    # a voxel's position in the ImageData is its physical position: origin + index x spacing
    x, y, z = 7, 3, 9
    assert img.points[x + SHAPE[0] * (y + SHAPE[1] * z)] == pytest.approx([-3.0 + 0.5 * x, 1.0 + 2.0 * y, 7.0 + 1.25 * z])


def test_to_pyvista_of_a_box_at_another_resolution(model):
    box = ((4, 12), (2.5, 9), (0, 10))
    img = model.to_pyvista((16, 13, 5), box, device="cpu", normalised=True, name="v")
    assert tuple(img.dimensions) == (16, 13, 5) and img.active_scalars_name == "v"
    expect = model.decode(shape_xyz=(16, 13, 5), box=box, device="cpu", normalised=True)
    np.testing.assert_array_equal(np.asarray(img.active_scalars), expect.ravel())
    # voxel 0's centre: a quarter of a model voxel past the box's lower face along x (2 output voxels a model voxel)
    assert img.origin == pytest.approx((-3.0 + 0.5 * (4 - 0.5 + 0.25), 1.0 + 2.0 * (2.5 - 0.5 + 0.25), 7.0 + 1.25 * (0 - 0.5 + 1.0)))
    assert img.spacing == pytest.approx((0.25, 1.0, 2.5))
    with pytest.raises(WarpgaussError, match="reaches outside the model's extent"):
        model.to_pyvista(box=((0, 4), (0, 4), (0, 11)), device="cpu")


def test_render_image_is_the_png_warpgauss_render_writes(model, tmp_path):
    path = tmp_path / "m.wgs"
    model.save(path, encoding="float32")
    png = tmp_path / "m.png"
    r = cli("render", path, "-o", png, "--size", "40x28", "--azimuth", "30", "--colormap", "magma", "--device", "cpu")
    assert r.exit_code == 0, r.output
    rgba = warpgauss.render_image(path, {"azimuth": 30}, size=(40, 28), colormap="magma", device="cpu")
    assert rgba.shape == (28, 40, 4) and rgba.dtype == np.uint8
    np.testing.assert_array_equal(rgba[..., :3], np.asarray(PILImage.open(png).convert("RGB")))
    # alpha is the ray's opacity: some pixels miss the grid (0), some rays cross the field
    assert rgba[..., 3].min() == 0 and rgba[..., 3].max() > 64
    from warpgauss.render.renderers import Camera, render_model

    exact = render_model(model, Camera(azimuth=30), method="cached", device="cpu", settings=None)
    same = warpgauss.render_image(model, Camera(azimuth=30), device="cpu")
    np.testing.assert_array_equal(same, exact.rgb8(alpha=True))  # the defaults are the command line's: cached, 512x512
    other = warpgauss.render_image(model, {"azimuth": 120, "elevation": -10}, size=40, device="cpu")
    assert other.shape == (40, 40, 4) and not np.array_equal(other[:28, :40], rgba)


def test_render_image_refuses_bad_requests_in_one_line(model):
    for kwargs, says in (
        ({"camera": {"azimut": 3}}, "camera takes the fields"),
        ({"size": (3, 4, 5)}, "size must be N or (width, height)"),
        ({"size": 0}, "image size must be positive"),
        ({"method": "raytrace"}, "unknown render method"),
        ({"residual": True}, "has no residual"),
        ({"colormap": "nope"}, "unknown colormap"),
    ):
        with pytest.raises(WarpgaussError, match=says.replace("(", r"\(").replace(")", r"\)")) as e:
            warpgauss.render_image(model, device="cpu", **kwargs)
        assert "\n" not in str(e.value)
