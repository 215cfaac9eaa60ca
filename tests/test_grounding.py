"""The span searches of `segmo.pipeline.grounding` on constructed similarities (no model)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch

from segmo.errors import SegmoError
from segmo.pipeline.grounding import all_spans, check_search, ordered_spans, sliding_windows


def brute_force_cut(similarity: np.ndarray, spans: np.ndarray, n: int, min_tokens: int):
    """Every cut of [0, n) into a contiguous spans of ≥ min_tokens → (best sum, its spans)."""
    column = {tuple(s): i for i, s in enumerate(spans.tolist())}
    a = similarity.shape[0]
    best = (-np.inf, None)
    for inner in itertools.combinations(range(1, n), a - 1):
        bounds = (0, *inner, n)
        cut = [(bounds[j], bounds[j + 1]) for j in range(a)]
        if any(e - s < min_tokens for s, e in cut):
            continue
        total = sum(similarity[j, column[c]] for j, c in enumerate(cut))
        if total > best[0] + 1e-12:
            best = (total, cut)
    return best


def test_all_spans_counts_every_span_of_the_minimum_length() -> None:
    spans = all_spans(5, 2)
    assert len(spans) == (5 - 2 + 1) * (5 - 2 + 2) // 2 == 10
    assert spans.tolist()[:3] == [[0, 2], [0, 3], [0, 4]] and spans.tolist()[-1] == [3, 5]
    assert ((spans[:, 1] - spans[:, 0]) >= 2).all() and spans.max() == 5
    assert len(all_spans(49, 2)) == 1176
    with pytest.raises(ValueError, match="min_tokens"):
        all_spans(3, 4)


@pytest.mark.parametrize("seed", range(20))
def test_ordered_cut_is_the_brute_force_optimum(seed) -> None:
    rng = np.random.default_rng(seed)
    n, a, m = int(rng.integers(6, 12)), int(rng.integers(1, 4)), int(rng.integers(1, 3))
    spans = all_spans(n, m)
    similarity = rng.uniform(-1, 1, size=(a, len(spans)))
    cut = ordered_spans(similarity, spans, n)
    total, expected = brute_force_cut(similarity, spans, n, m)
    column = {tuple(s): i for i, s in enumerate(spans.tolist())}
    assert sum(similarity[j, column[tuple(c)]] for j, c in enumerate(cut.tolist())) == pytest.approx(total)
    assert [tuple(c) for c in cut.tolist()] == expected  # optimum unique for random scores


def test_ordered_cut_covers_the_tokens_in_order() -> None:
    n = 20
    spans = all_spans(n, 2)
    # Segment k likes tokens [5k, 5k + 5) (4 segments); a score that rewards overlap.
    centre = torch.tensor([[5 * k, 5 * k + 5] for k in range(4)])
    s, e = torch.from_numpy(spans).T
    overlap = (torch.minimum(e, centre[:, 1:]) - torch.maximum(s, centre[:, :1])).clamp(min=0)
    similarity = overlap / (e - s + 5 - overlap)  # IoU with the planted span
    cut = ordered_spans(similarity, spans, n)
    assert cut.tolist() == [[0, 5], [5, 10], [10, 15], [15, 20]]
    # A planted order the caption contradicts: the cut still goes in caption order.
    reversed_cut = ordered_spans(similarity.flip(0), spans, n)
    assert reversed_cut[0, 0] == 0 and reversed_cut[-1, 1] == n
    assert (reversed_cut[1:, 0] == reversed_cut[:-1, 1]).all()
    assert ((reversed_cut[:, 1] - reversed_cut[:, 0]) >= 2).all()


def test_ordered_cut_refuses_an_impossible_cut() -> None:
    spans = all_spans(3, 2)
    with pytest.raises(ValueError, match="no cut of 3 tokens into 2"):
        ordered_spans(np.zeros((2, len(spans))), spans, 3)
    with pytest.raises(ValueError, match="scores for"):
        ordered_spans(np.zeros((2, 4)), spans, 3)


def test_search_arguments() -> None:
    # (search, window, stride, min_tokens); None: not given
    assert check_search(None, None, None, None) == "ordered"
    assert check_search(None, 5, 1, None) == "window"
    assert check_search("window", None, None, None) == "window"  # the paper's 5 tokens
    assert check_search("spans", None, None, 2) == "spans"
    for args, message in (((None, 0, None, None), "window=0 must be a size >= 1"),
                          ((None, [3, 0], None, None), "window=\\[3, 0\\]"),
                          (("best", None, None, None), "search='best'; choose from ordered, spans, window"),
                          (("spans", 5, None, None), "window=5 is for search='window'"),
                          (("window", 5, 0, None), "stride=0"),
                          (("ordered", None, None, 0), "min_tokens=0"),
                          # options the search would ignore without a word
                          ((None, None, 1, None), "stride=1 is for search='window', not 'ordered'"),
                          (("window", None, None, 2), "min_tokens=2 is for search 'ordered' or "
                                                      "'spans', not 'window'")):
        with pytest.raises(SegmoError, match=message) as error:
            check_search(*args)
        assert "\n" not in str(error.value)


def test_a_numpy_window_is_a_window():
    # check_search takes numpy integers; sliding_windows tried to iterate one (TypeError)
    assert sliding_windows(10, np.int64(3), np.int64(2)).tolist() == sliding_windows(10, 3, 2).tolist()
    assert check_search(None, np.int64(3), np.int64(2), None) == "window"
