"""Mask/residual transformers, length estimator and their training helpers (tiny sizes)."""

from __future__ import annotations

import math

import pytest
import torch

from segmo.models.cpu_inference import matmul_attention
from segmo.models.length_estimator import LengthEstimator, LengthEstimatorConfig
from segmo.models.mask_transformer import (
    MaskTransformer,
    MaskTransformerConfig,
    mask_tokens,
    masked_token_loss,
)
from segmo.models.pretrained import load_pretrained
from segmo.models.residual_transformer import (
    ResidualTransformer,
    ResidualTransformerConfig,
    sample_layers,
)

TINY = dict(codebook_size=16, text_dim=8, max_segments=3, max_tokens=12, dim=32, depth=2,
            heads=2, ff_dim=64, dropout=0.1)


def tiny_mask(norm_first: bool = False, seed: int = 0) -> MaskTransformer:
    torch.manual_seed(seed)
    return MaskTransformer(MaskTransformerConfig(**TINY, norm_first=norm_first)).eval()


def tiny_residual(seed: int = 0) -> ResidualTransformer:
    torch.manual_seed(seed)
    return ResidualTransformer(ResidualTransformerConfig(**TINY, num_quantizers=3)).eval()


def text(b: int, a: int = 3, seed: int = 1):
    g = torch.Generator().manual_seed(seed)
    sentence = torch.randn(b, 8, generator=g)
    segments = torch.randn(b, a, 8, generator=g)
    segment_mask = torch.ones(b, a, dtype=torch.bool)
    return sentence, segments, segment_mask


@pytest.mark.parametrize("norm_first", [False, True])
def test_mask_transformer_shapes(norm_first):
    model = tiny_mask(norm_first)
    b, n = 3, 10
    indices = torch.randint(0, 18, (b, n))
    token_mask = torch.arange(n) < torch.tensor([10, 7, 1])[:, None]
    out = model(indices, token_mask, *text(b))
    assert out.logits.shape == (b, n, 16)
    assert out.motion_features.shape == (b, n, 32)
    assert out.segment_features.shape == (b, 3, 32)
    assert out.sentence_features.shape == (b, 32)
    assert torch.isfinite(out.logits).all()


def test_segment_order_is_an_input_but_not_on_the_alignment_side():
    """Segments are ordered: permuting them changes what the motion tokens see. The text
    side of alignment carries no order, so it is just permuted with them: the alignment
    loss cannot be met by slot position alone."""
    model = tiny_mask()
    b, n = 2, 8
    indices = torch.randint(0, 16, (b, n))
    token_mask = torch.ones(b, n, dtype=torch.bool)
    sentence, segments, segment_mask = text(b)
    order = torch.tensor([2, 0, 1])
    with torch.no_grad():
        out = model(indices, token_mask, sentence, segments, segment_mask)
        permuted = model(indices, token_mask, sentence, segments[:, order], segment_mask)
    assert not torch.allclose(out.motion_features, permuted.motion_features, atol=1e-3)
    # Equal up to fp32 rounding, not bit for bit: MKL's AVX2 sgemm (Intel CPUs without
    # AVX-512) rounds a row differently by its place in the batch (1.5e-8 measured). Any
    # order information would show at the scale of the order embeddings (~1e-2).
    torch.testing.assert_close(out.segment_features[:, order], permuted.segment_features,
                               rtol=1e-6, atol=1e-7)


def test_unordered_rows_take_segments_as_a_set():
    """Rows marked `unordered` (grounding's mode) ignore the segment order; the other rows
    of the same batch keep theirs."""
    model = tiny_mask()
    with torch.no_grad():
        model.prefix.order.normal_()  # trained-sized order embeddings, not init-sized ones
    b, n = 2, 8
    indices = torch.randint(0, 16, (b, n))
    token_mask = torch.ones(b, n, dtype=torch.bool)
    sentence, segments, segment_mask = text(b)
    segment_mask[1, 2] = False
    order = torch.tensor([2, 0, 1])
    unordered = torch.tensor([True, False])
    with torch.no_grad():
        out = model(indices, token_mask, sentence, segments, segment_mask, unordered=unordered)
        permuted = model(indices, token_mask, sentence, segments[:, order], segment_mask[:, order],
                         unordered=unordered)
    torch.testing.assert_close(out.motion_features[0], permuted.motion_features[0],
                               rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(out.logits[0], permuted.logits[0], rtol=1e-5, atol=1e-5)
    assert not torch.allclose(out.motion_features[1], permuted.motion_features[1], atol=1e-3)


def test_empty_segment_slots_change_nothing():
    model = tiny_mask()
    b, n = 2, 8
    indices = torch.randint(0, 17, (b, n))
    token_mask = torch.ones(b, n, dtype=torch.bool)
    sentence, segments, segment_mask = text(b)
    segment_mask[0, 2] = False
    segment_mask[1, 1:] = False
    zeros = segments.masked_fill(~segment_mask[..., None], 0.0)
    noise = torch.where(segment_mask[..., None], segments, torch.randn_like(segments) * 10)
    noise[1, 2] = float("nan")  # a cache may pad empty slots with anything
    a = model(indices, token_mask, sentence, zeros, segment_mask)
    c = model(indices, token_mask, sentence, noise, segment_mask)
    torch.testing.assert_close(a.logits, c.logits, rtol=0, atol=0)
    torch.testing.assert_close(a.motion_features, c.motion_features, rtol=0, atol=0)
    torch.testing.assert_close(a.segment_features[segment_mask], c.segment_features[segment_mask],
                               rtol=0, atol=0)
    # ...while a valid slot's content does matter.
    segment_mask[0, 2] = True
    d = model(indices, token_mask, sentence, noise, segment_mask)
    assert not torch.allclose(d.logits[0], c.logits[0])


def test_padded_tokens_do_not_affect_valid_outputs():
    model = tiny_mask(norm_first=True)
    n = 10
    indices = torch.randint(0, 16, (1, n))
    sentence, segments, segment_mask = text(1)
    alone = model(indices[:, :6], torch.ones(1, 6, dtype=torch.bool), sentence, segments,
                  segment_mask)
    token_mask = torch.arange(n)[None] < 6
    for fill in (0, 5, 17):
        padded = indices.clone()
        padded[:, 6:] = fill
        out = model(padded, token_mask, sentence, segments, segment_mask)
        torch.testing.assert_close(out.logits[:, :6], alone.logits, rtol=1e-5, atol=1e-5)


def test_drop_condition_removes_text():
    model = tiny_mask()
    b, n = 2, 6
    indices = torch.randint(0, 16, (b, n))
    token_mask = torch.ones(b, n, dtype=torch.bool)
    drop = torch.tensor([True, False])
    a = model(indices, token_mask, *text(b, seed=1), drop_condition=drop)
    c = model(indices, token_mask, *text(b, seed=2), drop_condition=drop)
    torch.testing.assert_close(a.logits[0], c.logits[0], rtol=0, atol=0)
    assert not torch.allclose(a.logits[1], c.logits[1])


@pytest.mark.parametrize("norm_first", [False, True])
def test_text_prefix_sees_the_text_only(norm_first):
    """Prefix tokens attend to the prefix alone: their outputs ignore the motion tokens, and
    a condition encoded once gives the same outputs as one encoded on every call."""
    model = tiny_mask(norm_first)
    b, n = 2, 9
    token_mask = torch.ones(b, n, dtype=torch.bool)
    cond = text(b)
    first = model(torch.randint(0, 18, (b, n)), token_mask, *cond)
    second = model(torch.randint(0, 18, (b, n)), token_mask, *cond)
    torch.testing.assert_close(first.segment_features, second.segment_features, rtol=0, atol=0)
    torch.testing.assert_close(first.sentence_features, second.sentence_features, rtol=0, atol=0)
    assert not torch.allclose(first.motion_features, second.motion_features)

    indices = torch.randint(0, 18, (b, n))
    condition = model.condition(*cond)
    assert condition.encoded is not None
    cached = model.forward_condition(indices, token_mask, condition)
    condition.encoded = None  # encoded again inside the call
    fresh = model.forward_condition(indices, token_mask, condition)
    torch.testing.assert_close(cached.logits, fresh.logits, rtol=0, atol=0)


def test_residual_passes_share_one_prefix_encoding():
    """The target layer enters with the motion inputs, so one encoded text prefix serves
    every layer's pass and gives what encoding it afresh gives."""
    model = tiny_residual()
    cond = text(2)
    indices = torch.randint(0, 16, (2, 6, 3))
    token_mask = torch.ones(2, 6, dtype=torch.bool)
    condition = model.condition(*cond)
    x = model.embed(indices, 2)
    shared = [model.forward_embedded(x, layer, token_mask, condition).logits for layer in (1, 2)]
    condition.encoded = None
    fresh = [model.forward_embedded(x, layer, token_mask, condition).logits for layer in (1, 2)]
    for a, c in zip(shared, fresh):
        torch.testing.assert_close(a, c, rtol=0, atol=0)
    # The layer embedding reaches the output through the trunk, not only through the tied projection.
    before = model.forward_embedded(x, torch.tensor([1, 1]), token_mask, condition).logits
    with torch.no_grad():
        model.layer_embeddings[1] += 1.0
    moved = model.forward_embedded(x, torch.tensor([1, 1]), token_mask, condition).logits
    assert not torch.allclose(before, moved)


@pytest.mark.parametrize("norm_first", [False, True])
def test_outputs_at_chosen_positions_match_the_full_pass(norm_first):
    """Asking for some positions (decoding asks for those it samples) gives exactly the
    full pass's outputs there, for both transformers; other positions still act as keys."""
    mask, residual = tiny_mask(norm_first).eval(), tiny_residual().eval()
    b, n = 3, 7
    token_mask = torch.arange(n) < torch.tensor([7, 5, 3])[:, None]
    positions = torch.tensor([[0, 4, 6], [1, 2, 3], [0, 1, 2]])
    rows = torch.arange(b)[:, None]
    with torch.inference_mode():
        indices = torch.randint(0, 16, (b, n))
        condition = mask.condition(*text(b))
        full = mask.forward_condition(indices, token_mask, condition)
        some = mask.forward_condition(indices, token_mask, condition, positions)
        assert some.logits.shape == (b, 3, 16)
        torch.testing.assert_close(some.logits, full.logits[rows, positions])
        torch.testing.assert_close(some.motion_features, full.motion_features[rows, positions])
        changed = indices.clone()
        changed[0, 5] = (changed[0, 5] + 1) % 16  # not asked for, still attended to
        moved = mask.forward_condition(changed, token_mask, condition, positions)
        assert not torch.allclose(moved.logits[0], some.logits[0])

        condition = residual.condition(*text(b))
        x = residual.embed(torch.randint(0, 16, (b, n, 3)), 2)
        for layer in (2, torch.tensor([1, 2, 1])):
            full = residual.forward_embedded(x, layer, token_mask, condition)
            some = residual.forward_embedded(x, layer, token_mask, condition, positions)
            torch.testing.assert_close(some.logits, full.logits[rows, positions])
    with pytest.raises(ValueError, match="positions must be"):
        mask.forward_condition(indices, token_mask, mask.condition(*text(b)), positions[0])


def test_dropped_condition_keeps_prefix_keys_finite():
    """A row with every prefix slot masked still gets finite prefix keys and values
    (PyTorch < 2.5 gives NaN to a query without any key), so NaN cannot reach the motion
    through masked values."""
    model = tiny_mask()
    condition = model.condition(*text(2), drop_condition=torch.tensor([True, False]))
    assert not bool(condition.mask[0].any())
    for block in condition.encoded.blocks:
        assert torch.isfinite(block.keys).all() and torch.isfinite(block.values).all()


@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
def test_inference_attention_matches_sdpa(dtype):
    """CPU inference attention (two matmuls) computes what SDPA's fused kernel does."""
    g = torch.Generator().manual_seed(0)
    q, k, v = (torch.randn(3, 2, length, 8, generator=g).to(dtype) for length in (5, 7, 7))
    key_valid = torch.ones(3, 7, dtype=torch.bool)
    key_valid[1, :3] = False
    key_valid[2, 4:] = False
    v[2, :, 4:] = 1e4  # masked values must not leak
    with torch.inference_mode():
        fast = matmul_attention(q, k, v, key_valid)
    reference = torch.nn.functional.scaled_dot_product_attention(
        q.float(), k.float(), v.float(), attn_mask=key_valid[:, None, None, :])
    tolerance = 1e-6 if dtype == torch.float32 else 2e-2
    torch.testing.assert_close(fast.float(), reference, rtol=tolerance, atol=tolerance)
    assert fast.dtype == dtype
    # With autograd the fused kernel runs, and the two agree.
    trained = matmul_attention(q.float().requires_grad_(), k.float(), v.float(), key_valid)
    torch.testing.assert_close(trained.detach(), reference, rtol=1e-6, atol=1e-6)


def test_too_many_segments_and_tokens_refused():
    model = tiny_mask()
    with pytest.raises(ValueError, match="segment slots"):
        model(torch.zeros(1, 4, dtype=torch.long), torch.ones(1, 4, dtype=torch.bool),
              *text(1, a=4))
    with pytest.raises(ValueError, match="max_tokens"):
        model(torch.zeros(1, 13, dtype=torch.long), torch.ones(1, 13, dtype=torch.bool), *text(1))


def test_mask_tokens_follows_schedule_and_split():
    g = torch.Generator().manual_seed(0)
    b, n, v = 4000, 12, 16
    lengths = torch.randint(1, n + 1, (b,), generator=g)
    token_mask = torch.arange(n) < lengths[:, None]
    indices = torch.randint(0, v, (b, n), generator=g)
    inputs, target = mask_tokens(indices, token_mask, v, torch.Generator().manual_seed(1))
    count = target.sum(dim=1)
    assert bool((count >= 1).all()) and bool((count <= lengths).all())
    assert not bool((target & ~token_mask).any())
    assert bool((inputs[~token_mask] == v + 1).all())
    assert bool((inputs[token_mask & ~target] == indices[token_mask & ~target]).all())
    masked = (inputs[target] == v).float().mean().item()
    assert 0.77 < masked < 0.83
    # mean of cos(πt/2) over U(0,1) is 2/π
    ratio = (count.float() / lengths).mean().item()
    assert 0.6 < ratio < 0.72
    again = mask_tokens(indices, token_mask, v, torch.Generator().manual_seed(1))
    assert torch.equal(again[0], inputs) and torch.equal(again[1], target)


def test_masked_token_loss_uses_masked_positions_only():
    g = torch.Generator().manual_seed(0)
    logits = torch.randn(2, 5, 16, generator=g)
    targets = torch.randint(0, 16, (2, 5), generator=g)
    target_mask = torch.tensor([[1, 0, 1, 0, 0], [0, 0, 0, 1, 0]], dtype=torch.bool)
    loss = masked_token_loss(logits, targets, target_mask)
    changed = logits.clone()
    changed[~target_mask] = 100.0
    torch.testing.assert_close(masked_token_loss(changed, targets, target_mask), loss)
    expected = torch.nn.functional.cross_entropy(logits[target_mask], targets[target_mask])
    torch.testing.assert_close(loss, expected)
    with pytest.raises(ValueError):
        masked_token_loss(logits, targets, torch.zeros_like(target_mask))


def test_round_trip_gives_identical_outputs(tmp_path):
    mask, residual = tiny_mask(norm_first=True), tiny_residual()
    length = LengthEstimator(LengthEstimatorConfig(text_dim=8, hidden=16, max_tokens=12)).eval()
    indices = torch.randint(0, 16, (2, 7, 3))
    token_mask = torch.ones(2, 7, dtype=torch.bool)
    cond = text(2)
    for model in (mask, residual, length):
        model.save_pretrained(tmp_path / model.kind, meta={"text_encoder": "stub"})
        loaded = load_pretrained(tmp_path / model.kind)
        assert type(loaded) is type(model) and loaded.meta["text_encoder"] == "stub"
        if model is mask:
            a, c = (m(indices[..., 0], token_mask, *cond).logits for m in (model, loaded))
        elif model is residual:
            a, c = (m(indices, 2, token_mask, *cond).logits for m in (model, loaded))
        else:
            a, c = model(cond[0]), loaded(cond[0])
        torch.testing.assert_close(a, c, rtol=0, atol=0)
    with pytest.raises(ValueError, match="not a 'mask' model"):
        MaskTransformer.from_pretrained(tmp_path / "residual")


def test_a_mask_directory_with_the_former_alignment_fields_loads(tmp_path):
    """Mask config.json files written before the alignment loss moved to the task hold its
    settings (method, temperature, weight, segmenter) and max_segments in `alignment`: they
    are read and ignored; the head is rebuilt from out_dim alone."""
    import json

    from segmo.models.alignment import AlignmentConfig

    torch.manual_seed(0)
    model = MaskTransformer(MaskTransformerConfig(**TINY, alignment=AlignmentConfig(out_dim=8)))
    path = model.eval().save_pretrained(tmp_path / "mask")
    payload = json.loads((path / "config.json").read_text())
    assert payload["config"]["alignment"] == {"out_dim": 8}
    payload["config"]["alignment"].update(method="in_sample", temperature=0.1, weight=1.0,
                                          segmenter="uniform", max_segments=3)
    (path / "config.json").write_text(json.dumps(payload))
    loaded = load_pretrained(path)
    assert loaded.config.alignment == AlignmentConfig(out_dim=8)
    h, segments = torch.randn(2, 5, 32), torch.randn(2, 3, 32)
    spans = torch.tensor([[[0, 2], [1, 5]]]).expand(2, 2, 2)
    old, new = model.alignment, loaded.alignment
    torch.testing.assert_close(new.embed_text(segments), old.embed_text(segments), rtol=0, atol=0)
    torch.testing.assert_close(new.embed_motion(h, spans), old.embed_motion(h, spans), rtol=0, atol=0)


def test_residual_output_tied_to_layer_embedding():
    model = tiny_residual()
    assert model.output_weight(2).data_ptr() == model.code_embeddings[2].data_ptr()
    shapes = [p.shape for name, p in model.named_parameters() if name != "code_embeddings"]
    assert (16, 32) not in shapes, "a separate output projection exists"
    indices = torch.randint(0, 16, (2, 6, 3))
    token_mask = torch.ones(2, 6, dtype=torch.bool)
    cond = text(2)
    before = model(indices, 2, token_mask, *cond).logits
    with torch.no_grad():
        model.code_embeddings[2, 5] += 1.0  # layer 2 is output-only when predicting layer 2
    after = model(indices, 2, token_mask, *cond).logits
    changed = (after - before).abs().amax(dim=(0, 1)) > 0
    assert changed.tolist() == [c == 5 for c in range(16)]
    # gradient flows from the layer-2 logits into the layer-2 embedding table
    model.zero_grad()
    model(indices, 2, token_mask, *cond).logits.sum().backward()
    assert model.code_embeddings.grad[2].abs().sum() > 0


def test_residual_input_uses_lower_layers_only():
    model = tiny_residual()
    indices = torch.randint(0, 16, (2, 6, 3))
    token_mask = torch.ones(2, 6, dtype=torch.bool)
    cond = text(2)
    a = model(indices, 1, token_mask, *cond).logits
    changed = indices.clone()
    changed[..., 1:] = torch.randint(0, 16, (2, 6, 2))
    torch.testing.assert_close(model(changed, 1, token_mask, *cond).logits, a, rtol=0, atol=0)
    dropped = indices.clone()
    dropped[..., 1] = -1  # −1 embeds as zero: layer 2 sees only layer 0
    x = model.embed(dropped, 2)
    torch.testing.assert_close(x, model.embed_layer(indices[..., 0], 0))
    # per-sample layers agree with the int path
    per_sample = model(indices, torch.tensor([1, 2]), token_mask, *cond).logits
    torch.testing.assert_close(per_sample[0], a[0], rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(per_sample[1], model(indices, 2, token_mask, *cond).logits[1],
                               rtol=1e-5, atol=1e-5)
    with pytest.raises(ValueError, match="layer must be in 1..2"):
        model(indices, 0, token_mask, *cond)


def layer_probabilities(num_quantizers: int) -> list[float]:
    """Exact P(j) of `sample_layers` for j = 1..q−1: P(j ≤ k) = (2/π)·arccos(1 − k/(q−1))."""
    cdf = [2 / math.pi * math.acos(1 - k / (num_quantizers - 1)) for k in range(num_quantizers)]
    return [cdf[k] - cdf[k - 1] for k in range(1, num_quantizers)]


def test_sample_layers_favours_low_layers():
    layers = sample_layers(40000, 6, torch.Generator().manual_seed(0))
    assert int(layers.min()) == 1 and int(layers.max()) == 5
    freq = torch.bincount(layers, minlength=6)[1:].float() / layers.numel()
    expected = torch.tensor(layer_probabilities(6))
    torch.testing.assert_close(freq, expected, rtol=0, atol=0.01)
    assert freq[0] > freq[1] > freq[4]


def test_length_estimator_sample():
    model = LengthEstimator(LengthEstimatorConfig(text_dim=8, hidden=16, max_tokens=12)).eval()
    sentence = torch.randn(50, 8)
    assert model(sentence).shape == (50, 12)
    frames = model.sample(sentence, torch.Generator().manual_seed(0))
    assert bool((frames % 4 == 0).all()) and int(frames.min()) >= 4 and int(frames.max()) <= 48
    assert torch.equal(frames, model.sample(sentence, torch.Generator().manual_seed(0)))
    assert model.frames_to_classes(torch.tensor([4, 48])).tolist() == [0, 11]
    with pytest.raises(ValueError, match="multiples of 4"):
        model.frames_to_classes(torch.tensor([6]))


def test_linear_fast_paths_match_f_linear():
    """Where this CPU has them (segmo.cpu), the oneDNN paths run and match F.linear; where
    it lacks one (bf16 without AVX-512), the layer is F.linear (tests/test_cpu.py simulates
    those CPUs on any host)."""
    from segmo import cpu
    from segmo.models.cpu_inference import PackedLinear

    torch.manual_seed(0)
    layer = PackedLinear(16, 24, activation="gelu")
    x = torch.randn(3, 5, 16)
    reference = torch.nn.functional.gelu(torch.nn.functional.linear(x, layer.weight, layer.bias))
    with torch.inference_mode():
        torch.testing.assert_close(layer(x), reference, rtol=1e-5, atol=1e-5)
    assert set(layer._packed) == ({"fp32"} if cpu.onednn_linear() else set())
    assert layer(x).requires_grad  # training path keeps autograd
    with torch.inference_mode(), torch.autocast("cpu", dtype=torch.bfloat16):
        fast = layer(x)
        assert ("bf16" in layer._packed) == (cpu.onednn_linear() and cpu.onednn_bf16())
        assert fast.dtype == torch.bfloat16
        torch.testing.assert_close(fast.float(), reference, rtol=0.05, atol=0.05)
        with torch.no_grad():
            layer.weight.mul_(2)  # the bf16 copy must follow in-place updates
        refreshed = layer(x).float()
    doubled = torch.nn.functional.gelu(torch.nn.functional.linear(x, layer.weight, layer.bias))
    torch.testing.assert_close(refreshed, doubled, rtol=0.05, atol=0.05)
    # ...and so must the fp32 packed weights; a used layer still copies and pickles.
    with torch.inference_mode():
        torch.testing.assert_close(layer(x), doubled, rtol=1e-5, atol=1e-5)
    import copy
    import pickle

    for clone in (copy.deepcopy(layer), pickle.loads(pickle.dumps(layer))):
        with torch.inference_mode():
            torch.testing.assert_close(clone(x), doubled, rtol=1e-5, atol=1e-5)


def test_memory_slots_are_attended_in_every_row_and_zero_slots_is_todays_model():
    from segmo.models.attention_recorder import record_attention
    from segmo.models.mask_transformer import MaskTransformer, MaskTransformerConfig

    tiny = dict(codebook_size=16, text_dim=8, max_segments=3, max_tokens=12, dim=32, depth=2,
                heads=2, ff_dim=64, dropout=0.0)
    torch.manual_seed(0)
    plain = MaskTransformer(MaskTransformerConfig(**tiny)).eval()
    torch.manual_seed(0)
    zero = MaskTransformer(MaskTransformerConfig(**tiny, memory_slots=0)).eval()
    assert plain.state_dict().keys() == zero.state_dict().keys()
    torch.manual_seed(0)
    slots = MaskTransformer(MaskTransformerConfig(**tiny, memory_slots=4)).eval()
    assert slots.trunk.memory.shape == (4, 32)
    g = torch.Generator().manual_seed(1)
    sentence, segments = torch.randn(2, 8, generator=g), torch.randn(2, 3, 8, generator=g)
    segment_mask = torch.ones(2, 3, dtype=torch.bool)
    ids = torch.randint(0, 16, (2, 6), generator=g)
    token_mask = torch.ones(2, 6, dtype=torch.bool)
    drop = torch.tensor([False, True])
    with torch.no_grad():
        a = plain(ids, token_mask, sentence, segments, segment_mask, drop).logits
        b = zero(ids, token_mask, sentence, segments, segment_mask, drop).logits
        assert torch.equal(a, b)
        with record_attention({"mask": slots}) as recording:
            out = slots(ids, token_mask, sentence, segments, segment_mask, drop).logits
    assert torch.isfinite(out).all()
    m = recording.of("mask")[0]
    # The dropped row is not recorded; the memory keys follow the text keys.
    assert m.rows.tolist() == [0]
    assert m.key_labels[4:8] == ["memory 0", "memory 1", "memory 2", "memory 3"]
    assert m.text_length == 4 and m.prefix_length == 8
    assert float(m.weights[..., 4:8].sum(-1).min()) > 0  # the slots are attended
    # The memory's keys do not depend on the text: the same for both rows.
    encoded = slots.condition(sentence, segments, segment_mask, drop).encoded
    keys = encoded.blocks[1].keys[:, :, 4:]
    assert torch.equal(keys[0], keys[1]) and encoded.conditional_rows().tolist() == [True, False]
    # The unconditional row attends to the memory (its only prefix keys).
    assert bool(encoded.blocks[0].mask[1, 4:].all()) and not bool(encoded.blocks[0].mask[1, :4].any())


def test_memory_slots_generate_and_survive_save_and_load(tmp_path):
    from segmo.generation import SamplingOptions, generate_tokens
    from segmo.models.mask_transformer import MaskTransformer, MaskTransformerConfig
    from segmo.models.pretrained import load_pretrained

    torch.manual_seed(0)
    model = MaskTransformer(MaskTransformerConfig(
        codebook_size=16, text_dim=8, max_segments=3, max_tokens=12, dim=32, depth=2, heads=2,
        ff_dim=64, memory_slots=3))
    loaded = load_pretrained(model.save_pretrained(tmp_path / "mask"))
    assert loaded.config.memory_slots == 3 and torch.equal(loaded.trunk.memory, model.trunk.memory)
    g = torch.Generator().manual_seed(2)
    text = (torch.randn(2, 8, generator=g), torch.randn(2, 3, 8, generator=g),
            torch.ones(2, 3, dtype=torch.bool))

    def run(m):
        return generate_tokens(m, None, *text, torch.tensor([48, 20]),
                               options=SamplingOptions(steps=4),
                               generator=torch.Generator().manual_seed(0))

    tokens = run(model)
    assert torch.equal(tokens, run(loaded)) and tokens.shape == (2, 12, 1)


def test_memory_keys_are_encoded_once_in_inference_and_again_when_anything_changes():
    from segmo.models.cpu_inference import use_cpu_kernels
    from segmo.models.mask_transformer import MaskTransformer, MaskTransformerConfig

    torch.manual_seed(0)
    model = MaskTransformer(MaskTransformerConfig(
        codebook_size=16, text_dim=8, max_segments=3, max_tokens=12, dim=32, depth=2, heads=2,
        ff_dim=64, memory_slots=3)).eval()
    trunk = model.trunk

    def fresh():  # what the slots encode to, never cached
        m, valid, out = trunk.memory[None], torch.ones(1, 3, dtype=torch.bool), []
        for block in trunk.blocks:
            m, kv = block(m, valid)
            out.append(kv)
        return out

    with torch.no_grad():
        first = trunk.memory_keys(torch.float32)
        assert trunk.memory_keys(torch.float32) is first  # kept
        for (k, v), (k0, v0) in zip(first, fresh(), strict=True):
            assert torch.equal(k, k0) and torch.equal(v, v0)
        trunk.blocks[1].attention.qkv.bias.add_(1.0)  # an in-place update: encoded again
        second = trunk.memory_keys(torch.float32)
        assert second is not first and not torch.equal(second[1][0], first[1][0])
        assert torch.equal(second[1][0], fresh()[1][0])
        use_cpu_kernels(model)  # other kernels: encoded again
        assert trunk.memory_keys(torch.float32) is not second
    model.train()  # training never keeps them (dropout, gradients)
    with torch.no_grad():
        assert trunk.memory_keys(torch.float32) is not trunk.memory_keys(torch.float32)
    model.eval()
    assert trunk.memory_keys(torch.float32)[0][0].requires_grad  # with gradients: not kept
    assert trunk.__dict__["_memory_cache"] is None


@pytest.mark.parametrize("norm_first", [False, True])
def test_prefix_keys_are_those_of_every_slot_run_through_every_block_in_full(norm_first):
    # The prefix pass runs the valid slots alone (packed) and the last block's keys and
    # values alone: the same keys at the valid slots as the full pass over all slots.
    from segmo.models.transformer import Trunk

    torch.manual_seed(0)
    trunk = Trunk(32, 3, 2, 64, 0.0, norm_first, 12, memory_slots=2).eval()
    prefix = torch.randn(3, 4, 32)
    mask = torch.tensor([[True, True, False, False], [True] * 4, [False] * 4])
    among = mask | ~mask.any(1, keepdim=True)
    with torch.no_grad():
        encoded = trunk.encode_prefix(prefix, mask)
        x, m = prefix, trunk.memory[None]
        for block, kv in zip(trunk.blocks, encoded.blocks, strict=True):
            x, (keys, values) = block(x, among)
            m, (memory_keys, memory_values) = block(m, torch.ones(1, 2, dtype=torch.bool))
            for got, full in ((kv.keys, keys), (kv.values, values)):
                torch.testing.assert_close(got[:, :, :4].transpose(1, 2)[mask],
                                           full.transpose(1, 2)[mask], rtol=1e-5, atol=1e-6)
                # A row without a valid slot (its condition dropped): zeros, finite.
                assert not got[2, :, :4].any()
            assert torch.equal(kv.keys[:, :, 4:], memory_keys.expand(3, -1, -1, -1))
            assert torch.equal(kv.values[:, :, 4:], memory_values.expand(3, -1, -1, -1))


def test_packed_prefix_pass_trains_with_finite_gradients_and_refuses_other_keys():
    from segmo.models.transformer import SelfAttention, Trunk

    torch.manual_seed(0)
    trunk = Trunk(32, 2, 2, 64, 0.2, False, 12).train()
    prefix = torch.randn(2, 3, 32, requires_grad=True)
    mask = torch.tensor([[True, False, False], [False, False, False]])
    encoded = trunk.encode_prefix(prefix, mask)
    sum(b.keys.sum() + b.values.sum() for b in encoded.blocks).backward()
    assert torch.isfinite(prefix.grad).all() and prefix.grad[0, 0].abs().sum() > 0
    assert not prefix.grad[:, 1:].any() and not prefix.grad[1].any()  # padding: no part
    assert all(torch.isfinite(p.grad).all() for p in trunk.parameters() if p.grad is not None)
    attention = SelfAttention(32, 2, 0.0)
    with pytest.raises(ValueError, match="packed x takes no prefix and no queries"):
        attention(torch.randn(1, 32), mask, queries=torch.zeros(2, 1, dtype=torch.long))
