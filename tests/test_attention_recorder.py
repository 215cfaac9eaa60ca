"""The attention recorder: it sees every motion query's weights and changes nothing."""

from __future__ import annotations

import copy

import pytest
import torch
from test_generation import TINY, text

from segmo import cpu
from segmo.generation import SamplingOptions, edit_tokens, generate_tokens
from segmo.models.attention_control import AttentionControl
from segmo.models.attention_recorder import is_recorded, record_attention
from segmo.models.cpu_inference import matmul_attention, use_cpu_kernels
from segmo.models.mask_transformer import MaskTransformer, MaskTransformerConfig
from segmo.models.residual_transformer import ResidualTransformer, ResidualTransformerConfig
from segmo.models.transformer import SelfAttention, Trunk, attention

STEPS = 4
LENGTHS = torch.tensor([40, 24])


def tiny_models(**overrides):
    """The tiny mask and residual transformers of `TINY` (+ `overrides`), seeded, eval mode."""
    torch.manual_seed(0)
    config = dict(TINY, **overrides)
    mask = MaskTransformer(MaskTransformerConfig(**config)).eval()
    residual = ResidualTransformer(ResidualTransformerConfig(**config, num_quantizers=3)).eval()
    with torch.no_grad():
        mask.classifier.weight.mul_(50)
        residual.code_embeddings.mul_(50)
    return mask, residual


def run(mask, residual, precision):
    return generate_tokens(mask, residual, *text(2), LENGTHS, options=SamplingOptions(steps=STEPS),
                           precision=precision, generator=torch.Generator().manual_seed(0))


PRECISIONS = [pytest.param("fp32"), pytest.param("bf16", marks=pytest.mark.skipif(
    not cpu.native_bf16(), reason="this CPU has no native bf16 (AVX-512 BF16, AMX or AVX-NE-CONVERT)"))]


@pytest.mark.parametrize("kernels", ["sdpa", "cpu_matmul"])
@pytest.mark.parametrize("precision", PRECISIONS)
def test_recording_changes_no_token_on_either_attention_path(precision, kernels):
    mask, residual = tiny_models()
    if kernels == "cpu_matmul":
        mask, residual = use_cpu_kernels(mask), use_cpu_kernels(residual)
    plain = run(mask, residual, precision)
    with record_attention({"mask": mask, "residual": residual}) as recording:
        recorded = run(mask, residual, precision)
    assert torch.equal(plain, recorded)
    assert recording.steps("mask") == STEPS and recording.steps("residual") == 2  # layers 1, 2
    assert len(recording.of("mask")) == STEPS * TINY["depth"]
    # Closed: the models are as they were (nothing wrapped, so nothing costs).
    for model in (mask, residual):
        assert all("forward_motion" not in m.__dict__ for m in model.modules() if isinstance(m, Trunk))
        expected = matmul_attention if kernels == "cpu_matmul" else attention
        assert all(m.attend is expected for m in model.modules() if isinstance(m, SelfAttention))
    assert torch.equal(run(mask, residual, precision), plain)


def test_maps_hold_the_conditional_rows_labelled_keys_and_normalised_weights():
    mask, residual = tiny_models()
    with record_attention({"mask": mask}) as recording:
        run(mask, residual, "fp32")
    n = int(LENGTHS.max()) // 4
    for m in recording.of("mask"):
        assert m.rows.tolist() == [0, 1]  # rows 2, 3 of the guidance batch: no condition
        assert m.key_labels == ["sentence", "segment 1", "segment 2", "segment 3",
                                *(f"motion {i}" for i in range(n))]
        assert m.prefix_length == 4 and m.weights.shape[:2] == (2, TINY["heads"])
        assert m.weights.shape[2] == m.queries.shape[1] and m.weights.shape[3] == 4 + n
        valid = m.key_valid[:, None, None, :].expand_as(m.weights)
        assert float(m.weights[~valid].abs().max()) == 0.0
        torch.testing.assert_close(m.weights.sum(-1), torch.ones(m.weights.shape[:3]))
        # text(2) leaves segment 3 of row 0 empty; row 1's motion has 6 of 10 tokens.
        assert not bool(m.key_valid[0, 3]) and not bool(m.key_valid[1, 4 + 6:].any())
    last = [m for m in recording.of("mask") if m.block == TINY["depth"] - 1]
    # The last block queries only the positions its step samples; the first step all.
    assert last[0].queries.shape[1] == n and last[-1].queries.shape[1] < n


def test_recorded_weights_are_the_ones_the_model_uses():
    mask, _ = tiny_models()
    outputs = []
    module = next(m for m in mask.modules() if isinstance(m, SelfAttention))
    original = module.attend

    def keep(q, k, v, key_valid, dropout=0.0):
        out = original(q, k, v, key_valid, dropout)
        outputs.append((out, v))
        return out

    module.attend = keep
    sentence, segments, segment_mask = text(2)
    indices = torch.randint(0, 16, (2, 10))
    token_mask = torch.ones(2, 10, dtype=torch.bool)
    with torch.no_grad(), record_attention({"mask": mask}) as recording:
        mask.forward_condition(indices, token_mask, mask.condition(sentence, segments, segment_mask))
    m = recording.of("mask")[0]
    out, v = outputs[-1]  # block 0's motion pass (the prefix encoding ran first)
    torch.testing.assert_close(torch.matmul(m.weights, v[m.rows]), out[m.rows], atol=1e-5, rtol=1e-5)


def test_edit_is_recorded_and_unchanged():
    mask, residual = tiny_models()
    tokens = run(mask, residual, "fp32")
    args = (mask, residual, tokens, (2, 5), *text(2))
    options = SamplingOptions(steps=STEPS)
    plain = edit_tokens(*args, options=options, generator=torch.Generator().manual_seed(1))
    with record_attention({"mask": copy.deepcopy(mask)}) as unused, \
            record_attention({"mask": mask, "residual": residual}) as recording:
        again = edit_tokens(*args, options=options, generator=torch.Generator().manual_seed(1))
    assert torch.equal(plain, again) and unused.maps == [] and recording.steps("mask") >= 1


@pytest.mark.parametrize("precision", PRECISIONS)
def test_weights_are_fp32_under_any_precision(precision):
    mask, residual = tiny_models()
    with record_attention({"mask": mask}) as recording:
        run(mask, residual, precision)
    weights = recording.of("mask")[0].weights
    assert weights.dtype == torch.float32
    torch.testing.assert_close(weights.sum(-1), torch.ones(weights.shape[:3]), atol=1e-6, rtol=0)


def test_a_recording_or_control_opened_inside_a_recording_leaves_it_recording():
    """An edit (attention control) or attention grounding (a recording) inside an open
    recording removed its trunk wrapper and unmarked its trunks on closing: the passes run
    after them in the same recording were recorded no more."""
    mask, residual = tiny_models()
    mask, residual = use_cpu_kernels(mask), use_cpu_kernels(residual)
    models = {"mask": mask, "residual": residual}
    plain = run(mask, residual, "fp32")
    with record_attention(models) as recording:
        run(mask, residual, "fp32")
        once = len(recording.maps)
        with AttentionControl(models).storing():
            run(mask, residual, "fp32")
        with record_attention({"mask": mask}):
            run(mask, residual, "fp32")
        assert is_recorded(mask) and is_recorded(residual)
        before = len(recording.maps)
        assert torch.equal(run(mask, residual, "fp32"), plain)
        assert len(recording.maps) - before == once
    assert not is_recorded(mask) and not is_recorded(residual)
    for model in (mask, residual):
        assert all("forward_motion" not in m.__dict__ for m in model.modules() if isinstance(m, Trunk))
        assert all(m.attend is matmul_attention for m in model.modules() if isinstance(m, SelfAttention))
