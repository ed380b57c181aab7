"""Group sampler and scene stylization on tiny SDXL-architecture models (CPU, float32)."""

import pytest
import torch
from diffusers import DDIMScheduler, DPMSolverMultistepScheduler, UniPCMultistepScheduler
from diffusers.models.attention_processor import AttnProcessor2_0

from artnvg_core.cameras import CameraSet
from artnvg_core.diffusion.attention import AttentionControl
from artnvg_core.diffusion.conditioning import encode_prompt, image_features, prepare_conditioning
from artnvg_core.diffusion.memory import enable_low_memory, visiting
from artnvg_core.diffusion.sampler import (
    SCHEDULERS,
    SamplerSettings,
    resample_noise,
    stylize_group,
)
from artnvg_core.diffusion.settings import guided_steps
from artnvg_core.diffusion.stylize import stylize_groups, stylize_views
from artnvg_core.grouping import group_views
from artnvg_core.progress import Cancelled
from diffusion_tiny import one_cpu_thread  # noqa: F401  (autouse fixture)
from diffusion_tiny import diffusers_pipeline, tiny_models

PROMPT, NEGATIVE = "a garden, oil painting", "blurry"


def _images(count: int, height: int = 64, width: int = 64, seed: int = 0) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    return torch.rand(count, height, width, 3, generator=generator)


@pytest.fixture(scope="module")
def csgo_models(tmp_path_factory):
    return tiny_models(tmp_path_factory.mktemp("csgo"))


def _stop_guidance_after(step_count: int):
    """diffusers' callback for dynamic classifier-free guidance: after ``step_count`` steps, guidance off and
    the conditional half of every doubled input kept (the documented "truncation of CFG" recipe)."""

    def callback(pipe, step, timestep, tensors):
        if step + 1 != step_count:
            return {}
        pipe._guidance_scale = 0.0
        return {name: value.chunk(2)[1] for name, value in tensors.items()}

    return callback


def _diffusers_reference(models, images, scheduler, steps, guidance, control_scale, seed, guided_steps=None):
    base = models.base
    saved = {name: dict(model.attn_processors) for name, model in (("unet", base.unet), ("cn", models.controlnet))}
    base.unet.set_attn_processor(AttnProcessor2_0())
    models.controlnet.set_attn_processor(AttnProcessor2_0())
    pipe = diffusers_pipeline(base, SCHEDULERS[scheduler].from_config(base.scheduler_config), models.controlnet)
    try:
        out = pipe(
            prompt=[PROMPT] * len(images),
            negative_prompt=[NEGATIVE] * len(images),
            image=images.permute(0, 3, 1, 2),
            height=images.shape[1],
            width=images.shape[2],
            num_inference_steps=steps,
            guidance_scale=guidance,
            controlnet_conditioning_scale=control_scale,
            generator=torch.Generator().manual_seed(seed),
            output_type="pt",
            callback_on_step_end=None if guided_steps is None else _stop_guidance_after(guided_steps),
            callback_on_step_end_tensor_inputs=["prompt_embeds", "add_text_embeds", "add_time_ids", "image"],
        ).images
    finally:
        base.unet.set_attn_processor(saved["unet"])
        models.controlnet.set_attn_processor(saved["cn"])
    return out.permute(0, 2, 3, 1)


@pytest.mark.parametrize("scheduler, guidance, cfg_until", [
    ("ddim", 7.0, 1.0), ("euler_ancestral", 5.0, 1.0), ("ddim", 1.0, 1.0), ("dpmpp_2m", 7.0, 1.0),
    ("unipc", 7.0, 0.5), ("ddim", 7.0, 0.3)])
def test_matches_diffusers_controlnet_pipeline(csgo_models, scheduler, guidance, cfg_until):
    """NV attention off and CSGO scales 0: our sampler is diffusers' SDXL ControlNet pipeline, with guidance
    truncated as diffusers' dynamic-CFG callback truncates it (2 of 4 steps guided at 0.5, 2 at 0.3)."""
    images = _images(3)
    guided = None if cfg_until == 1 else {0.5: 2, 0.3: 2}[cfg_until]
    expected = _diffusers_reference(csgo_models, images, scheduler, 4, guidance, 0.8, seed=7, guided_steps=guided)
    conditioning = prepare_conditioning(csgo_models, _images(1, seed=9), PROMPT, NEGATIVE)
    settings = SamplerSettings(
        steps=4,
        guidance_scale=guidance,
        content_scale=0.0,
        style_scale=0.0,
        control_scale=0.8,
        neighbour_views=False,
        resolution=None,
        scheduler=scheduler,
        cfg_until=cfg_until,
    )
    ours = stylize_group(csgo_models, images, conditioning, settings, seed=7)
    assert ours.shape == (3, 64, 64, 3)
    assert (ours - expected).abs().max().item() <= 1e-4


class _BoundProcessor:
    """One of our cross-attention processors with fixed settings, for a pipeline that hands the
    ControlNet no cross_attention_kwargs (as CSGO's processors keep their token counts themselves)."""

    def __init__(self, processor, control):
        self.processor, self.control = processor, control

    def __call__(self, attn, hidden_states, encoder_hidden_states=None, attention_mask=None, temb=None):
        return self.processor(attn, hidden_states, encoder_hidden_states, attention_mask, temb, control=self.control)


def test_csgo_tokens_match_diffusers_pipeline_at_a_non_square_size(csgo_models):
    """With CSGO tokens in play (paper routing, NV off) at 64x128, our sampler equals diffusers' SDXL ControlNet
    pipeline fed prompt embeddings [text, view i's own content tokens, style tokens] and unconditional ones from
    zero features: catches swapped guidance halves, another view's content tokens and (w, h) size ids."""
    models, views = csgo_models, 3
    images, style_image = _images(views, height=64, width=128), _images(1, seed=9)
    control = AttentionControl(num_content_tokens=4, num_style_tokens=8, content_scale=0.8, style_scale=0.7)
    base = models.base
    pipe = diffusers_pipeline(base, SCHEDULERS["ddim"].from_config(base.scheduler_config), models.controlnet)
    text, negative_text, pooled, negative_pooled = pipe.encode_prompt(PROMPT, device=torch.device("cpu"),
                                                                      negative_prompt=NEGATIVE)
    style = models.csgo.tokens("style", image_features(models.image_encoder, style_image))
    content = [models.csgo.tokens("content", image_features(models.image_encoder, images[i : i + 1])) for i in
               range(views)]  # one view at a time
    cond = torch.cat([torch.cat([text, c.cond, style.cond], 1) for c in content])
    uncond = torch.cat([torch.cat([negative_text, c.uncond, style.uncond], 1) for c in content])
    saved = {model: dict(model.attn_processors) for model in (base.unet, models.controlnet)}
    for model, processors in saved.items():
        model.set_attn_processor({name: AttnProcessor2_0() if name.endswith("attn1.processor")
                                  else _BoundProcessor(processor, control) for name, processor in processors.items()})
    try:
        expected = pipe(
            prompt_embeds=cond, negative_prompt_embeds=uncond, pooled_prompt_embeds=pooled.expand(views, -1),
            negative_pooled_prompt_embeds=negative_pooled.expand(views, -1), image=images.permute(0, 3, 1, 2),
            height=64, width=128, num_inference_steps=3, guidance_scale=5.0, controlnet_conditioning_scale=0.9,
            generator=torch.Generator().manual_seed(4), output_type="pt",
        ).images.permute(0, 2, 3, 1)
    finally:
        for model, processors in saved.items():
            model.set_attn_processor(processors)
    settings = SamplerSettings(steps=3, guidance_scale=5.0, content_scale=0.8, style_scale=0.7, control_scale=0.9,
                               content_routing="paper", neighbour_views=False, resolution=None)
    conditioning = prepare_conditioning(models, style_image, PROMPT, NEGATIVE)
    ours = stylize_group(models, images, conditioning, settings, seed=4)
    assert ours.shape == (views, 64, 128, 3)
    assert (ours - expected).abs().max().item() <= 1e-4


def test_prompt_encoding_matches_diffusers(csgo_models):
    base = csgo_models.base
    pipe = diffusers_pipeline(base, SCHEDULERS["ddim"].from_config(base.scheduler_config), csgo_models.controlnet)
    for negative in (NEGATIVE, None):
        ours = encode_prompt(base, PROMPT, negative)
        theirs = pipe.encode_prompt(PROMPT, device=torch.device("cpu"), negative_prompt=negative)
        for a, b in zip((ours.text, ours.negative_text, ours.pooled, ours.negative_pooled), theirs):
            assert torch.equal(a, b)
    assert not encode_prompt(base, PROMPT, None).negative_text.any()


def _run(models, images, seed=3, noise_seeds=None, **changes):
    settings = dict(steps=2, guidance_scale=5.0, resolution=None)
    settings.update(changes)
    conditioning = prepare_conditioning(models, _images(1, seed=9), PROMPT, NEGATIVE)
    return stylize_group(models, images, conditioning, SamplerSettings(**settings), seed=seed, noise_seeds=noise_seeds)


def test_switches_change_the_result(csgo_models):
    images = _images(3)
    base = _run(csgo_models, images, neighbour_views=False, content_scale=0.0, style_scale=0.0)
    for change in ({"neighbour_views": True}, {"content_scale": 1.0, "content_routing": "paper"}, {"style_scale": 0.6}):
        settings = {"neighbour_views": False, "content_scale": 0.0, "style_scale": 0.0, **change}
        assert (_run(csgo_models, images, **settings) - base).abs().max() > 1e-4, change
    assert torch.equal(_run(csgo_models, images, neighbour_views=False, content_scale=0.0, style_scale=0.0), base)


def test_released_routing_reads_no_content_tokens(csgo_models, tmp_path):
    """CSGO's released inference: with the content entries loaded, "released" equals "paper" at
    content_scale 0, and content_scale changes nothing; "paper" needs the entries."""
    images = _images(3)
    released = _run(csgo_models, images, content_scale=1.0)
    assert torch.equal(released, _run(csgo_models, images, content_routing="paper", content_scale=0.0))
    assert torch.equal(released, _run(csgo_models, images, content_scale=0.3))
    without_content = tiny_models(tmp_path, unet_content=False)
    assert _run(without_content, images).shape == images.shape
    with pytest.raises(ValueError, match="content_routing 'paper' needs the CSGO file's content entries"):
        _run(without_content, images, content_routing="paper")
    with pytest.raises(ValueError, match="SamplerSettings.content_routing must be one of"):
        SamplerSettings(content_routing="papers")


def test_single_view_group_ignores_nv_switch(csgo_models):
    images = _images(1)
    assert torch.equal(
        _run(csgo_models, images, neighbour_views=True), _run(csgo_models, images, neighbour_views=False)
    )


@pytest.mark.parametrize("size_rule, latent", [("long_side", (8, 16)), ("area", (8, 24))])
def test_samples_at_the_working_size_and_returns_the_views_size(csgo_models, size_rule, latent):
    # 50x90 views, resolution 128: CSGO's rule gives 64x128 (long side 128, 71 floored to 32's),
    # the area rule about 128² pixels in 64's: 64x192. The tiny VAE shrinks 8x, like SDXL's.
    seen = []
    hook = csgo_models.base.unet.register_forward_pre_hook(lambda module, args: seen.append(args[0].shape[2:]))
    try:
        out = _run(csgo_models, _images(2, height=50, width=90), resolution=128, size_rule=size_rule)
    finally:
        hook.remove()
    assert set(seen) == {latent}
    assert out.shape == (2, 50, 90, 3) and out.dtype == torch.float32
    assert out.min() >= 0 and out.max() <= 1


def _unet_batches(models, run) -> list[int]:
    """Batch sizes of the UNet calls made by ``run()``."""
    seen = []
    hook = models.base.unet.register_forward_pre_hook(lambda module, args: seen.append(len(args[0])))
    try:
        run()
    finally:
        hook.remove()
    return seen


@pytest.mark.parametrize("scheduler", ["ddim", "dpmpp_2m", "unipc"])
def test_scheduler_and_steps_reach_diffusers(csgo_models, scheduler, monkeypatch):
    """The named diffusers scheduler class is the one that steps, set to the requested step count; one
    UNet call per step."""
    used = []

    class Recording(SCHEDULERS[scheduler]):
        def set_timesteps(self, steps, *args, **kwargs):
            used.append((type(self).__mro__[1], steps))
            return super().set_timesteps(steps, *args, **kwargs)

    monkeypatch.setitem(SCHEDULERS, scheduler, Recording)
    batches = _unet_batches(csgo_models, lambda: _run(csgo_models, _images(2), steps=3, scheduler=scheduler))
    expected = {"ddim": DDIMScheduler, "dpmpp_2m": DPMSolverMultistepScheduler, "unipc": UniPCMultistepScheduler}
    assert used == [(expected[scheduler], 3)] and batches == [4, 4, 4]
    config = Recording.from_config(csgo_models.base.scheduler_config).config
    if scheduler == "dpmpp_2m":
        assert (config.algorithm_type, config.solver_order) == ("dpmsolver++", 2)


def test_guidance_truncation_halves_the_late_steps(csgo_models):
    """cfg_until: the first ceil(fraction x steps) steps run both guidance halves (batch 2N), the rest the
    conditional half (batch N); 1.0 is the untruncated run bit for bit, 0 the unguided run; sequential
    halves agree."""
    images = _images(3)
    full = _run(csgo_models, images, steps=5)
    assert torch.equal(_run(csgo_models, images, steps=5, cfg_until=1.0), full)
    truncated = []
    for cfg_until, sequential, expected in ((0.6, False, [6, 6, 6, 3, 3]), (0.6, True, [3, 3, 3, 3, 3, 3, 3, 3]),
                                            (0.0, False, [3] * 5), (0.8, False, [6] * 4 + [3])):
        batches = _unet_batches(csgo_models, lambda: truncated.append(
            _run(csgo_models, images, steps=5, cfg_until=cfg_until, sequential_cfg=sequential)))
        assert batches == expected, (cfg_until, sequential)
    torch.testing.assert_close(truncated[1], truncated[0], rtol=0, atol=1e-5)
    torch.testing.assert_close(truncated[2], _run(csgo_models, images, steps=5, guidance_scale=1.0), rtol=0, atol=1e-5)
    assert (truncated[0] - full).abs().max() > 1e-4 and (truncated[0] - truncated[2]).abs().max() > 1e-4
    assert guided_steps(50, 0.8, 5.0) == 40 and guided_steps(5, 0.5, 5.0) == 3
    assert guided_steps(50, 0.8, 1.0) == 0
    for value in (-0.1, 1.5):
        with pytest.raises(ValueError, match="SamplerSettings.cfg_until must be in \\[0, 1\\]"):
            SamplerSettings(cfg_until=value)


def _first_unet_input(models, run) -> torch.Tensor:
    """The latents the UNet sees first in ``run()`` (DDIM: the initial noise itself)."""
    seen = []
    hook = models.base.unet.register_forward_pre_hook(lambda module, args: seen.append(args[0].clone()))
    try:
        run()
    finally:
        hook.remove()
    return seen[0]


def test_noise_resolution_resamples_the_noise_of_the_other_grid(csgo_models):
    """At resolution 64 (latents 8x8) with noise_resolution 128, the first latents are the seeded 16x16 noise
    resampled to 8x8; at its own resolution the setting changes nothing."""
    images = _images(2)
    noise = _first_unet_input(csgo_models, lambda: _run(csgo_models, images, resolution=64, noise_resolution=128))
    expected = resample_noise(torch.randn((2, 4, 16, 16), generator=torch.Generator().manual_seed(3)), (8, 8))
    torch.testing.assert_close(noise[:2], expected)
    assert torch.equal(_run(csgo_models, images, resolution=64, noise_resolution=64),
                       _run(csgo_models, images, resolution=64))
    with pytest.raises(ValueError, match="SamplerSettings.noise_resolution"):
        SamplerSettings(noise_resolution=32)


def test_resample_noise_area_averages_and_standardises():
    coarse = torch.randn(2, 4, 4, 6, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    fine = coarse.repeat_interleave(2, dim=2).repeat_interleave(2, dim=3)  # each coarse cell as 2x2 cells
    out = resample_noise(fine, (4, 6))
    standard = (coarse - coarse.mean((2, 3), keepdim=True)) / coarse.std((2, 3), keepdim=True)
    torch.testing.assert_close(out, standard)
    odd = resample_noise(torch.randn(3, 4, 16, 16, generator=torch.Generator().manual_seed(1)), (12, 12))
    assert odd.shape == (3, 4, 12, 12)
    torch.testing.assert_close(odd.mean((2, 3)), torch.zeros(3, 4), atol=1e-6, rtol=0)
    torch.testing.assert_close(odd.std((2, 3)), torch.ones(3, 4), atol=1e-6, rtol=0)
    assert resample_noise(coarse, (4, 6)) is coarse


def test_noise_seeds_give_each_view_its_own_noise_whatever_its_group(csgo_models):
    """With one seed per view and NV attention off (views independent), a view's result does not depend on
    the group it is sampled in; its first latents are its own seeded noise."""
    images = _images(3)
    together = _run(csgo_models, images, neighbour_views=False, noise_seeds=[10, 11, 12])
    alone = _run(csgo_models, images[1:2], neighbour_views=False, noise_seeds=[11])
    torch.testing.assert_close(alone, together[1:2], rtol=0, atol=1e-5)
    noise = _first_unet_input(csgo_models, lambda: _run(csgo_models, images[1:], noise_seeds=[11, 12]))
    expected = torch.cat([torch.randn((1, 4, 8, 8), generator=torch.Generator().manual_seed(s)) for s in (11, 12)])
    torch.testing.assert_close(noise[:2], expected)
    with pytest.raises(ValueError, match="2 noise_seeds for 3 views"):
        _run(csgo_models, images, noise_seeds=[1, 2])


def test_progress_and_stop(csgo_models):
    calls = []
    conditioning = prepare_conditioning(csgo_models, _images(1), PROMPT, NEGATIVE)
    settings = SamplerSettings(steps=3, resolution=None)
    stylize_group(csgo_models, _images(2), conditioning, settings, progress=lambda s, t, info: calls.append((s, t)))
    assert calls == [(1, 3), (2, 3), (3, 3)]
    with pytest.raises(Cancelled):
        stylize_group(
            csgo_models,
            _images(2),
            conditioning,
            settings,
            should_stop=lambda: len(calls) >= 4,
            progress=lambda s, t, info: calls.append((s, t)),
        )
    assert len(calls) == 4


def test_bad_inputs_raise(csgo_models):
    conditioning = prepare_conditioning(csgo_models, _images(1), PROMPT, NEGATIVE)
    with pytest.raises(ValueError, match=r"content_images: expected an IMAGE batch \[B, H, W, 3\]"):
        stylize_group(csgo_models, torch.rand(2, 3, 64, 64), conditioning)
    with pytest.raises(ValueError, match="values must lie in \\[0, 1\\]"):
        stylize_group(csgo_models, 2 * _images(2), conditioning)
    with pytest.raises(ValueError, match="style_image is required"):
        prepare_conditioning(csgo_models, None, PROMPT)
    with pytest.raises(ValueError, match="scheduler must be one of"):
        SamplerSettings(scheduler="magic")


def _line_cameras(count: int) -> CameraSet:
    world_to_cam = torch.eye(4).repeat(count, 1, 1)
    world_to_cam[:, 0, 3] = -torch.arange(count, dtype=torch.float32)  # centres at x = 0, 1, 2, ...
    intrinsics = torch.tensor([[60.0, 0, 32], [0, 60.0, 32], [0, 0, 1]]).repeat(count, 1, 1)
    return CameraSet(
        world_to_cam=world_to_cam,
        intrinsics=intrinsics,
        width=64,
        height=64,
        names=[f"v{i}" for i in range(count)],
        image_paths=[None] * count,
    )


def test_scene_runs_groups_and_keeps_view_order(csgo_models):
    """6 views on a line in 2 groups of 3: each view's output equals its group's own run (seed + group index)."""
    images = _images(6)
    order = torch.tensor([4, 0, 5, 2, 1, 3])  # shuffled capture order
    cameras = _line_cameras(6)
    cameras.world_to_cam = cameras.world_to_cam[order]
    settings = SamplerSettings(steps=2, guidance_scale=5.0, resolution=None)
    calls = []
    out = stylize_views(
        csgo_models,
        images,
        cameras,
        _images(1, seed=9),
        settings,
        group_size=3,
        seed=10,
        prompt=PROMPT,
        negative_prompt=NEGATIVE,
        progress=lambda s, t, i: calls.append((s, t, i["group"])),
    )
    assert [c[:2] for c in calls] == [(1, 4), (2, 4), (3, 4), (4, 4)]
    conditioning = prepare_conditioning(csgo_models, _images(1, seed=9), PROMPT, NEGATIVE)
    groups = [list(group.views) for group in group_views(cameras, 3)]
    near = sorted(int(i) for i in torch.nonzero(order < 3))  # views whose centre is x in {0, 1, 2}
    assert sorted(map(sorted, groups)) == sorted([near, sorted(set(range(6)) - set(near))])
    for index, views in enumerate(groups):
        expected = stylize_group(csgo_models, images[views], conditioning, settings, seed=10 + index)
        torch.testing.assert_close(out[views], expected, rtol=0, atol=1e-6)


def test_scene_hands_each_group_its_views_noise_seeds(csgo_models):
    images, cameras = _images(6), _line_cameras(6)
    groups = group_views(cameras, 3)
    conditioning = prepare_conditioning(csgo_models, _images(1, seed=9), PROMPT, NEGATIVE)
    settings = SamplerSettings(steps=1, guidance_scale=5.0, resolution=None)
    seeds = [100 + 7 * v for v in range(6)]
    out = stylize_groups(csgo_models, images, groups, conditioning, settings, seed=4, noise_seeds=seeds)
    for index, group in enumerate(groups):
        views = list(group.views)
        expected = stylize_group(csgo_models, images[views], conditioning, settings, seed=4 + index,
                                 noise_seeds=[seeds[v] for v in views], view_centers=cameras.centers[views])
        torch.testing.assert_close(out[views], expected, rtol=0, atol=1e-6)
    with pytest.raises(ValueError, match="5 noise_seeds for 6 views"):
        stylize_groups(csgo_models, images, groups, conditioning, settings, noise_seeds=seeds[:5])


def test_sequential_guidance_halves_match_the_joint_batch(csgo_models):
    images = _images(3)
    torch.testing.assert_close(
        _run(csgo_models, images, sequential_cfg=True), _run(csgo_models, images), rtol=0, atol=1e-5
    )


def test_low_memory_mode_matches(tmp_path):
    """Feed-forward chunking and idle-model placement change rounding only (CPU: nothing moves)."""
    models = tiny_models(tmp_path)
    images = _images(3)
    expected = _run(models, images)
    enable_low_memory(models)
    assert all(block._chunk_size == 1 for block in models.base.unet.modules() if hasattr(block, "_chunk_size"))
    torch.testing.assert_close(_run(models, images, sequential_cfg=True), expected, rtol=0, atol=1e-5)


def test_nv_approximations_change_the_result_unless_degenerate(csgo_models):
    images, centers = _images(4), torch.tensor([[0.0, 0, 0], [1, 0, 0], [3, 0, 0], [7, 0, 0]])
    conditioning = prepare_conditioning(csgo_models, _images(1, seed=9), PROMPT, NEGATIVE)

    def run(**changes):
        settings = SamplerSettings(steps=2, guidance_scale=5.0, resolution=None, **changes)
        return stylize_group(csgo_models, images, conditioning, settings, seed=3, view_centers=centers)

    exact = run()
    assert torch.equal(run(nv_nearest=3), exact)  # every other view: the exact path
    per_view = run(neighbour_views=False)
    for change in ({"nv_levels": "lowest"}, {"nv_nearest": 1}, {"nv_kv_downsample": 2}):
        approximate = run(**change)
        assert torch.equal(approximate, run(**change)), change
        assert (approximate - exact).abs().max() > 1e-5, change
        assert (approximate - per_view).abs().max() > 1e-5, change
    with pytest.raises(ValueError, match="nv_nearest needs view_centers"):
        stylize_group(csgo_models, images, conditioning, SamplerSettings(steps=1, nv_nearest=1, resolution=None))
    for field, value in (("nv_levels", "middle"), ("nv_nearest", 0), ("nv_kv_downsample", 0)):
        with pytest.raises(ValueError, match=f"SamplerSettings.{field}"):
            SamplerSettings(**{field: value})


def test_scene_passes_camera_centres_to_nearest_views(csgo_models):
    """stylize_views hands each group its views' centres: nv_nearest=1 runs and matches the group run."""
    images, cameras = _images(6), _line_cameras(6)
    settings = SamplerSettings(steps=1, guidance_scale=5.0, resolution=None, nv_nearest=1)
    out = stylize_views(csgo_models, images, cameras, _images(1, seed=9), settings, group_size=6, seed=2,
                        prompt=PROMPT, negative_prompt=NEGATIVE)
    conditioning = prepare_conditioning(csgo_models, _images(1, seed=9), PROMPT, NEGATIVE)
    expected = stylize_group(csgo_models, images, conditioning, settings, seed=2, view_centers=cameras.centers)
    torch.testing.assert_close(out, expected, rtol=0, atol=1e-6)


def test_visiting_swaps_weights_in_and_back():
    """Inside the block the module computes with copies on the device; afterwards it holds its own tensors."""
    layer = torch.nn.Linear(3, 2)
    homes = [t.data_ptr() for t in layer.parameters()]
    with visiting(layer, torch.device("meta")):
        assert all(t.device.type == "meta" for t in layer.parameters())
        assert layer(torch.zeros(1, 3, device="meta")).device.type == "meta"
    assert [t.data_ptr() for t in layer.parameters()] == homes
    with visiting(layer, torch.device("cpu")), visiting(None, torch.device("meta")):  # no-ops
        assert [t.data_ptr() for t in layer.parameters()] == homes
