"""Segment alignment head and losses: masking, scaling, symmetry, gradients, ISC."""

from __future__ import annotations

import math
import typing

import pytest
import torch
import torch.nn.functional as F

from segmo.data.collate import related_samples
from segmo.models.alignment import (
    AlignmentConfig,
    AlignmentHead,
    SegmentAggregator,
    isc_from_cosines,
    paired_cosine,
    segment_similarity,
    span_mask,
    span_max,
)
from segmo.pipeline.space import SegmentEmbeddings
from segmo.segmentation import segment_batch
from segmo.tasks.alignment_loss import (
    AlignmentLoss,
    AlignMethod,
    batch_loss,
    global_loss,
    in_sample_loss,
    token_loss,
)

DIM = 16


def gen(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def batch(seed: int = 0):
    """b=4 samples: 3, 1, 5 and 2 segments; token lengths 20, 9, 25, 6 of n = 25."""
    g = gen(seed)
    num, lengths = torch.tensor([3, 1, 5, 2]), torch.tensor([20, 9, 25, 6])
    h = torch.randn(4, 25, DIM, generator=g)
    segments = torch.randn(4, 5, DIM, generator=g)
    mask = torch.arange(5) < num[:, None]
    spans = segment_batch(None, num, lengths, max_segments=5)
    return h, lengths, segments, mask, spans, torch.randn(4, DIM, generator=g)


def test_span_mask_and_aggregator_pooling():
    spans = torch.tensor([[[0, 2], [2, 5], [0, 0]]])
    assert span_mask(spans, 6).int().tolist() == [
        [[1, 1, 0, 0, 0, 0], [0, 0, 1, 1, 1, 0], [0, 0, 0, 0, 0, 0]]
    ]
    agg = SegmentAggregator(2, 3)
    agg.mlp = torch.nn.Identity()  # look at the pooled concat(mean, max) itself
    h = torch.tensor([[[1.0, 0.0], [3.0, 4.0], [2.0, -1.0], [0.0, -3.0], [7.0, 2.0], [9, 9]]])
    pooled = agg(h, spans)
    assert torch.allclose(pooled[0, 0], torch.tensor([2.0, 2.0, 3.0, 4.0]))
    assert torch.allclose(pooled[0, 1], torch.tensor([3.0, -2 / 3, 7.0, 2.0]))
    assert (pooled[0, 2] == 0).all()  # empty (padding) span pools to zeros, never -inf


def test_aggregator_matches_per_span_loop():
    h, _, _, mask, spans, _ = batch()
    agg = SegmentAggregator(DIM, 8)
    out = agg(h, spans)
    for i in range(4):
        for j in range(int(mask[i].sum())):
            s, e = spans[i, j].tolist()
            part = h[i, s:e]
            expected = agg.mlp(torch.cat([part.mean(0), part.amax(0)]))
            assert torch.allclose(out[i, j], expected, atol=1e-5)


def test_span_max_matches_masking_each_span_in_values_and_gradients():
    # Overlapping windows (as grounding scores them), spans reaching past either end, an
    # empty slot and a row without any span: the gathered reduction must give what masking
    # h for each span gives, and route the gradient to the same rows.
    g = gen(3)
    h = torch.randn(3, 7, 4, generator=g)
    spans = torch.tensor([[[0, 3], [1, 7], [2, 3], [6, 7]],
                          [[-2, 2], [5, 11], [0, 0], [4, 4]],
                          [[0, 0], [3, 3], [0, 0], [0, 0]]])
    upstream = torch.randn(3, 4, 4, generator=g)
    fast = h.clone().requires_grad_()
    (span_max(fast, spans) * upstream).sum().backward()
    slow = h.clone().requires_grad_()
    inside = span_mask(spans, 7)
    peak = slow[:, None].masked_fill(~inside[..., None], float("-inf")).amax(dim=2)
    expected = torch.where(inside.any(-1, keepdim=True), peak, torch.zeros_like(peak))
    (expected * upstream).sum().backward()
    assert torch.equal(span_max(h, spans), expected.detach())
    assert torch.equal(fast.grad, slow.grad)
    assert (span_max(h, spans)[2] == 0).all() and (fast.grad[2] == 0).all()
    assert torch.equal(span_max(h, torch.zeros(3, 2, 2, dtype=torch.long)), torch.zeros(3, 2, 4))


@pytest.mark.parametrize("method", ["in_sample", "batch", "global", "token"])
def test_padded_slots_change_nothing(method):
    h, lengths, segments, mask, spans, sentence = batch()
    torch.manual_seed(0)  # the parameters; inputs below come from explicit generators
    head, loss_fn = AlignmentHead(DIM, AlignmentConfig(out_dim=8)), AlignmentLoss(method)
    pad = ~mask
    results = []
    fills = (torch.zeros_like(segments), 100 * torch.randn(segments.shape, generator=gen(5)),
             torch.full_like(segments, float("nan")))  # NaN reached every gradient via 0 · NaN
    for fill in fills:
        seg = torch.where(pad[..., None], fill, segments).requires_grad_()
        hh = h.clone()
        hh[torch.arange(25) >= lengths[:, None]] = fill[:, :1].expand(-1, 25, -1)[
            torch.arange(25) >= lengths[:, None]
        ]  # padded tokens too
        hh.requires_grad_()
        head.zero_grad()
        loss = loss_fn(head, hh, lengths, seg, mask, spans, sentence).losses["align"]
        loss.backward()
        grads = [p.grad.clone() for p in head.parameters() if p.grad is not None]
        results.append((loss.detach(), seg.grad, hh.grad, grads))
    (l0, s0, h0, p0) = results[0]
    assert torch.isfinite(l0) and l0 > 0
    assert (h0[torch.arange(25) >= lengths[:, None]] == 0).all()
    for l1, s1, h1, p1 in results[1:]:
        assert torch.allclose(l0, l1)
        if method == "global":
            assert s0 is None and s1 is None  # segments are not used by the global ablation
        else:
            assert torch.allclose(s0, s1) and (s0[pad] == 0).all()
        assert torch.allclose(h0, h1, atol=1e-6)
        assert all(torch.allclose(a, b, atol=1e-6) for a, b in zip(p0, p1))


def test_one_segment_samples_contribute_nothing():
    g = gen(1)
    text, motion = torch.randn(3, 4, 8, generator=g), torch.randn(3, 4, 8, generator=g)
    mask = torch.tensor([[1, 1, 1, 0], [1, 0, 0, 0], [1, 1, 0, 0]], dtype=torch.bool)
    full = in_sample_loss(text, motion, mask)["align"]
    # Changing the one-segment sample entirely, or removing it, leaves the loss unchanged.
    other = text.clone()
    other[1] = torch.randn(4, 8, generator=g)
    assert torch.allclose(full, in_sample_loss(other, motion, mask)["align"])
    keep = torch.tensor([0, 2])
    assert torch.allclose(full, in_sample_loss(text[keep], motion[keep], mask[keep])["align"])
    # No sample with ≥ 2 segments: an exact zero that still backpropagates.
    text.requires_grad_()
    zero = in_sample_loss(text, motion, mask & torch.tensor([1, 0, 0, 0], dtype=torch.bool))
    assert zero["align"].item() == 0.0
    zero["align"].backward()
    assert text.grad is not None and (text.grad == 0).all()


def test_perfect_alignment_beats_shuffled_and_loss_is_symmetric():
    g = gen(2)
    text = torch.randn(6, 5, 32, generator=g)
    mask = torch.ones(6, 5, dtype=torch.bool)
    mask[0, 3:] = False
    noisy = text + 0.1 * torch.randn(text.shape, generator=g)
    aligned = in_sample_loss(text, noisy, mask)["align"]
    shuffled = in_sample_loss(text, noisy[:, [1, 2, 0, 4, 3]], mask)["align"]
    assert aligned < 0.05 < 1.0 < shuffled
    swapped = in_sample_loss(noisy, text, mask)
    forward = in_sample_loss(text, noisy, mask)
    assert torch.allclose(forward["align"], swapped["align"])
    assert torch.allclose(forward["align_t2m"], swapped["align_m2t"])


def test_each_method_scales_as_log_of_its_negatives():
    """With all embeddings equal every logit ties: loss = log(number of candidates)."""
    b, a, d = 4, 5, 8
    same = torch.ones(b, a, d)
    mask = torch.arange(a) < torch.tensor([3, 1, 5, 2])[:, None]
    # in_sample: rows of samples with 3, 5, 2 segments -> mean of log(k) over those 10 rows
    expected = (3 * math.log(3) + 5 * math.log(5) + 2 * math.log(2)) / 10
    assert math.isclose(in_sample_loss(same, same, mask)["align"].item(), expected, rel_tol=1e-5)
    # batch: all 11 valid segments against each other
    assert math.isclose(batch_loss(same, same, mask)["align"].item(), math.log(11), rel_tol=1e-5)
    # global: b sentences against b motions
    assert math.isclose(
        global_loss(same[:, 0], same[:, 0])["align"].item(), math.log(b), rel_tol=1e-5
    )
    # token: m2t over the sample's segments, t2m over its covered tokens (positives = span)
    lengths = torch.tensor([9, 4, 10, 4])
    spans = segment_batch(None, mask.sum(1), lengths, max_segments=a)
    tokens = torch.ones(b, 10, d)
    out = token_loss(same, tokens, spans, mask)
    m2t = (9 * math.log(3) + 10 * math.log(5) + 4 * math.log(2)) / 23
    t2m = (3 * math.log(9 / 3) + 5 * math.log(10 / 2) + 2 * math.log(4 / 2)) / 10
    assert math.isclose(out["align_m2t"].item(), m2t, rel_tol=1e-5)
    assert math.isclose(out["align_t2m"].item(), t2m, rel_tol=1e-5)


def test_batch_and_global_never_contrast_a_motion_or_caption_with_itself():
    """A motion's captions come one sample each, so they share batches: two samples of one
    motion, or with the same caption, are never each other's negatives (`related_samples`,
    the evaluator's rule); segments of one sample still are."""
    m = F.normalize(torch.randn(3, DIM, generator=gen(7)), dim=-1)
    motion = m[[0, 0, 1, 2]]
    related = related_samples({"id": ["a", "a", "b", "c"], "caption": ["w", "x", "y", "z"]})
    assert global_loss(motion, motion)["align"] > 0.3  # related=None: every other sample a negative
    assert global_loss(motion, motion, related=related)["align"] < 1e-3
    segments = motion[:, None].expand(4, 2, DIM) * torch.tensor([1.0, -1.0])[:, None]
    mask = torch.ones(4, 2, dtype=torch.bool)
    assert batch_loss(segments, segments, mask)["align"] > 0.3
    assert batch_loss(segments, segments, mask, related=related)["align"] < 0.02
    # Equal embeddings: every logit ties, so the loss is the mean log of each row's candidates.
    # Samples 0 and 2 are one motion, 1 and 3 one caption (case and spaces aside).
    related = related_samples({"id": ["a", "b", "a", "c"], "caption": ["x", "jump", "y", " Jump"]})
    assert related.tolist() == [[True, False, True, False], [False, True, False, True],
                                [True, False, True, False], [False, True, False, True]]
    same = torch.ones(4, 5, 8)
    assert math.isclose(global_loss(same[:, 0], same[:, 0], related=related)["align"].item(),
                        math.log(3), rel_tol=1e-5)
    mask = torch.arange(5) < torch.tensor([3, 1, 5, 2])[:, None]
    expected = (3 * math.log(6) + 1 * math.log(9) + 5 * math.log(8) + 2 * math.log(10)) / 11
    assert math.isclose(batch_loss(same, same, mask, related=related)["align"].item(), expected,
                        rel_tol=1e-5)
    # A batch of one motion leaves no negative: an exact zero that still backpropagates.
    text = same[:, 0].clone().requires_grad_()
    zero = global_loss(text, same[:, 0], related=torch.ones(4, 4, dtype=torch.bool))["align"]
    zero.backward()
    assert zero.item() == 0.0 and (text.grad == 0).all()


def _former_in_sample(text, motion, mask, temperature=0.1):
    """`in_sample_loss` as it was before `related` came in, written out."""
    sim = torch.einsum("bid,bjd->bij", F.normalize(text, dim=-1), F.normalize(motion, dim=-1))
    logits = sim / temperature
    valid = mask[:, :, None] & mask[:, None, :]
    rows = mask & (mask.sum(-1, keepdim=True) >= 2)
    low = torch.finfo(logits.dtype).min
    t2m = -logits.masked_fill(~valid, low).log_softmax(-1).diagonal(dim1=-2, dim2=-1)[rows].mean()
    m2t = -logits.transpose(1, 2).masked_fill(~valid, low).log_softmax(-1).diagonal(
        dim1=-2, dim2=-1)[rows].mean()
    return 0.5 * (t2m + m2t)


@pytest.mark.parametrize("method", ["in_sample", "token"])
def test_within_sample_methods_ignore_related_samples(method):
    """in_sample (SegMo) and token contrast within one caption: the batch's other samples,
    related or not, change nothing, bit for bit, in the loss and its gradients."""
    h, lengths, segments, mask, spans, sentence = batch(2)
    torch.manual_seed(0)
    head, loss_fn = AlignmentHead(DIM, AlignmentConfig(out_dim=8)), AlignmentLoss(method)
    related = related_samples({"id": ["a", "a", "b", "a"], "caption": ["x", "y", "x", "z"]})
    results = []
    for rel in (None, related):
        seg = segments.clone().requires_grad_()
        out = loss_fn(head, h, lengths, seg, mask, spans, sentence, rel)
        grad = torch.autograd.grad(out.losses["align"], seg)[0]
        results.append((out.losses["align"], grad))
    assert torch.equal(results[0][0], results[1][0]) and torch.equal(results[0][1], results[1][1])
    if method == "in_sample":
        text = head.embed_text(segments)
        motion = head.embed_motion(h, spans)
        kept = mask & (spans[..., 1] > spans[..., 0])
        assert torch.equal(in_sample_loss(text, motion, kept)["align"],
                           _former_in_sample(text, motion, kept))
        assert torch.equal(results[0][0], _former_in_sample(text, motion, kept))


@pytest.mark.parametrize("method", typing.get_args(AlignMethod))
def test_every_method_runs_and_trains(method):
    h, lengths, segments, mask, spans, sentence = batch(3)
    torch.manual_seed(0)
    head, loss_fn = AlignmentHead(DIM, AlignmentConfig(out_dim=8)), AlignmentLoss(method)
    h.requires_grad_()
    out = loss_fn(head, h, lengths, segments, mask, spans, sentence)
    loss = out.losses["align"]
    assert loss.ndim == 0 and torch.isfinite(loss)
    loss.backward()
    assert h.grad is not None and h.grad.abs().sum() > 0
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in head.parameters())
    params = [h, *head.parameters()]
    for _ in range(10):  # plain gradient descent: torch.optim's first step costs seconds
        grads = torch.autograd.grad(
            loss_fn(head, h, lengths, segments, mask, spans, sentence).losses["align"], params
        )
        with torch.no_grad():
            for p, g in zip(params, grads):
                p -= 0.1 * g
    assert loss_fn(head, h, lengths, segments, mask, spans, sentence).losses["align"] < loss


def test_config_validation():
    with pytest.raises(ValueError, match="method='clip'"):
        AlignmentLoss(method="clip")
    with pytest.raises(ValueError, match="temperature"):
        AlignmentLoss(temperature=0.0)
    with pytest.raises(ValueError, match="segmenter"):
        AlignmentLoss(segmenter="dtw")


def test_isc_and_similarity():
    g = gen(4)
    text = torch.randn(2, 3, 8, generator=g)
    mask = torch.tensor([[True, True, False], [True, False, False]])
    mean, cv = isc_from_cosines(paired_cosine(text, 2 * text, mask))
    assert math.isclose(mean, 1.0, rel_tol=1e-5) and cv < 1e-3
    motion = torch.randn(2, 3, 8, generator=g)
    cos = torch.nn.functional.cosine_similarity(text, motion, dim=-1)[mask]
    mean, cv = isc_from_cosines(paired_cosine(text, motion, mask))
    assert math.isclose(mean, cos.mean().item(), rel_tol=1e-5)
    assert math.isclose(cv, (cos.std(unbiased=False) / cos.mean()).item(), rel_tol=1e-4)
    sim = segment_similarity(text, motion)
    assert sim.shape == (2, 3, 3)
    assert torch.allclose(sim.diagonal(dim1=1, dim2=2)[mask], cos)
    with pytest.raises(ValueError, match="no valid segment pair"):
        isc_from_cosines(paired_cosine(text, motion, torch.zeros(2, 3, dtype=torch.bool)))


def test_similarity_map_matches_embeddings():
    h, _, segments, _, spans, _ = batch(6)
    head = AlignmentHead(DIM, AlignmentConfig(out_dim=8))
    windows = torch.tensor([[0, 5], [3, 8], [10, 15]])
    # The grounding map of the segment space (segmo.pipeline.space) over these features.
    space = SegmentEmbeddings(segments=[["segment"] * 5] * 4, text=head.embed_text(segments),
                              segment_mask=torch.ones(4, 5, dtype=torch.bool),
                              num_tokens=torch.full((4,), 25), latents=h, features=h, head=head)
    sim = space.similarity(windows)
    assert sim.shape == (4, 5, 3) and sim.abs().max() <= 1.0 + 1e-6
    text = head.embed_text(segments)[2, 1]
    motion = head.embed_motion(h[2:3], windows[None])[0, 2]
    expected = torch.nn.functional.cosine_similarity(text, motion, dim=0)
    assert torch.allclose(sim[2, 1, 2], expected, atol=1e-6)
