"""Exact speedups (artnvg_core.diffusion.speed) on tiny SDXL-architecture models (CPU, float32).

Each option must leave the noise prediction and the sampled images unchanged up to float32
rounding. Compilation is traced with Dynamo's eager backend only: generating code for even the
tiny models takes minutes on a CPU; the GPU benchmark (bench/diffusion.py --variants) reports the
compiled deviation.
"""

import copy
import dataclasses

import pytest
import torch
from diffusers.models.attention_processor import Attention
from torch._dynamo.utils import counters
from torch.utils.flop_counter import FlopCounterMode

from artnvg_core.diffusion.attention import AttentionControl, NeighbourViewSelfAttention, attention_kwargs
from artnvg_core.diffusion.conditioning import prepare_conditioning
from artnvg_core.diffusion.models import DiffusionModels
from artnvg_core.diffusion.sampler import SamplerSettings, stylize_group
from artnvg_core.diffusion.speed import (
    BLOCK_RECOMPILE_LIMIT,
    REPEATED_BLOCKS,
    CUDNN_FIRST,
    SpeedOptions,
    apply_speedups,
    compile_repeated_blocks,
    cudnn_attention_first,
    sdpa_backend,
)
from diffusion_tiny import CROSS_DIM, TEXT_WIDTH
from diffusion_tiny import one_cpu_thread  # noqa: F401  (autouse fixture)
from diffusion_tiny import tiny_models

VIEWS, SIZE, TEXT_TOKENS, CONTENT_TOKENS, STYLE_TOKENS = 3, 64, 10, 4, 8
TOLERANCE = 1e-5  # relative L2, float32


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    return tiny_models(tmp_path_factory.mktemp("csgo"), num_style_tokens=STYLE_TOKENS)


def _step_inputs(views: int) -> dict:
    """CFG batch of 2 x ``views`` views with NV attention and CSGO tokens, seeded."""
    generator = torch.Generator().manual_seed(0)
    batch = 2 * views
    control = AttentionControl(views, CONTENT_TOKENS, STYLE_TOKENS, content_scale=1.0, style_scale=0.6)
    return {
        "sample": torch.randn(batch, 4, SIZE // 8, SIZE // 8, generator=generator),
        "timestep": torch.tensor(500),
        "encoder_hidden_states": torch.randn(
            batch, TEXT_TOKENS + CONTENT_TOKENS + STYLE_TOKENS, CROSS_DIM, generator=generator
        ),
        "hint": torch.rand(batch, 3, SIZE, SIZE, generator=generator),
        "added_cond_kwargs": {
            "text_embeds": torch.randn(batch, TEXT_WIDTH, generator=generator),
            "time_ids": torch.tensor([[SIZE, SIZE, 0, 0, SIZE, SIZE]] * batch, dtype=torch.float32),
        },
        "cross_attention_kwargs": attention_kwargs(control),
    }


@pytest.fixture(scope="module")
def step_inputs():
    return _step_inputs(VIEWS)


@torch.no_grad()
def _noise(models, inputs) -> torch.Tensor:
    inputs = dict(inputs)
    hint = inputs.pop("hint")
    down, mid = models.controlnet(controlnet_cond=hint, return_dict=False, **inputs)
    return models.base.unet(
        down_block_additional_residuals=down, mid_block_additional_residual=mid, return_dict=False, **inputs
    )[0]


def _relative_l2(a: torch.Tensor, b: torch.Tensor) -> float:
    return ((a - b).norm() / b.norm()).item()


def _copy(models) -> DiffusionModels:
    return dataclasses.replace(
        models,
        base=dataclasses.replace(models.base, unet=copy.deepcopy(models.base.unet)),
        controlnet=copy.deepcopy(models.controlnet),
    )


def _storage_bytes(model: torch.nn.Module) -> int:
    """Bytes of the distinct storages behind ``model``'s parameters."""
    storages = {p.untyped_storage().data_ptr(): p.untyped_storage().nbytes() for p in model.parameters()}
    return sum(storages.values())


def test_math_backend_matches_default(models, step_inputs):
    reference = _noise(models, step_inputs)
    with sdpa_backend("math"):
        math = _noise(models, step_inputs)
    assert reference.abs().mean() > 0.1
    assert _relative_l2(math, reference) < TOLERANCE


def test_backend_reaches_our_processors(models, step_inputs):
    """The context really restricts our processors' SDPA calls: cuDNN has no CPU kernel."""
    with sdpa_backend("cudnn"), pytest.raises(RuntimeError, match="backend|kernel"):
        _noise(models, step_inputs)


@pytest.mark.parametrize(
    "options", [SpeedOptions(channels_last=True), SpeedOptions(fuse_projections=True)], ids=["channels_last", "fused"]
)
def test_model_speedup_keeps_noise_prediction(models, step_inputs, options):
    variant = _copy(models)
    apply_speedups(variant, options)
    assert _relative_l2(_noise(variant, step_inputs), _noise(models, step_inputs)) < TOLERANCE


def test_channels_last_layout(models):
    variant = _copy(models)
    apply_speedups(variant, SpeedOptions(channels_last=True))
    convs = [m.weight for m in variant.base.unet.modules() if isinstance(m, torch.nn.Conv2d) and m.kernel_size == (3, 3)]
    assert convs and all(w.is_contiguous(memory_format=torch.channels_last) for w in convs)


def test_fused_projections_share_memory(models):
    """Every attention is fused; the separate weights are views of the fused one (no memory added)."""
    variant = _copy(models)
    before = _storage_bytes(variant.base.unet)
    apply_speedups(variant, SpeedOptions(fuse_projections=True))
    layers = [m for m in variant.base.unet.modules() if isinstance(m, Attention)]
    assert layers and all(layer.fused_projections for layer in layers)
    for layer in layers:
        fused = layer.to_kv if layer.is_cross_attention else layer.to_qkv
        assert layer.to_k.weight.untyped_storage().data_ptr() == fused.weight.untyped_storage().data_ptr()
        k_rows = layer.to_k.out_features
        k_start = 0 if layer.is_cross_attention else layer.to_q.out_features
        assert torch.equal(fused.weight[k_start : k_start + k_rows], layer.to_k.weight)
    assert _storage_bytes(variant.base.unet) == before


def test_sampler_with_all_exact_options_matches(models):
    generator = torch.Generator().manual_seed(1)
    images = torch.rand(VIEWS, SIZE, SIZE, 3, generator=generator)
    conditioning = prepare_conditioning(models, torch.rand(1, 64, 64, 3, generator=generator), "a cat", "blurry")
    settings = SamplerSettings(steps=2, guidance_scale=5.0, resolution=None)
    reference = stylize_group(models, images, conditioning, settings, seed=3)
    variant = _copy(models)
    apply_speedups(variant, SpeedOptions(channels_last=True, fuse_projections=True))
    fast = dataclasses.replace(settings, attention_backend="math")
    assert _relative_l2(stylize_group(variant, images, conditioning, fast, seed=3), reference) < TOLERANCE


def test_bad_options_raise():
    with pytest.raises(ValueError, match="SamplerSettings.attention_backend"):
        SamplerSettings(attention_backend="fast")
    with pytest.raises(ValueError, match="SpeedOptions.compile"):
        SpeedOptions(compile="fastest")
    with pytest.raises(ValueError, match="sdpa_backend"):
        sdpa_backend("flashy")


def test_flop_counter_counts_nv_attention_on_meta():
    """On the meta device the FLOP counter sees NV attention's products: 4 G H (N L)^2 D."""
    groups, views, tokens, heads, head_dim = 2, 3, 16, 2, 8
    with torch.device("meta"):
        layer = Attention(query_dim=heads * head_dim, heads=heads, dim_head=head_dim)
        x = torch.randn(groups * views, tokens, heads * head_dim)
    layer.set_processor(NeighbourViewSelfAttention())
    with FlopCounterMode(display=False) as counter:
        layer(x, control=AttentionControl(views_per_group=views))
    counts = {str(op): n for op, n in counter.get_flop_counts()["Global"].items()}
    width = heads * head_dim
    assert counts["aten.bmm"] == 4 * groups * heads * (views * tokens) ** 2 * head_dim
    projections = 4 * 2 * groups * views * tokens * width * width  # q, k, v, out
    assert counts.get("aten.mm", 0) + counts.get("aten.addmm", 0) == projections


@pytest.mark.parametrize("mode", [torch.no_grad, torch.inference_mode])
def test_cached_hint_embedding_is_exact_and_computed_once_per_hint(models, mode):
    """The sampler's images are bit-identical with the cache, and the embedding runs once per
    hint tensor (per guidance half with sequential CFG), not once per step; also under
    inference mode (ComfyUI's), where tensors have no version counter."""
    generator = torch.Generator().manual_seed(1)
    images = torch.rand(VIEWS, SIZE, SIZE, 3, generator=generator)
    conditioning = prepare_conditioning(models, torch.rand(1, 64, 64, 3, generator=generator), "a cat", "blurry")
    for sequential in (False, True):
        settings = SamplerSettings(steps=3, guidance_scale=5.0, resolution=None, sequential_cfg=sequential)
        reference = stylize_group(models, images, conditioning, settings, seed=3)
        variant = _copy(models)
        apply_speedups(variant, SpeedOptions(cache_hint_embedding=True))
        calls = []  # the embedding's first convolution runs only when the embedding is really computed
        variant.controlnet.controlnet_cond_embedding.conv_in.register_forward_hook(lambda *_: calls.append(1))
        with mode():
            assert torch.equal(stylize_group(variant, images, conditioning, settings, seed=3), reference)
        assert len(calls) == (2 if sequential else 1)


def test_cached_hint_embedding_recomputes_a_changed_hint(models, step_inputs):
    variant = _copy(models)
    apply_speedups(variant, SpeedOptions(cache_hint_embedding=True))
    inputs = dict(step_inputs, hint=step_inputs["hint"].clone())
    _noise(variant, inputs)
    inputs["hint"].mul_(0.5)  # in place: same object, new version
    assert torch.equal(_noise(variant, inputs), _noise(models, inputs))
    with torch.enable_grad():  # never cached while gradients are on
        first = variant.controlnet.controlnet_cond_embedding(inputs["hint"])
        assert first.grad_fn is not None


@pytest.fixture
def fresh_dynamo():
    """Dynamo with empty caches and counters; afterwards its recompile limit, which
    compile_repeated_blocks raises process-wide, is put back, so no other test sees the change.
    Dynamo's own config patch does the restoring: pytest 9.2's monkeypatch would undo a setting of
    Dynamo's config module by deleting it, which hides the setting for the rest of the process."""
    torch._dynamo.reset()
    counters.clear()
    with torch._dynamo.config.patch(recompile_limit=torch._dynamo.config.recompile_limit):
        yield
    torch._dynamo.reset()


@pytest.mark.slow
def test_regional_compile_compiles_repeated_blocks_only_and_keeps_output(models, step_inputs, fresh_dynamo):
    """Dynamo traces every transformer/ResNet block (eager backend: no code generation on the CPU
    test machine); the noise prediction is unchanged and the models themselves stay uncompiled;
    Dynamo may keep a graph for each of SDXL's ~20 block shapes."""
    torch._dynamo.config.recompile_limit = 8
    variant = _copy(models)
    counts = [compile_repeated_blocks(model, backend="eager")
              for model in (variant.base.unet, variant.controlnet)]
    blocks = [m for m in variant.base.unet.modules() if type(m).__name__ in REPEATED_BLOCKS]
    assert counts[0] == len(blocks) > 0 and counts[1] > 0
    assert all(block._compiled_call_impl is not None for block in blocks)
    assert variant.base.unet._compiled_call_impl is None
    assert torch._dynamo.config.recompile_limit >= BLOCK_RECOMPILE_LIMIT > 8
    assert _relative_l2(_noise(variant, step_inputs), _noise(models, step_inputs)) < TOLERANCE


@pytest.mark.slow
@pytest.mark.parametrize("dynamic", [True, None])
def test_dynamic_regional_compile_keeps_its_graphs_for_a_new_group_size(models, dynamic, fresh_dynamo):
    """With symbolic shapes, a group of another size reuses the blocks' graphs (Dynamo's default,
    dynamic=None, compiles them again); the output is unchanged at both sizes."""
    variant = _copy(models)
    for model in (variant.base.unet, variant.controlnet):
        compile_repeated_blocks(model, backend="eager", dynamic=dynamic)
    graphs = []
    for views in (VIEWS, VIEWS - 1):
        inputs = _step_inputs(views)
        assert _relative_l2(_noise(variant, inputs), _noise(models, inputs)) < TOLERANCE
        graphs.append(counters["stats"]["unique_graphs"])
    assert graphs[0] > 0
    assert (graphs[1] == graphs[0]) == (dynamic is True), graphs


def test_bad_speed_options_raise():
    with pytest.raises(ValueError, match="SpeedOptions.compile_scope"):
        SpeedOptions(compile="default", compile_scope="layers")
    with pytest.raises(ValueError, match="cache_hint_embedding"):
        SpeedOptions(compile="default", cache_hint_embedding=True)
    with pytest.raises(ValueError, match="compile_dynamic"):
        SpeedOptions(compile_dynamic=True)


def _backends_now() -> tuple[list[int], list[bool]]:
    """PyTorch's SDPA priority order and whether cuDNN, flash, efficient and math attention are enabled."""
    flags = [torch.backends.cuda.cudnn_sdp_enabled(), torch.backends.cuda.flash_sdp_enabled(),
             torch.backends.cuda.mem_efficient_sdp_enabled(), torch.backends.cuda.math_sdp_enabled()]
    return torch._C._get_sdp_priority_order(), flags


def test_cudnn_attention_first_orders_the_enabled_backends_and_restores():
    before = _backends_now()
    with cudnn_attention_first(torch.device("cuda")):
        order, flags = _backends_now()
        assert order[:4] == [int(backend) for backend in CUDNN_FIRST]
        assert order[0] == int(torch.nn.attention.SDPBackend.CUDNN_ATTENTION)
        assert flags == before[1]
    with sdpa_backend("flash"), cudnn_attention_first(torch.device("cuda")):  # a restriction holds
        assert _backends_now()[1] == [False, True, False, False]
    with cudnn_attention_first(torch.device("cpu")):
        assert _backends_now() == before
    assert _backends_now() == before


def test_attention_maths_runs_in_cudnn_first_order(monkeypatch):
    """attend (NV attention, the decoupled cross-attention) enters the order for its tensors' device."""
    from artnvg_core.diffusion import attention_math

    devices = []
    monkeypatch.setattr(attention_math, "cudnn_attention_first",
                        lambda device: devices.append(device) or cudnn_attention_first(device))
    q = torch.randn(4, 6, 8)
    attention_math.neighbour_view_attention(q, q, q, heads=2, views=2)
    assert devices == [q.device]


@pytest.mark.cuda
def test_nv_attention_runs_on_cudnn_after_another_order_was_set():
    """As in a ComfyUI process: an order with flash attention first set and left by other code; the NV
    attention still runs on cuDNN's kernel (where this GPU has it)."""
    from torch.nn.attention import SDPBackend, sdpa_kernel

    from artnvg_core.diffusion.attention_math import neighbour_view_attention

    if torch.cuda.get_device_capability() < (8, 0):
        pytest.skip("cuDNN's attention needs compute capability 8.0 or later")
    q = torch.randn(8, 1024, 640, device="cuda", dtype=torch.float16)
    with sdpa_kernel([SDPBackend.FLASH_ATTENTION, SDPBackend.EFFICIENT_ATTENTION, SDPBackend.MATH,
                      SDPBackend.CUDNN_ATTENTION], set_priority=True):
        with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CUDA]) as profile:
            neighbour_view_attention(q, q, q, heads=10, views=4)
            torch.cuda.synchronize()
    kernels = [event.key for event in profile.key_averages()]
    assert any("cudnn" in name.lower() for name in kernels), kernels
    assert not any("flash_fwd" in name for name in kernels), kernels
