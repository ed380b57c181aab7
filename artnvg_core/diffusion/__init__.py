"""The ArtNVG diffusion stage: SDXL + Tile ControlNet + CSGO content/style control + NV attention.

Entry points (import them from their modules; this package imports nothing heavy itself):

- :mod:`.loader`       -- ``load_models_for``: the one loader for a device (once per process, placed, compiled)
- :mod:`.models`       -- ``load_diffusion_models`` (and per-model loaders) -> ``DiffusionModels``
- :mod:`.stylize`      -- ``stylize_views``: a whole scene, group by group
- :mod:`.sampler`      -- ``stylize_group``: one neighbouring-view group
- :mod:`.settings`     -- ``SamplerSettings`` and the names it chooses from (imports no diffusers)
- :mod:`.conditioning` -- ``prepare_conditioning``: prompt embeddings and style tokens
- :mod:`.csgo_weights` -- ``load_csgo``: CSGO's weights in every layout the released loader reads
- :mod:`.csgo`         -- token routing, processor installation, ``CSGOProjections``
- :mod:`.attention`    -- ``NeighbourViewSelfAttention``, ``DecoupledCrossAttention``, ``AttentionControl``
- :mod:`.attention_math` -- ``neighbour_view_attention``, ``decoupled_attention``: the maths on q/k/v
  (the diffusers processors and the node pack's ComfyUI patches both call it)
- :mod:`.resampler`    -- ``PerceiverResampler``
- :mod:`.images`       -- IMAGE checks, SDXL sizes, resizing, CLIP preprocessing
- :mod:`.model_files`  -- ``ModelFiles`` (the four files), locating them (explicit path or Hugging Face
  cache), ``missing_model``, ``MissingModelError``
- :mod:`.model_cache`  -- ``load_once``: the loaded models kept for the next load with the same key
- :mod:`.architectures` -- SDXL / ControlNet / ViT-bigG configs (no weights)
- :mod:`.sdxl_config`  -- SDXL 1.0 base's diffusers configs and CLIP tokenizer files, shipped (``clip_bpe/``)
- :mod:`.memory`       -- ``enable_low_memory``: a 15-view group at 1024 px within 12 GiB
- :mod:`.speed`        -- exact speed-ups (``SpeedOptions``, ``COMPILED_BLOCKS``: compiled repeated blocks)
- :mod:`.compile_cache` -- compile work kept across runs (PyTorch's compile cache artifacts)
- :mod:`.executor`     -- ``GroupExecutor``: groups spread over several devices (Ray actors)
- :mod:`.quiet_notices` -- third-party log records that say nothing to our users, dropped exactly
"""
