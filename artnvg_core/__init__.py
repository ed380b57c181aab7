"""ArtNVG core: stylize 3D Gaussian Splatting scenes with a style image.

The library imports nothing from ComfyUI. Main entry points:

- :mod:`artnvg_core.scene`    -- ``GaussianScene`` (the raw Gaussians) and its validation
- :mod:`artnvg_core.formats`  -- ``load_scene`` / ``save_scene``: INRIA and compressed (PlayCanvas) PLY,
  .splat, .spz, .ksplat, splatfacto .ckpt
- :mod:`artnvg_core.cameras`  -- ``CameraSet``, camera loaders, paths, ``scene_frame``
- :mod:`artnvg_core.orbit`    -- ``orbit_cameras``: views around a scene that came without cameras
- :mod:`artnvg_core.raster`   -- ``render`` (differentiable Gaussian rasterizer); ``raster.views.render_views``
  renders every view of a set
- :mod:`artnvg_core.stylize`  -- the whole job: ``stylize_nnfm``, ``stylize_diffusion``
- :mod:`artnvg_core.cli`      -- the commands of ``python -m artnvg_core`` (docs/command_line.md)
"""

__version__ = "0.1.0"
