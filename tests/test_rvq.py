"""The residual quantizer and the RVQ-VAE tokenizer on random tensors."""

from __future__ import annotations

import pytest
import torch

from segmo.models.pretrained import load_pretrained
from segmo.models.quantizer import ResidualQuantizer
from segmo.models.tokenizer import FRAMES_PER_TOKEN, RVQVAE, RVQConfig


def tiny_config(**overrides) -> RVQConfig:
    values = dict(feature_dim=263, width=32, code_dim=16, codebook_size=16, num_quantizers=4)
    values.update(overrides)
    return RVQConfig(**values)


def quantizer(**overrides) -> ResidualQuantizer:
    values = dict(num_quantizers=4, codebook_size=16, code_dim=8, quantizer_dropout=0.0)
    values.update(overrides)
    return ResidualQuantizer(**values)


def test_shapes_and_outputs():
    model = RVQVAE(tiny_config())
    x = torch.randn(3, 32, 263)
    out = model(x, generator=torch.Generator().manual_seed(0))
    assert out.reconstruction.shape == (3, 32, 263)
    assert out.indices.shape == (3, 8, 4) and out.indices.dtype == torch.long
    assert out.perplexity.shape == (4,) and out.code_usage.shape == (4,)
    assert out.commitment_loss.ndim == 0 and out.commitment_loss.requires_grad
    model.eval()
    indices = model.encode(x)
    assert indices.shape == (3, 8, 4)
    assert model.decode(indices).shape == (3, 32, 263)
    assert (model.codebook_size, model.num_quantizers, model.code_dim) == (16, 4, 16)


def test_frames_per_token_is_the_encoders_stride():
    """The one constant that data cropping, lengths and token spans read is what the
    encoder does: n tokens from n * FRAMES_PER_TOKEN frames, and back."""
    model = RVQVAE(tiny_config()).eval()
    for n in (1, 5):
        indices = model.encode(torch.randn(1, n * FRAMES_PER_TOKEN, 263))
        assert indices.shape[1] == n
        assert model.decode(indices).shape[1] == n * FRAMES_PER_TOKEN


def test_bad_inputs_raise():
    model = RVQVAE(tiny_config())
    with pytest.raises(ValueError, match="multiple of 4"):
        model.encode(torch.randn(1, 30, 263))
    with pytest.raises(ValueError, match="263"):
        model.encode(torch.randn(1, 32, 251))
    with pytest.raises(ValueError, match=r"\[-1, 16\)"):
        model.decode(torch.full((1, 8, 4), 16))


def test_lengths_encode_and_decode_each_motion_as_alone():
    """With lengths, a motion's latents and decoded frames are those of the motion alone,
    whatever its batch-mates' lengths (without, the padding leaks into its last frames);
    samples of one length share one encoder/decoder call."""
    model = RVQVAE(tiny_config()).eval()
    model.quantizer.codebooks.normal_(generator=torch.Generator().manual_seed(0))
    x = torch.randn(3, 40, 263, generator=torch.Generator().manual_seed(1))
    lengths = torch.tensor([16, 40, 16])
    x[0, 16:] = x[2, 16:] = 0  # zero-padded, as a batch is
    calls = []
    model.encoder.register_forward_pre_hook(lambda _, args: calls.append(tuple(args[0].shape)))
    with torch.no_grad():
        latents = model.latents(x, lengths)
        assert calls == [(2, 263, 16), (1, 263, 40)]  # one call per length
        padded = model.latents(x)
        alone = model.latents(x[:1, :16])
    torch.testing.assert_close(latents[0, :4], alone[0], rtol=0, atol=1e-6)
    assert not torch.allclose(padded[0, :4], alone[0], atol=1e-4)  # what lengths prevent
    assert bool((latents[[0, 2], 4:] == 0).all())
    torch.testing.assert_close(latents[1], padded[1], rtol=0, atol=1e-6)
    calls.clear()
    with torch.no_grad():
        assert torch.equal(model.latents(x, torch.full((3,), 40)), padded)
    assert calls == [(3, 263, 40)]  # equal lengths: the one call over the batch

    indices = torch.randint(0, 16, (3, 10, 4), generator=torch.Generator().manual_seed(2))
    indices[0, 4:] = indices[2, 4:] = -1
    with torch.no_grad():
        decoded = model.decode(indices, lengths)
        alone = model.decode(indices[:1, :4])
        padded = model.decode(indices)
    torch.testing.assert_close(decoded[0, :16], alone[0], rtol=0, atol=1e-6)
    assert not torch.allclose(padded[0, :16], alone[0], atol=1e-4)
    assert bool((decoded[[0, 2], 16:] == 0).all())
    torch.testing.assert_close(decoded[1], padded[1], rtol=0, atol=1e-6)
    for bad in (torch.tensor([16, 40]), torch.tensor([16, 44, 16]), torch.tensor([16, 18, 16]),
                torch.tensor([0, 40, 16]), torch.tensor([16.0, 40.0, 16.0])):
        with pytest.raises(ValueError, match="lengths"):
            model.latents(x, bad)
        with pytest.raises(ValueError, match="lengths"):
            model.decode(indices, bad)


def test_encoder_output_is_the_nearest_code_sum():
    """The gradient path is straight-through and the forward value is the code sum."""
    rq = quantizer()
    rq(torch.randn(2, 10, 8))  # initialise
    rq.eval()  # no EMA step, so the codebook read back is the one used
    x = torch.randn(2, 10, 8, requires_grad=True)
    out = rq(x)
    assert torch.allclose(out.quantized, rq.codes(out.indices), atol=1e-6)
    out.quantized.sum().backward()
    assert torch.allclose(x.grad, torch.ones_like(x))  # one identity gradient, not q of them


def test_first_batch_initialises_and_residuals_shrink():
    rq = quantizer()
    assert not rq.initialised.any()
    x = torch.randn(4, 50, 8)
    out = rq(x, generator=torch.Generator().manual_seed(0))
    assert rq.initialised.all()
    # Every code of layer 0 is (after one EMA step) near an input vector.
    errors = [(x - rq.codes(out.indices[..., :k])).pow(2).mean() for k in range(1, 5)]
    assert all(a > b for a, b in zip(errors, errors[1:]))


def test_state_dict_round_trip_keeps_codebooks_and_flag():
    rq = quantizer()
    rq(torch.randn(4, 50, 8), generator=torch.Generator().manual_seed(0))
    state = rq.state_dict()
    assert {"codebooks", "ema_counts", "ema_sums", "initialised"} <= set(state)

    fresh = quantizer()
    fresh.load_state_dict(state)
    assert fresh.initialised.all()
    assert torch.equal(fresh.codebooks, rq.codebooks)
    # The next training batch updates both identically: nobody re-initialises.
    x = torch.randn(4, 50, 8)
    rq(x, generator=torch.Generator().manual_seed(1))
    fresh(x, generator=torch.Generator().manual_seed(1))
    assert torch.equal(fresh.codebooks, rq.codebooks)
    before = state["codebooks"]
    assert (fresh.codebooks - before).abs().max() < 0.5 * before.abs().max()


def test_dropout_emits_minus_one_and_decodes_it_as_zero():
    rq = quantizer(quantizer_dropout=1.0)
    generator = torch.Generator().manual_seed(0)
    depths = set()
    for _ in range(20):
        out = rq(torch.randn(2, 6, 8), generator=generator)
        kept = int((out.indices[0, 0] >= 0).sum())
        depths.add(kept)
        # Kept layers are a prefix, the same for the whole batch.
        assert (out.indices[..., :kept] >= 0).all() and (out.indices[..., kept:] == -1).all()
        assert torch.isnan(out.perplexity[kept:]).all() and not torch.isnan(out.perplexity[:kept]).any()
    assert len(depths) > 1 and max(depths) <= 4
    # Decoding -1 as zero equals decoding the kept prefix alone.
    model = RVQVAE(tiny_config()).eval()
    model.quantizer.codebooks.normal_(generator=generator)
    indices = torch.randint(0, 16, (2, 8, 4), generator=generator)
    dropped = indices.clone()
    dropped[..., 2:] = -1
    assert torch.allclose(model.decode(dropped), model.decode(indices[..., :2]))
    assert not torch.allclose(model.decode(dropped), model.decode(indices))


def test_dead_codes_are_replaced_by_inputs():
    rq = quantizer(num_quantizers=1, codebook_size=32)
    x = torch.randn(1, 40, 8)
    rq(x, generator=torch.Generator().manual_seed(0))
    # Inputs far away from the current codes: only a few codes get used, the rest die
    # slowly; after enough steps their counts are below 1 and they are re-seeded.
    far = torch.randn(1, 40, 8) + 50.0
    for _ in range(5):
        rq(far, generator=torch.Generator().manual_seed(0))
    assert (rq.ema_counts[0] >= 1.0 - 1e-6).all()
    near_far = (rq.codebooks[0] - 50.0).abs().mean(1) < 10
    assert near_far.float().mean() > 0.5


def test_eval_mode_leaves_state_alone():
    rq = quantizer()
    rq(torch.randn(2, 10, 8))
    state = {k: v.clone() for k, v in rq.state_dict().items()}
    rq.eval()
    rq(torch.randn(2, 10, 8))
    assert all(torch.equal(state[k], v) for k, v in rq.state_dict().items())


def test_mask_excludes_padding_from_statistics():
    rq_masked, rq_clean = quantizer(), quantizer()
    x = torch.randn(1, 12, 8)
    padded = torch.cat([x, torch.full((1, 4, 8), 1e3)], dim=1)
    mask = torch.arange(16)[None] < 12
    rq_masked(padded, mask=mask, generator=torch.Generator().manual_seed(0))
    rq_clean(x, generator=torch.Generator().manual_seed(0))
    assert torch.allclose(rq_masked.codebooks, rq_clean.codebooks)


def test_codebook_state_stays_fp32_under_half_and_autocast():
    model = RVQVAE(tiny_config())
    model.to(torch.bfloat16)
    assert model.quantizer.codebooks.dtype == torch.float32
    model.float()
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = model(torch.randn(2, 16, 263), generator=torch.Generator().manual_seed(0))
    assert model.quantizer.codebooks.dtype == torch.float32
    assert torch.isfinite(out.reconstruction.float()).all()


def test_save_and_load_pretrained(tmp_path):
    model = RVQVAE(tiny_config())
    model(torch.randn(2, 16, 263), generator=torch.Generator().manual_seed(0))
    model.set_statistics(torch.rand(263), torch.rand(263) + 0.5)
    model.eval()
    model.save_pretrained(tmp_path, meta={"skeleton": "t2m", "fps": 20.0})
    loaded = load_pretrained(tmp_path)
    assert isinstance(loaded, RVQVAE) and loaded.meta["skeleton"] == "t2m"
    x = torch.randn(2, 16, 263)
    indices = model.encode(x)
    assert torch.equal(loaded.encode(x), indices)
    assert torch.equal(loaded.decode(indices), model.decode(indices))
    assert torch.equal(loaded.std, model.std) and loaded.quantizer.initialised.all()
    raw = torch.randn(3, 263)
    assert torch.allclose(loaded.normalize(loaded.denormalize(raw)), raw, atol=1e-5)
