"""Sampling, masked/residual decoding with classifier-free guidance, editing (tiny models)."""

from __future__ import annotations

import pytest
import torch

from segmo.errors import SegmoError
from segmo.generation import (
    SamplingOptions,
    decode_tokens,
    edit_tokens,
    generate_tokens,
    guidance_condition,
    guided_logits,
    sample_tokens,
)
from segmo.generation import generate as generate_module
from segmo.generation.sampling import MAX_SCALE, SCALES, top_k_count
from segmo.models.mask_transformer import MaskTransformer, MaskTransformerConfig
from segmo.models.residual_transformer import ResidualTransformer, ResidualTransformerConfig

TINY = dict(codebook_size=16, text_dim=8, max_segments=3, max_tokens=12, dim=32, depth=2,
            heads=2, ff_dim=64, dropout=0.1)


@pytest.fixture(scope="module")
def models():
    torch.manual_seed(0)
    mask = MaskTransformer(MaskTransformerConfig(**TINY))
    residual = ResidualTransformer(ResidualTransformerConfig(**TINY, num_quantizers=3))
    # Sharper logits than the 0.02-std initialisation, so that the text matters.
    with torch.no_grad():
        mask.classifier.weight.mul_(50)
        residual.code_embeddings.mul_(50)
    return mask, residual


def text(b: int, seed: int = 1):
    g = torch.Generator().manual_seed(seed)
    segment_mask = torch.ones(b, 3, dtype=torch.bool)
    segment_mask[0, 2] = False
    return torch.randn(b, 8, generator=g), torch.randn(b, 3, 8, generator=g), segment_mask


class StubTokenizer:
    """decode(indices (b, n, q), lengths) → (b, 4n, d): sum of per-layer codes, upsampled ×4
    (each position on its own, so lengths change nothing)."""

    codebook_size, num_quantizers, code_dim = 16, 3, 5

    def __init__(self) -> None:
        self.codes = torch.randn(3, 16, 5, generator=torch.Generator().manual_seed(0))

    def decode(self, indices: torch.Tensor, lengths: torch.Tensor | None = None) -> torch.Tensor:
        assert indices.shape[2] == self.num_quantizers
        picked = self.codes[torch.arange(3), indices.clamp(min=0)]  # (b, n, q, d)
        summed = (picked * (indices >= 0)[..., None]).sum(2)
        return summed.repeat_interleave(4, dim=1)


def test_top_k_count():
    assert top_k_count(512, 0.1) == 52 and top_k_count(16, 0.01) == 1 and top_k_count(8, 1.0) == 8
    with pytest.raises(ValueError):
        top_k_count(512, 0.0)


@pytest.mark.parametrize("sampler", ["categorical", "gumbel"])
def test_sample_tokens(sampler):
    logits = torch.randn(300, 40)
    tokens, conf = sample_tokens(logits, 0.1, 1.0, sampler, torch.Generator().manual_seed(0))
    again, _ = sample_tokens(logits, 0.1, 1.0, sampler, torch.Generator().manual_seed(0))
    assert torch.equal(tokens, again)
    top4 = logits.topk(4, dim=-1).indices
    assert bool((top4 == tokens[:, None]).any(dim=1).all()), "drew outside the top-k"
    kept = logits.masked_fill(logits < logits.topk(4, dim=-1).values[:, -1:], float("-inf"))
    torch.testing.assert_close(conf, kept.softmax(-1).gather(-1, tokens[:, None])[:, 0])
    greedy, _ = sample_tokens(logits, 0.1, 0.0, sampler)
    assert torch.equal(greedy, logits.argmax(-1))
    # both samplers draw from softmax(top-k logits / T): empirical frequencies match
    probs = torch.tensor([0.5, 0.25, 0.15, 0.1])
    logits = torch.cat([probs.log(), torch.full((6,), -5.0)])  # 10 codes, top-4 kept
    many, _ = sample_tokens(logits.expand(20000, 10), 0.4, 2.0, sampler,
                            torch.Generator().manual_seed(1))
    freq = torch.bincount(many, minlength=10).float() / 20000
    expected = (probs.log() / 2.0).softmax(-1)
    torch.testing.assert_close(freq[:4], expected, rtol=0, atol=0.015)
    assert float(freq[4:].sum()) == 0.0


@pytest.mark.parametrize("sampler", ["categorical", "gumbel"])
def test_a_tiny_temperature_draws_the_best_token(sampler):
    # 1e-40: values / temperature overflowed to inf, the probabilities were NaN and the
    # categorical draw took the worst token.
    logits = torch.tensor([[1.0, 3.0, 2.0, 0.5], [0.0, -1.0, 4.0, 2.0]])
    for temperature in (1e-3, 1e-30, 1e-40):
        tokens, confidence = sample_tokens(logits, 1.0, temperature, sampler,
                                           torch.Generator().manual_seed(0))
        assert tokens.tolist() == [1, 2], temperature
        torch.testing.assert_close(confidence, logits.softmax(-1).amax(-1))


@pytest.mark.parametrize("sampler", ["categorical", "gumbel"])
def test_confidence_does_not_depend_on_the_temperature(sampler):
    # At T = 1e-3 the drawn tokens' probabilities under softmax(logits / T) were 1 almost
    # everywhere, so re-masking "the least confident" fell to the last positions, while
    # T = 0 ranked by softmax(logits). A draw's confidence is its temperature-free probability.
    logits = torch.randn(200, 64, generator=torch.Generator().manual_seed(2)) * 3
    greedy, greedy_conf = sample_tokens(logits, 0.1, 0.0, sampler)
    for temperature in (1e-6, 1e-3):
        tokens, conf = sample_tokens(logits, 0.1, temperature, sampler, torch.Generator().manual_seed(0))
        assert torch.equal(tokens, greedy)
        torch.testing.assert_close(conf, greedy_conf)
        assert len(conf.unique()) > 150  # ranks, not ties
    tokens, conf = sample_tokens(logits, 0.1, 0.5, sampler, torch.Generator().manual_seed(0))
    top = logits.topk(7, dim=-1).values
    expected = (logits.gather(-1, tokens[:, None])[:, 0] - top.logsumexp(-1)).exp()
    torch.testing.assert_close(conf, expected)


@pytest.mark.parametrize("name", SCALES)
def test_a_scale_that_would_overflow_the_guided_logits_is_refused(name):
    SamplingOptions(**{name: MAX_SCALE})
    with pytest.raises(SegmoError, match=f"{name} must be in"):
        SamplingOptions(**{name: 1e308})


def test_guidance_scale_one_equals_conditional(models):
    mask, _ = models
    mask.eval()
    b, n = 3, 9
    sentence, segments, segment_mask = text(b)
    indices = torch.randint(0, 17, (b, n))
    token_mask = torch.arange(n) < torch.tensor([9, 5, 2])[:, None]
    condition = guidance_condition(mask, sentence, segments, segment_mask)
    both = mask.forward_condition(torch.cat([indices, indices]),
                                  torch.cat([token_mask, token_mask]), condition).logits
    conditional = mask(indices, token_mask, sentence, segments, segment_mask).logits
    unconditional = mask(indices, token_mask, sentence, segments, segment_mask,
                         drop_condition=torch.ones(b, dtype=torch.bool)).logits
    torch.testing.assert_close(guided_logits(both, 1.0), conditional, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(guided_logits(both, 0.0), unconditional, rtol=1e-5, atol=1e-5)
    assert not torch.allclose(conditional, unconditional)


def test_generate_shapes_padding_and_seeds(models):
    mask, residual = models
    mask.train()  # generation must switch to eval and restore each model's mode
    residual.eval()
    lengths = torch.tensor([48, 20, 4])
    cond = text(3)
    rng_state = torch.random.get_rng_state()
    out = generate_tokens(mask, residual, *cond, lengths, options=SamplingOptions(steps=4),
                          generator=torch.Generator().manual_seed(0))
    assert torch.equal(torch.random.get_rng_state(), rng_state), "global RNG was used"
    assert mask.training and not residual.training
    mask.eval()
    assert out.shape == (3, 12, 3) and out.dtype == torch.long
    valid = torch.arange(12) < (lengths // 4)[:, None]
    assert bool((out[valid] >= 0).all()) and bool((out[valid] < 16).all())
    assert bool((out[~valid] == -1).all())
    same = generate_tokens(mask, residual, *cond, lengths, options=SamplingOptions(steps=4),
                           generator=torch.Generator().manual_seed(0))
    other = generate_tokens(mask, residual, *cond, lengths, options=SamplingOptions(steps=4),
                            generator=torch.Generator().manual_seed(1))
    assert torch.equal(out, same)
    assert not torch.equal(out, other)
    base_only = generate_tokens(mask, None, *cond, lengths, options=SamplingOptions(steps=4),
                                generator=torch.Generator().manual_seed(0))
    assert torch.equal(base_only[..., 0], out[..., 0])


@pytest.mark.parametrize("precision,sampler",
                         [("bf16", "gumbel"), ("fp32", "gumbel"), ("auto", "categorical")])
def test_generate_precision_and_sampler(models, precision, sampler):
    mask, residual = models
    out = generate_tokens(mask, residual, *text(2), torch.tensor([40, 12]),
                          options=SamplingOptions(steps=3, sampler=sampler),
                          precision=precision,
                          generator=torch.Generator().manual_seed(0))
    again = generate_tokens(mask, residual, *text(2), torch.tensor([40, 12]),
                            options=SamplingOptions(steps=3, sampler=sampler),
                            precision=precision,
                            generator=torch.Generator().manual_seed(0))
    assert out.shape == (2, 10, 3) and torch.equal(out, again)
    assert bool((out[1, 3:] == -1).all()) and bool((out[0] >= 0).all())


def test_one_batched_guidance_pass_per_step(models, monkeypatch):
    mask, residual = models
    batches: list[int] = []
    original = MaskTransformer.forward_condition

    computed: list[int] = []

    def counting(self, indices, token_mask, condition, positions=None, sink_rows=None):
        batches.append(indices.shape[0])
        computed.append(indices.shape[1] if positions is None else positions.shape[1])
        return original(self, indices, token_mask, condition, positions, sink_rows)

    monkeypatch.setattr(MaskTransformer, "forward_condition", counting)
    generate_tokens(mask, residual, *text(3), torch.tensor([16, 16, 8]),
                    options=SamplingOptions(steps=5),
                    generator=torch.Generator().manual_seed(0))
    # Step 0: 3 conditional rows and 2 unconditional ones (the two 16-frame rows are all
    # masked, the same input). Step 1 (t = ¼) masks everything again (⌈0.92·4⌉ = 4,
    # ⌈0.92·2⌉ = 2): the same input as step 0, no pass. Then one pass per step, of 6 rows
    # unless two unconditional rows happen to hold the same tokens.
    assert batches[0] == 5 and len(batches) == 4 and all(5 <= rows <= 6 for rows in batches)
    # Only the sampled positions reach the last block: ⌈γ(t)·4⌉ for t = 0, ½, ¾, 1.
    assert computed == [4, 3, 2, 1]


def plain_passes(monkeypatch):
    """Masked decoding without its exact savings: every step's pass over all 2b rows."""
    monkeypatch.setattr(generate_module, "is_recorded", lambda model: True)
    monkeypatch.setattr(generate_module, "_guidance_pass",
                        lambda model, ids, token_mask, condition, positions, sink_rows=None:
                        model.forward_condition(ids, token_mask, condition, positions,
                                                sink_rows).logits)


@pytest.mark.parametrize("lengths,steps", [([48, 48, 48, 20], 10), ([16, 40, 8], 4), ([48], 10)])
def test_exact_savings_keep_every_token(models, monkeypatch, lengths, steps):
    # Reusing a repeated step's pass and computing identical unconditional rows once
    # change no token of a generation or an edit.
    mask, residual = models
    b = len(lengths)

    def run():
        tokens = generate_tokens(mask, residual, *text(b), torch.tensor(lengths),
                                 options=SamplingOptions(steps=steps),
                                 generator=torch.Generator().manual_seed(5))
        edited = edit_tokens(mask, residual, tokens, (1, 5), *text(b, seed=6),
                             options=SamplingOptions(steps=steps),
                             generator=torch.Generator().manual_seed(6))
        return torch.cat([tokens, edited])

    saved = run()
    plain_passes(monkeypatch)
    assert torch.equal(saved, run())


def test_unconditional_rows_computed_once_match_the_full_batch(models):
    # The logits of a deduplicated pass equal those of the full guidance batch.
    mask, _ = models
    b, n = 4, 12
    condition = guidance_condition(mask, *text(b))
    ids = torch.full((2 * b, n), mask.mask_id)
    token_mask = torch.ones(2 * b, n, dtype=torch.bool)
    token_mask[[2, 6], 8:] = False
    with torch.inference_mode():
        mask.eval()
        full = mask.forward_condition(ids, token_mask, condition).logits
        deduplicated = generate_module._guidance_pass(mask, ids, token_mask, condition, None)
    valid = token_mask[..., None].expand_as(full)
    torch.testing.assert_close(deduplicated[valid], full[valid], rtol=1e-5, atol=1e-5)


def test_sampling_only_the_drawn_positions_changes_no_token(models, monkeypatch):
    mask, residual = models
    lengths = torch.tensor([48, 32, 20])

    def run():
        tokens = generate_tokens(mask, residual, *text(3), lengths,
                                 options=SamplingOptions(steps=6),
                                 generator=torch.Generator().manual_seed(3))
        edited = edit_tokens(mask, residual, tokens, (2, 6), *text(3, seed=4),
                             options=SamplingOptions(steps=3),
                             generator=torch.Generator().manual_seed(4))
        return torch.cat([tokens, edited])

    pruned = run()
    monkeypatch.setattr(generate_module, "_sampled_positions", lambda select: (None, select))
    assert torch.equal(pruned, run())


@pytest.mark.parametrize("bad", [[46], [0], [52], [-4]])
def test_bad_lengths_refused(models, bad):
    mask, residual = models
    with pytest.raises(ValueError, match="multiples of 4 frames in \\[4, 48\\]"):
        generate_tokens(mask, residual, *text(1), torch.tensor(bad))


def test_edit_keeps_tokens_outside_span(models):
    mask, residual = models
    lengths = torch.tensor([48, 32, 24, 48])
    original = generate_tokens(mask, residual, *text(4), lengths, options=SamplingOptions(steps=4),
                               generator=torch.Generator().manual_seed(0))
    start, end = 3, 7
    edited = edit_tokens(mask, residual, original, (start, end), *text(4, seed=9),
                         options=SamplingOptions(steps=4),
                         generator=torch.Generator().manual_seed(5))
    outside = torch.ones(12, dtype=torch.bool)
    outside[start:end] = False
    assert torch.equal(edited[:, outside], original[:, outside])  # base and residual layers
    inside = edited[:, start:end]
    valid = (torch.arange(start, end) < (lengths // 4)[:, None])[..., None]
    assert bool((inside >= 0)[valid.expand_as(inside)].all())
    assert bool((inside == -1)[~valid.expand_as(inside)].all())
    assert not torch.equal(inside, original[:, start:end])
    # per-sample spans; a span over padding leaves that sample untouched
    spans = torch.tensor([[0, 2], [5, 8], [10, 12], [11, 12]])
    edited = edit_tokens(mask, residual, original, spans, *text(4, seed=9),
                         options=SamplingOptions(steps=2),
                         generator=torch.Generator().manual_seed(5))
    for i, (s, e) in enumerate(spans.tolist()):
        keep = torch.ones(12, dtype=torch.bool)
        keep[s:e] = False
        assert torch.equal(edited[i, keep], original[i, keep])
    assert torch.equal(edited[2], original[2])
    with pytest.raises(ValueError, match="span"):
        edit_tokens(mask, residual, original, (5, 5), *text(4))
    with pytest.raises(ValueError, match="residual_model is needed"):
        edit_tokens(mask, None, original, (0, 2), *text(4))


def test_decode_tokens_with_stub_tokenizer(models):
    mask, residual = models
    tokenizer = StubTokenizer()
    lengths = torch.tensor([48, 20])
    indices = generate_tokens(mask, residual, *text(2), lengths, options=SamplingOptions(steps=2),
                              generator=torch.Generator().manual_seed(0))
    features = decode_tokens(tokenizer, indices, lengths)
    assert features.shape == (2, 48, 5)
    assert bool((features[1, 20:] == 0).all()) and bool((features[1, :20] != 0).any())
    base = decode_tokens(tokenizer, indices[..., :1], lengths)  # missing layers → −1
    expected = tokenizer.codes[0][indices[0, :, 0]].repeat_interleave(4, dim=0)
    torch.testing.assert_close(base[0], expected)
    with pytest.raises(ValueError, match="precision"):
        decode_tokens(tokenizer, indices, lengths, precision="fp16")


def test_bf16_decoding_agrees_with_fp32():
    from segmo.models.tokenizer import RVQVAE, RVQConfig

    torch.manual_seed(0)
    tokenizer = RVQVAE(RVQConfig(feature_dim=12, width=32, code_dim=16, codebook_size=16,
                                 num_quantizers=3)).eval()
    indices = torch.randint(0, 16, (2, 6, 3))
    lengths = torch.tensor([24, 16])
    fp32 = decode_tokens(tokenizer, indices, lengths, precision="fp32")
    bf16 = decode_tokens(tokenizer, indices, lengths, precision="bf16")
    assert bf16.dtype == torch.float32 and not torch.equal(bf16, fp32)  # it did run in bf16
    torch.testing.assert_close(bf16, fp32, rtol=0.05, atol=0.05 * fp32.abs().max().item())


def test_keep_freed_memory_takes_effect_on_glibc():
    import platform

    from segmo.generation.allocator import keep_freed_memory

    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        pytest.skip("mallopt is glibc's")
    assert keep_freed_memory() is True
    assert keep_freed_memory() is True  # idempotent


def test_unguided_residual_layers_run_the_conditional_rows_alone(models, monkeypatch):
    mask, residual = models
    lengths = torch.tensor([48, 20])

    def run(**options):
        return generate_tokens(mask, residual, *text(2), lengths,
                               options=SamplingOptions(steps=4, **options),
                               generator=torch.Generator().manual_seed(2))

    every = run()
    assert torch.equal(every, run(residual_guided_layers=2))  # q − 1 = 2 layers: all guided
    rows: list[int] = []
    original = ResidualTransformer.forward_embedded

    def counting(self, x, layer, token_mask, condition, positions=None):
        rows.append(x.shape[0])
        assert condition.tokens.shape[0] == x.shape[0]
        return original(self, x, layer, token_mask, condition, positions)

    monkeypatch.setattr(ResidualTransformer, "forward_embedded", counting)
    first = run(residual_guided_layers=1)
    assert rows == [4, 2]  # layer 1 guided (2b rows), layer 2 conditional only (b rows)
    # Base tokens and the guided layer do not depend on the layers above.
    assert torch.equal(first[..., :2], every[..., :2])
    rows.clear()
    none = run(residual_guided_layers=0)
    assert rows == [2, 2] and torch.equal(none[..., 0], every[..., 0])
    assert (none[..., 1:] >= 0).sum() == (every[..., 1:] >= 0).sum()  # same valid positions


def test_residual_decode_draws_only_the_layers_asked_for(models):
    """`layers` draws those residual layers and keeps the others' codes, which the layers
    drawn above them read: layer 2 alone, drawn on the given layer 1, differs from layer 2
    drawn on a layer 1 drawn first."""
    from segmo.generation.generate import guided_logits, residual_decode

    residual = models[1].eval()
    token_mask = torch.tensor([[True] * 6, [True] * 4 + [False] * 2])
    given = torch.randint(0, 16, (2, 6, 3), generator=torch.Generator().manual_seed(4))
    condition = guidance_condition(residual, *text(2))
    options = SamplingOptions(temperature=0.0)

    def decode(layers=None):
        return residual_decode(residual, given, token_mask, token_mask, condition, options,
                               torch.Generator().manual_seed(5), layers)

    every, second = decode(), decode([2])
    valid = token_mask
    assert torch.equal(second[..., :2][valid], given[..., :2][valid])  # base and layer 1 kept
    assert not torch.equal(second[..., 2][valid], given[..., 2][valid])  # layer 2 drawn
    assert not torch.equal(every[..., 1][valid], given[..., 1][valid])
    # Greedy draws: layer 2 alone is the guided argmax read on the given layers 0 and 1.
    x = residual.embed(given.masked_fill(~token_mask[..., None], -1), 2)
    logits = residual.forward_embedded(torch.cat([x, x]), 2, torch.cat([token_mask] * 2),
                                       condition).logits
    expected = guided_logits(logits, options.residual_guidance_scale).argmax(-1)
    assert torch.equal(second[..., 2][valid], expected[valid])
    assert not torch.equal(second[..., 2][valid], every[..., 2][valid])
    assert torch.equal(decode([1, 2]), every)
    assert bool((second[..., 1:][~valid] == -1).all())  # padding stays padding
    for bad in ([0], [3]):
        with pytest.raises(ValueError, match="layers must be in 1..2"):
            decode(bad)


def test_residual_guided_layers_refuses_what_it_cannot_use():
    for bad in (-1, 1.5, True, "2"):
        with pytest.raises(Exception, match="residual_guided_layers"):
            SamplingOptions(residual_guided_layers=bad)


def three_captions(models, **options) -> torch.Tensor:
    """Tokens of three captions (48, 32 and 20 frames), 6 steps, seed 8, under `options`."""
    mask, residual = models
    return generate_tokens(mask, residual, *text(3), torch.tensor([48, 32, 20]),
                           options=SamplingOptions(steps=6, **options),
                           generator=torch.Generator().manual_seed(8))


def test_sink_ctrl_with_k_base_zero_is_plain_cfg_and_otherwise_changes_tokens(models):
    cfg = three_captions(models)
    assert torch.equal(cfg, three_captions(models, guidance="sink_ctrl", ctrl_k_base=0.0))
    assert not torch.equal(cfg[..., 0],
                           three_captions(models, guidance="sink_ctrl", ctrl_k_base=2.0)[..., 0])


def test_sink_ctrl_carries_the_corrected_difference_of_each_position():
    from segmo.generation.generate import SinkControl

    options = SamplingOptions(guidance="sink_ctrl", guidance_scale=2.0, ctrl_lambda=3.0,
                              ctrl_k_base=1.0, ctrl_alpha=0.5, sink_ratio=2.0)  # k_eff = 2
    control = SinkControl(options, torch.Size([1, 3]), 2, torch.device("cpu"))
    conditional = torch.tensor([[[3.0, 0.0], [1.0, 1.0]]])
    unconditional = torch.zeros(1, 2, 2)
    logits = torch.cat([conditional, unconditional])
    picked = torch.tensor([[True, False]])
    first = control.guided(logits, torch.tensor([[0, 2]]), picked)
    # E = (3, 0) at position 0: S = E (no history), E − 2·sign(S) = (1, 0); u + 2·E = (2, 0).
    assert torch.equal(first, torch.tensor([[2.0, 0.0]]))
    assert torch.equal(control.previous[0, 0], torch.tensor([1.0, 0.0]))
    assert torch.equal(control.previous[0, 2], torch.zeros(2))  # not picked: not carried
    # Next step, position 0 again with E = (−1, 0): S = E + 2·E_prev = (1, 0) → E − 2·(1, 0).
    second = control.guided(torch.cat([torch.tensor([[[-1.0, 0.0]]]), torch.zeros(1, 1, 2)]),
                            torch.tensor([[0]]), torch.tensor([[True]]))
    assert torch.equal(second, torch.tensor([[-6.0, 0.0]]))


def test_guidance_must_be_known():
    with pytest.raises(Exception, match="guidance"):
        SamplingOptions(guidance="ctrl")


def _sink_model(t):
    torch.manual_seed(0)
    model = MaskTransformer(MaskTransformerConfig(**TINY, sink_mask_t=t))
    with torch.no_grad():  # sharp logits, a strong text prefix, peaked attention
        model.classifier.weight.mul_(10)
        model.prefix.project.weight.mul_(50)
        for block in model.trunk.blocks:
            block.attention.qkv.weight.mul_(4)
    return model


def test_sink_mask_at_t_one_or_more_is_no_mask_and_below_masks_the_sentence(models):
    from segmo.models.attention_recorder import record_attention

    mask, _ = models
    lengths = torch.tensor([48, 32])

    def run(model):
        return generate_tokens(model, None, *text(2), lengths, options=SamplingOptions(steps=5),
                               generator=torch.Generator().manual_seed(1))

    none, at_one, above = _sink_model(None), _sink_model(1.0), _sink_model(1.5)
    assert torch.equal(run(none), run(at_one)) and torch.equal(run(none), run(above))
    model = _sink_model(0.5)  # t = 0, ¼, ½: not masked; ¾, 1: masked
    with record_attention({"mask": model}) as recording:
        masked = run(model)
    assert not torch.equal(masked, run(none))
    for m in recording.of("mask"):
        sentence = m.weights[..., m.key_labels.index("sentence")]
        if m.step >= 3:
            assert float(sentence.abs().max()) == 0.0 and not bool(m.key_valid[:, 0].any())
        else:
            assert float(sentence.min()) > 0.0


def test_sink_mask_in_training_masks_the_rows_past_the_threshold():
    from segmo.models.mask_transformer import mask_ratio_time

    target = torch.tensor([[True, True, True, True], [True, False, False, False]])
    valid = torch.ones(2, 4, dtype=torch.bool)
    t = mask_ratio_time(target, valid)  # all masked: t = 0; a quarter masked: t = 0.84
    assert float(t[0]) == 0.0 and abs(float(t[1]) - 0.8391) < 1e-3
    assert _sink_model(0.2).sink_mask_rows(t).tolist() == [False, True]
    assert _sink_model(None).sink_mask_rows(t) is None


def test_local_unconditional_rows_keep_segments_and_drop_the_sentence(models):
    mask, residual = models
    condition = guidance_condition(mask, *text(2), unconditional="local")
    # rows 2, 3: unconditional, the sentence slot off, the segments as the conditional rows'
    assert condition.mask[2:, 0].tolist() == [False, False]
    assert torch.equal(condition.mask[2:, 1:], condition.mask[:2, 1:])
    plain = guidance_condition(mask, *text(2))
    assert not bool(plain.mask[2:].any())
    lengths = torch.tensor([48, 32])

    def run(**options):
        return generate_tokens(mask, residual, *text(2), lengths,
                               options=SamplingOptions(steps=4, **options),
                               generator=torch.Generator().manual_seed(3))

    assert run().shape == run(unconditional="local").shape


def test_local_unconditional_is_the_base_tokens_option_only(models, monkeypatch):
    """The residual transformer, trained without local-unconditional rows, gets
    unconditional rows without text whatever `unconditional` says."""
    import segmo.generation.generate as generate

    mask, residual = models
    seen = []
    real = generate.residual_decode
    monkeypatch.setattr(generate, "residual_decode",
                        lambda model, out, editable, token_mask, condition, *a: seen.append(condition)
                        or real(model, out, editable, token_mask, condition, *a))
    generate_tokens(mask, residual, *text(2), torch.tensor([48, 32]),
                    options=SamplingOptions(steps=2, unconditional="local"),
                    generator=torch.Generator().manual_seed(3))
    assert len(seen) == 1 and not bool(seen[0].mask[2:].any()) and bool(seen[0].mask[:2].any())
    with pytest.raises(Exception, match="unconditional"):
        SamplingOptions(unconditional="segments")


def test_local_uncond_prob_keeps_the_segments_of_dropped_samples():
    from segmo.tasks.common import TransformerTask

    class Stub:
        hparams = type("H", (), {"local_uncond_prob": 1.0})()

    drop = torch.tensor([True, False, True])
    assert TransformerTask.keep_local(Stub(), drop).tolist() == [True, False, True]
    Stub.hparams.local_uncond_prob = 0.0
    assert TransformerTask.keep_local(Stub(), drop) is None


def test_remasking_by_segments_takes_each_segments_share():
    # Scores of one step: position 2 (segment 0) and 9 (segment 1) already final.
    groups = torch.tensor([[0, 0, 0, 0, 1, 1, 1, 1, 1, 1, 1, 1, 2, 2]])
    editable = torch.ones(1, 14, dtype=torch.bool)
    editable[0, 13] = False  # fixed (an edit's kept token)
    scores = torch.tensor([[0.9, 0.1, float("inf"), 0.5, 0.2, 0.3, 0.05, 0.6, 0.7,
                            float("inf"), 0.8, 0.4, 0.35, float("inf")]])
    t = 0.5  # γ = cos(π/4) ≈ 0.707
    by_segment = generate_module.remasked(scores, editable, t, groups)
    # ⌈0.707·m_j⌉ of m_j = 4, 8, 1 editable tokens: 3, 6, 1, the least confident of each
    # (segment 0 keeps none of its predicted tokens, segment 1 its most confident, 0.8)
    assert torch.nonzero(by_segment[0]).flatten().tolist() == [0, 1, 3, 4, 5, 6, 7, 8, 11, 12]
    # ... which is not MoMask's ⌈0.707·13⌉ = 10 least confident of the motion: it keeps
    # the motion's most confident, 0.9 in segment 0
    whole = generate_module.remasked(scores, editable, t)
    assert int(whole.sum()) == 10 and not bool(whole[0, 0]) and bool(whole[0, 10])
    assert not bool((by_segment | whole)[0, [2, 9, 13]].any())  # final and fixed stay
    # one group is the motion: MoMask's choice
    one = generate_module.remasked(scores, editable, t, torch.zeros_like(groups))
    assert torch.equal(one, whole)
    spans = torch.tensor([[[0, 4], [4, 12], [12, 13]]])
    assert generate_module.token_groups(spans, 15).tolist() == [
        [0, 0, 0, 0, 1, 1, 1, 1, 1, 1, 1, 1, 2, 3, 3]]  # past the spans: a group of its own


def test_remasking_by_segments_counts_per_segment_at_every_step(monkeypatch):
    torch.manual_seed(0)
    timed = MaskTransformer(MaskTransformerConfig(**TINY, segment_timing=True))
    with torch.no_grad():
        timed.classifier.weight.mul_(50)
    steps = []
    real = generate_module.remasked

    def spy(scores, editable, t, groups=None):
        steps.append((t, groups, real(scores, editable, t, groups)))
        return steps[-1][2]

    monkeypatch.setattr(generate_module, "remasked", spy)
    lengths, durations = torch.tensor([48, 40]), torch.tensor([[1.0, 6.0, 0.0], [3.0, 1.0, 1.0]])

    def run(remasking):
        steps.clear()
        return generate_tokens(timed, None, *text(2), lengths, durations=durations,
                               options=SamplingOptions(steps=5, remasking=remasking),
                               generator=torch.Generator().manual_seed(0))

    by_segment = run("segments")
    assert len(steps) == 5
    for t, groups, masked in steps:
        assert groups[0, :2].tolist() == [0, 0] and groups[0, 2:12].eq(1).all()  # 1 : 6 of 12
        for group in range(4):
            inside = (groups == group) & (torch.arange(12) < lengths[:, None] // 4)
            count = generate_module.masked_count(t, inside.sum(dim=1))
            assert torch.equal((masked & inside).sum(dim=1), count)
    confidence = run("confidence")
    assert all(groups is None for _, groups, _ in steps)
    assert not torch.equal(by_segment, confidence)
    # without spans (a model without timing) there is nothing to count by
    plain = MaskTransformer(MaskTransformerConfig(**TINY))
    assert torch.equal(*(generate_tokens(plain, None, *text(2), lengths,
                                         options=SamplingOptions(steps=5, remasking=r),
                                         generator=torch.Generator().manual_seed(0))
                         for r in ("segments", "confidence")))
    with pytest.raises(Exception, match="remasking must be 'confidence' or 'segments'"):
        SamplingOptions(remasking="random")


def test_hidden_segments_mask_their_slots_and_keep_their_content(models):
    mask, _ = models
    sentence, segments, segment_mask = text(2)
    hidden = torch.tensor([[False, True, False], [True, False, False]])
    plain = mask.condition(sentence, segments, segment_mask)
    condition = mask.condition(sentence, segments, segment_mask, hidden_segments=hidden)
    assert torch.equal(condition.mask[:, 1:], plain.mask[:, 1:] & ~hidden)
    assert bool(condition.mask[:, 0].all())  # the sentence stays
    torch.testing.assert_close(condition.content, plain.content)  # what they say is kept
    with pytest.raises(ValueError, match="hidden_segments must be"):
        mask.condition(sentence, segments, segment_mask, hidden_segments=hidden[:, :2])


def test_segment_guidance_adds_each_segments_own_difference(models):
    """u + s·(c − u) + w·Σⱼ (c − c₋ⱼ), with c₋ⱼ the conditional logits with segment j hidden:
    computed here pass by pass against `segment_guided`."""
    mask, _ = models
    mask.eval()
    b, n = 2, 7
    sentence, segments, segment_mask = text(b)
    indices = torch.randint(0, 17, (b, n))
    token_mask = torch.arange(n) < torch.tensor([7, 4])[:, None]
    condition = guidance_condition(mask, sentence, segments, segment_mask)
    both = mask.forward_condition(torch.cat([indices, indices]),
                                  torch.cat([token_mask, token_mask]), condition).logits
    guidance = generate_module.segment_guidance_condition(mask, sentence, segments,
                                                          segment_mask, 0.7)
    assert guidance.rows.tolist() == [0, 0, 1, 1, 1]  # caption 0 has two segments
    without = mask.forward_condition(indices[guidance.rows], token_mask[guidance.rows],
                                     guidance.condition).logits
    conditional, unconditional = both.chunk(2)
    expected = unconditional + 2.0 * (conditional - unconditional)
    for i in range(b):
        for j in range(int(segment_mask[i].sum())):
            hidden = torch.zeros(1, 3, dtype=torch.bool)
            hidden[0, j] = True
            alone = mask(indices[i:i + 1], token_mask[i:i + 1], sentence[i:i + 1],
                         segments[i:i + 1], segment_mask[i:i + 1], hidden_segments=hidden).logits
            expected[i] += 0.7 * (conditional[i] - alone[0])
    torch.testing.assert_close(generate_module.segment_guided(both, without, guidance, 2.0),
                               expected, rtol=1e-4, atol=1e-4)
    assert generate_module.segment_guidance_condition(mask, sentence, segments,
                                                      segment_mask, 0.0) is None


def test_segment_guidance_zero_is_plain_cfg_and_otherwise_changes_tokens(models):
    mask, residual = models
    cfg = three_captions(models)
    assert torch.equal(cfg, three_captions(models, segment_guidance=0.0))
    guided = three_captions(models, segment_guidance=3.0)
    assert torch.equal(guided < 0, cfg < 0)  # the same padding
    assert not torch.equal(cfg[..., 0], guided[..., 0])
    # One caption of one motion token and three segments: more guidance rows than the batch's.
    one = generate_tokens(mask, residual, torch.randn(1, 8), torch.randn(1, 3, 8),
                          torch.ones(1, 3, dtype=torch.bool), torch.tensor([4]),
                          options=SamplingOptions(steps=3, segment_guidance=1.0))
    assert one.shape == (1, 1, 3) and bool((one >= 0).all())


@pytest.mark.parametrize("bad, message", [
    (dict(segment_guidance=-1.0), "segment_guidance must be >= 0"),
    (dict(segment_guidance=float("nan")), "segment_guidance must be a finite number"),
    (dict(segment_guidance=1.0, guidance="sink_ctrl"), "segment_guidance works with guidance 'cfg'"),
])
def test_segment_guidance_refuses_what_it_cannot_use(bad, message):
    with pytest.raises(Exception, match=message):
        SamplingOptions(**bad)


def test_choice_temperature_ranks_by_noisy_log_confidence():
    scores = torch.tensor([[0.9, 0.1, float("inf"), 0.5, 0.2, 0.3]])
    # no noise: the ranking of the confidences themselves; final tokens stay +inf
    calm = generate_module.noisy_confidence(scores, 0.0, torch.Generator().manual_seed(0))
    assert torch.isinf(calm[0, 2]) and torch.equal(calm.argsort(), scores.argsort())
    # much noise: over draws the least confident position is not always the same one
    generator = torch.Generator().manual_seed(0)
    lowest = {int(generate_module.noisy_confidence(scores, 50.0, generator).argmin())
              for _ in range(50)}
    assert len(lowest) > 2 and 2 not in lowest
    # the same generator state, the same noise
    first, second = (generate_module.noisy_confidence(scores, 3.0, torch.Generator().manual_seed(4))
                     for _ in range(2))
    assert torch.equal(first, second)


def test_choice_temperature_changes_the_remasking_only_between_the_ends(monkeypatch):
    torch.manual_seed(0)
    plain = MaskTransformer(MaskTransformerConfig(**TINY))
    seen = []
    real = generate_module.remasked

    def spy(scores, editable, t, groups=None):
        seen.append((t, scores.clone()))
        return real(scores, editable, t, groups)

    monkeypatch.setattr(generate_module, "remasked", spy)
    lengths = torch.tensor([48, 40])

    def run(tau):
        seen.clear()
        tokens = generate_tokens(plain, None, *text(2), lengths,
                                 options=SamplingOptions(steps=5, choice_temperature=tau),
                                 generator=torch.Generator().manual_seed(0))
        return tokens, list(seen)

    calm, calm_steps = run(0.0)
    noisy, noisy_steps = run(2.0)
    assert torch.equal(noisy, run(2.0)[0])  # reproducible from the generator
    assert not torch.equal(calm, noisy)
    # confidences in [0, 1] at every step without noise; with it, log-confidence plus noise
    # in the middle steps, and the first step (all masked) and the last (no noise) as before
    assert all(bool((s[torch.isfinite(s)] >= 0).all()) for _, s in calm_steps)
    for t, s in noisy_steps:
        finite = torch.isfinite(s)
        if 0 < t < 1:
            assert bool((s[finite] < 0).any())
        else:
            assert bool((s[finite] >= 0).all())
    with pytest.raises(Exception, match="choice_temperature must be >= 0"):
        SamplingOptions(choice_temperature=-1.0)
    with pytest.raises(Exception, match="choice_temperature must be a finite number"):
        SamplingOptions(choice_temperature=float("nan"))


@pytest.mark.parametrize("device", ["cpu", torch.device("cpu")])
def test_inference_takes_its_device_by_name(device):
    # The signature's own default "cpu" raised AttributeError: 'str' object has no attribute 'type'.
    layer = torch.nn.Linear(2, 2).train()
    with generate_module.inference([layer], "fp32", device):
        assert not layer.training and torch.is_inference_mode_enabled()
    assert layer.training
