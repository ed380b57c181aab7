"""The commands of ``python -m artnvg_core`` (docs/command_line.md): the top wing of the library,
imported by nothing else in it.

- :mod:`.main`     -- ``render``, the parser of every command, and ``main`` (exit status)
- :mod:`.stylize`  -- ``stylize``: one scene with one style image, NNFM or diffusion
- :mod:`.evaluate` -- ``evaluate``: metrics, comparison strip and preview of a stylization
- :mod:`.batch`    -- ``batch``: many stylize jobs over the GPUs of a machine or a Ray cluster
- :mod:`.common`   -- what the commands share: value parsing, progress bars, verbose loading,
  the options of views built around a scene without cameras
"""
