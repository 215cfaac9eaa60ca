"""Segment timing (`segmo.models.segment_timing`): spans from shares tile the motion, the
head's loss prefers the true shares, and a model without timing is the model before it."""

from __future__ import annotations

import pytest
import torch

from segmo.models.mask_transformer import MaskTransformer, MaskTransformerConfig
from segmo.models.segment_timing import TimingHead, shares_to_spans, timing_loss

TINY = dict(codebook_size=16, text_dim=8, max_segments=5, max_tokens=49, dim=32, depth=1,
            heads=2, ff_dim=64)


def test_spans_from_shares_tile_the_motion_in_order():
    generator = torch.Generator().manual_seed(0)
    for _ in range(200):
        b, a = 6, 5
        count = torch.randint(1, a + 1, (b,), generator=generator)
        mask = torch.arange(a)[None] < count[:, None]
        shares = torch.rand(b, a, generator=generator) ** 4  # some very short segments
        lengths = torch.randint(1, 50, (b,), generator=generator)
        spans = shares_to_spans(shares, mask, lengths)
        for i in range(b):
            c, n = int(count[i]), int(lengths[i])
            starts, ends = spans[i, :c, 0].tolist(), spans[i, :c, 1].tolist()
            assert starts[0] == 0 and ends[-1] == n and starts[1:] == ends[:-1]
            widths = [e - s for s, e in zip(starts, ends)]
            assert min(widths) >= (1 if n >= c else 0)
            assert (spans[i, c:] == n).all()  # empty slots sit at the end


def test_spans_follow_the_shares():
    mask = torch.ones(1, 3, dtype=torch.bool)
    spans = shares_to_spans(torch.tensor([[1.0, 2.0, 1.0]]), mask, torch.tensor([40]))
    assert spans[0].tolist() == [[0, 10], [10, 30], [30, 40]]
    # a share too small for a token still gets one; all zero splits evenly
    assert shares_to_spans(torch.tensor([[0.0, 1.0, 0.0]]), mask, torch.tensor([10]))[0].tolist() \
        == [[0, 1], [1, 9], [9, 10]]
    assert shares_to_spans(torch.zeros(1, 3), mask, torch.tensor([9]))[0].tolist() \
        == [[0, 3], [3, 6], [6, 9]]


def test_timing_loss_is_lowest_at_the_true_shares():
    spans = torch.tensor([[[0, 2], [2, 10], [10, 10]]])
    known = torch.tensor([[True, True, False]])
    true = torch.tensor([[0.2, 0.8, 0.0]]).log()
    even = torch.tensor([[0.5, 0.5, 0.0]]).log()
    assert timing_loss(true, spans, known) < timing_loss(even, spans, known)
    assert float(timing_loss(even, spans, torch.zeros_like(known))) == 0.0
    head = TimingHead(4)
    log_shares = head(torch.randn(1, 3, 4), torch.tensor([[True, True, False]]))
    assert log_shares[0, 2] == float("-inf") and torch.isclose(log_shares[0, :2].exp().sum(),
                                                               torch.tensor(1.0))


def test_a_model_without_timing_is_unchanged_and_refuses_spans():
    torch.manual_seed(0)
    plain = MaskTransformer(MaskTransformerConfig(**TINY))
    torch.manual_seed(0)
    timed = MaskTransformer(MaskTransformerConfig(**TINY, segment_timing=True))
    extra = set(timed.state_dict()) - set(plain.state_dict())
    assert extra and all(k.startswith(("timing.", "timing_head.")) for k in extra)
    for key, value in plain.state_dict().items():  # the shared parameters start the same
        assert torch.equal(value, timed.state_dict()[key]), key
    sentence, segments = torch.randn(2, 8), torch.randn(2, 5, 8)
    mask = torch.tensor([[1, 1, 1, 0, 0], [1, 0, 0, 0, 0]], dtype=torch.bool)
    spans = timed.predict_spans(segments, mask, torch.tensor([12, 7]))
    assert spans.shape == (2, 5, 2)
    with pytest.raises(ValueError, match="no segment timing"):
        plain.condition(sentence, segments, mask, spans=spans)
    with pytest.raises(ValueError, match="spans must be"):
        timed.condition(sentence, segments, mask, spans=spans[:, :3])
    # the prefix is unchanged; each motion position is told its segment, where known
    timed.eval()
    base = timed.condition(sentence, segments, mask)
    given = timed.condition(sentence, segments, mask, spans=spans)
    unknown = timed.condition(sentence, segments, mask, spans=spans,
                              span_known=torch.zeros(2, 5, dtype=torch.bool))
    assert torch.equal(given.tokens, base.tokens) and base.token_segments is None
    assert given.token_segments[0, :12].tolist() == [k for k in range(3) for _ in
                                                     range(int(spans[0, k, 1] - spans[0, k, 0]))]
    assert given.token_segments[1, :7].tolist() == [0] * 7 and (given.token_segments[1, 7:] == -1).all()
    assert (unknown.token_segments == -1).all()
    ids, valid = torch.full((2, 12), 16), torch.ones(2, 12, dtype=torch.bool)
    assert torch.equal(timed.forward_condition(ids, valid, unknown).logits,
                       timed.forward_condition(ids, valid, base).logits)
    assert not torch.equal(timed.forward_condition(ids, valid, given).logits,
                           timed.forward_condition(ids, valid, base).logits)


def test_timing_survives_save_and_load(tmp_path):
    torch.manual_seed(0)
    timed = MaskTransformer(MaskTransformerConfig(**TINY, segment_timing=True)).eval()
    path = timed.save_pretrained(tmp_path / "mask")
    loaded = MaskTransformer.from_pretrained(path).eval()
    segments, mask = torch.randn(1, 5, 8), torch.tensor([[1, 1, 1, 0, 0]], dtype=torch.bool)
    assert loaded.config.segment_timing
    assert torch.equal(loaded.predict_spans(segments, mask, torch.tensor([30])),
                       timed.predict_spans(segments, mask, torch.tensor([30])))


def test_position_text_gives_each_position_its_own_segments_text(tmp_path):
    """With `position_text`, what a position adds to its token embedding changes with its
    own segment's text and with no other's; unknown positions add nothing; and the option
    needs timing and survives save and load."""
    from segmo.models.segment_timing import SegmentTiming

    with pytest.raises(ValueError, match="position_text needs segment_timing"):
        MaskTransformer(MaskTransformerConfig(**TINY, position_text=True))
    torch.manual_seed(0)
    timing = SegmentTiming(4, 3, text=True)
    with pytest.raises(ValueError, match="needs segment_content"):
        timing(torch.zeros(1, 2, dtype=torch.long))
    token_segments = torch.tensor([[0, 0, 1, 1, 1, 2, -1]])
    content = torch.randn(1, 3, 4)
    changed = content.clone()
    changed[0, 1] += 1.0  # the second segment says something else
    before, after = timing(token_segments, content), timing(token_segments, changed)
    moved = (before != after).any(-1)[0].tolist()
    assert moved == [False, False, True, True, True, False, False]
    assert (before[0, 6] == 0).all()  # unknown position
    assert torch.allclose(before[0, 5], timing.index[2] + timing.text(content[0, 2]))
    torch.manual_seed(0)
    model = MaskTransformer(MaskTransformerConfig(**TINY, segment_timing=True,
                                                  position_text=True)).eval()
    loaded = MaskTransformer.from_pretrained(model.save_pretrained(tmp_path / "mask")).eval()
    sentence, segments = torch.randn(1, 8), torch.randn(1, 5, 8)
    mask = torch.tensor([[1, 1, 1, 0, 0]], dtype=torch.bool)
    spans = model.predict_spans(segments, mask, torch.tensor([12]))
    ids, valid = torch.full((1, 12), 16), torch.ones(1, 12, dtype=torch.bool)
    assert loaded.config.position_text
    assert torch.equal(loaded.forward_condition(ids, valid, loaded.condition(
        sentence, segments, mask, spans=spans)).logits, model.forward_condition(
        ids, valid, model.condition(sentence, segments, mask, spans=spans)).logits)
