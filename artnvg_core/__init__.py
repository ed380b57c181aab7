"""ArtNVG core: stylize 3D Gaussian Splatting scenes with a style image.

The library imports nothing from ComfyUI. Main entry points:

- :mod:`artnvg_core.scene`    -- ``GaussianScene`` and PLY / splatfacto checkpoint I/O
- :mod:`artnvg_core.cameras`  -- ``CameraSet`` and camera loaders / paths
- :mod:`artnvg_core.raster`   -- ``render`` (differentiable Gaussian rasterizer)
"""

__version__ = "0.1.0"
