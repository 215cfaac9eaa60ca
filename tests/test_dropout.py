"""The CPU dropout of the transformers' training (`segmo.models.dropout`) and the training
attention that uses it: same distribution and expectation as PyTorch's, reproducible."""

from __future__ import annotations

import pytest
import torch

from segmo.models.dropout import LEVELS, Dropout, dropout
from segmo.models.transformer import attention


@pytest.mark.parametrize("p", [0.1, 0.2, 0.5, 0.9])
def test_drops_a_share_p_and_scales_the_rest_to_keep_the_expectation(p):
    torch.manual_seed(0)
    x = torch.full((1000, 1000), 3.0)
    y = dropout(x, p)
    dropped = float((y == 0).float().mean())
    assert abs(dropped - p) < 0.002  # binomial std 0.0005 at p = 0.5
    kept = y[y != 0]
    rounded = round(p * LEVELS) / LEVELS
    assert torch.all(kept == 3.0 / (1 - rounded))
    assert abs(float(y.mean()) - 3.0) < 0.01


def test_every_bit_pattern_is_used_so_neighbours_are_independent():
    # Four elements share one 64-bit draw: their masks must not be tied to each other.
    torch.manual_seed(1)
    keep = dropout(torch.ones(250_000, 4), 0.5) != 0
    both = float((keep[:, 0] & keep[:, 1]).float().mean())
    assert abs(both - 0.25) < 0.005
    assert all(abs(float(keep[:, j].float().mean()) - 0.5) < 0.005 for j in range(4))


def test_reproducible_under_manual_seed_and_different_without():
    x = torch.randn(33, 17)  # a size not divisible by four
    torch.manual_seed(5)
    a = dropout(x, 0.3)
    torch.manual_seed(5)
    b = dropout(x, 0.3)
    c = dropout(x, 0.3)
    assert torch.equal(a, b)
    assert not torch.equal(b, c)


def test_identity_in_eval_at_zero_and_below_the_resolution_and_zeros_at_one():
    x = torch.randn(8, 8)
    assert dropout(x, 0.2, training=False) is x
    assert dropout(x, 0.0) is x
    assert dropout(x, 1e-7) is x  # below 2^-17: rounds to keeping everything
    assert torch.equal(dropout(x, 1.0), torch.zeros_like(x))
    with pytest.raises(ValueError, match="p must be in"):
        dropout(x, 1.5)
    with pytest.raises(ValueError, match="p must be in"):
        dropout(x, -0.1)


def test_gradient_is_the_mask():
    torch.manual_seed(2)
    x = torch.randn(64, 32, requires_grad=True)
    y = dropout(x, 0.25)
    y.sum().backward()
    assert torch.equal(x.grad, torch.where(y != 0, 1 / (1 - 0.25), 0.0))


def test_module_follows_train_and_eval_like_nn_dropout():
    module = Dropout(0.4)
    assert isinstance(module, torch.nn.Dropout) and module.p == 0.4
    x = torch.ones(100, 100)
    assert torch.equal(module.eval()(x), x)
    assert float((module.train()(x) == 0).float().mean()) > 0.3


def test_other_devices_keep_pytorchs_kernel():
    x = torch.ones(4, 4, device="meta")
    assert dropout(x, 0.5).device.type == "meta"


def test_training_attention_on_the_cpu_is_sdpa_with_dropout_on_its_weights():
    torch.manual_seed(3)
    q, k, v = (torch.randn(2, 3, 5, 8) for _ in range(3))
    key_valid = torch.tensor([[True] * 5, [True, True, True, False, False]])
    reference = attention(q, k, v, key_valid)  # PyTorch's SDPA
    # A dropout below the resolution takes the training path and drops nothing.
    assert torch.allclose(attention(q, k, v, key_valid, dropout=1e-7), reference, atol=1e-6)
    # With dropout, invalid keys still take no part: their values change nothing.
    changed = v.clone()
    changed[1, :, 3:] = 1e6
    torch.manual_seed(4)
    a = attention(q, k, v, key_valid, dropout=0.3)
    torch.manual_seed(4)
    b = attention(q, k, changed, key_valid, dropout=0.3)
    assert torch.allclose(a, b)
    # And on average over masks, it is the attention without dropout.
    mean = torch.stack([attention(q, k, v, key_valid, dropout=0.3) for _ in range(4000)]).mean(0)
    assert torch.allclose(mean, reference, atol=0.06)
