"""Rendering a model: the scene, camera and ray-marching core every renderer shares
(:mod:`.raymarch`), the renderers and ``render_image`` (:mod:`.renderers`), EWA splatting
(:mod:`.splat`), transfer functions (:mod:`.transfer`), and what ``warpgauss serve`` shows
(:mod:`.viewer`) and serves (:mod:`.serve`, the trame page).

    from warpgauss.render import Camera, RenderSettings, render_model
    img = render_model(model, Camera(azimuth=30, elevation=20), settings=RenderSettings(width=512))

A new renderer is a class in :mod:`.renderers` (or a module of its own here) with the
``render(camera) -> Image`` of the others, named in :data:`METHODS` and :func:`make_renderer`.
"""

from ..core.moved import forward
from .raymarch import Camera, Image, RenderSettings, Scene, View, resolve_view
from .renderers import (
    METHODS,
    BoundedRenderer,
    CachedRenderer,
    ModelRenderer,
    VolumeRenderer,
    image_psnr,
    image_ssim,
    make_renderer,
    render_image,
    render_model,
    save_png,
    side_by_side,
    with_settings,
)
from .transfer import TransferFunction, make_transfer_function

__all__ = [
    "METHODS",
    "BoundedRenderer",
    "CachedRenderer",
    "Camera",
    "Image",
    "ModelRenderer",
    "RenderSettings",
    "Scene",
    "TransferFunction",
    "View",
    "VolumeRenderer",
    "image_psnr",
    "image_ssim",
    "make_renderer",
    "make_transfer_function",
    "render_image",
    "render_model",
    "resolve_view",
    "save_png",
    "side_by_side",
    "with_settings",
]

# warpgauss.render was one module (now .renderers): its other names still read, with a warning
__getattr__ = forward(__name__, f"{__name__}.renderers")
