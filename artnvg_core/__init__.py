"""ArtNVG core: stylize 3D Gaussian Splatting scenes with a style image.

The library imports nothing from ComfyUI. Main entry points:

- :mod:`artnvg_core.scene`    -- ``GaussianScene`` (the raw Gaussians) and its validation
- :mod:`artnvg_core.formats`  -- ``load_scene`` / ``save_scene`` (PLY, SPZ, .splat, splatfacto .ckpt)
- :mod:`artnvg_core.cameras`  -- ``CameraSet``, camera loaders, paths and rigs
- :mod:`artnvg_core.raster`   -- ``render`` (differentiable Gaussian rasterizer)
"""

__version__ = "0.1.0"
