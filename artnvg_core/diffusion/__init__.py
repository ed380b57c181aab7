"""The ArtNVG diffusion stage: SDXL + Tile ControlNet + CSGO content/style control + NV attention.

Entry points (import them from their modules; this package imports nothing heavy itself):

- :mod:`.models`       -- ``load_diffusion_models`` (and per-model loaders) -> ``DiffusionModels``
- :mod:`.stylize`      -- ``stylize_views``: a whole scene, group by group
- :mod:`.sampler`      -- ``stylize_group``, ``SamplerSettings``: one neighbouring-view group
- :mod:`.conditioning` -- ``prepare_conditioning``: prompt embeddings and style tokens
- :mod:`.csgo_weights` -- ``load_csgo``: CSGO's weights in every layout the released loader reads
- :mod:`.csgo`         -- token routing, processor installation, ``CSGOProjections``
- :mod:`.attention`    -- ``NeighbourViewSelfAttention``, ``DecoupledCrossAttention``, ``AttentionControl``
- :mod:`.resampler`    -- ``PerceiverResampler``
- :mod:`.images`       -- IMAGE checks, SDXL sizes, resizing, CLIP preprocessing
- :mod:`.model_files`  -- locating model files (explicit path or Hugging Face cache), ``MissingModelError``
- :mod:`.architectures` -- SDXL / ControlNet / ViT-bigG configs (no weights)
"""
