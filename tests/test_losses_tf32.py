"""The TF32 switches: set inside the block, restored after, through PyTorch's new flag where it exists."""

from types import SimpleNamespace

import pytest
import torch

from artnvg_core.losses import tf32


@pytest.mark.parametrize("enabled, value", [(True, "tf32"), (False, "ieee")])
def test_switches_set_the_new_flag_and_restore_it(enabled, value):
    switches = ((tf32.matmul_tf32, torch.backends.cuda.matmul), (tf32.convolution_tf32, torch.backends.cudnn.conv))
    for switch, owner in switches:
        before = owner.fp32_precision
        opposite = "ieee" if enabled else "tf32"
        owner.fp32_precision = opposite
        try:
            with switch(enabled):
                assert owner.fp32_precision == value
            assert owner.fp32_precision == opposite
        finally:
            owner.fp32_precision = before


def test_legacy_flag_where_the_new_one_is_missing_and_restored_on_error():
    legacy = SimpleNamespace(allow_tf32=False)
    with pytest.raises(RuntimeError), tf32._switch(SimpleNamespace(), legacy, True):  # noqa: SLF001
        assert legacy.allow_tf32 is True
        raise RuntimeError("inside")
    assert legacy.allow_tf32 is False
    with tf32._switch(None, legacy, True):  # noqa: SLF001  (no new owner at all: PyTorch before cudnn.conv)
        assert legacy.allow_tf32 is True
    assert legacy.allow_tf32 is False
