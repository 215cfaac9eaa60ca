"""Known-answer tests of segmo.evaluation metrics, retrieval, grounding and action order."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from segmo.evaluation import report
from segmo.evaluation.action_order import (
    collapse,
    collapse_spans,
    edit_distance,
    error_kind,
    error_shares,
    frame_confusions,
    matched_actions,
    normalised_edit_distance,
    recall_by_share,
    sequence_accuracy,
)
from segmo.evaluation.grounding import grounding_metrics, temporal_iou
from segmo.evaluation.metrics import (
    diversity,
    euclidean_distance_matrix,
    evaluate_generation,
    fid,
    format_table,
    frechet_distance,
    matching_score,
    mean_and_interval,
    multimodality,
    r_precision,
    segment_bucket,
)
from segmo.evaluation.retrieval import (
    batched_retrieval_metrics,
    motion_to_text_ranks,
    retrieval_metrics,
    text_to_motion_ranks,
)
from segmo.pipeline.grounding import best_span, sliding_windows


def _paired(n: int = 320, d: int = 16, noise: float = 0.1, seed: int = 0):
    rng = np.random.default_rng(seed)
    motion = rng.normal(size=(n, d))
    return motion + noise * rng.normal(size=(n, d)), motion


def test_distance_matrix() -> None:
    d = euclidean_distance_matrix([[0, 0], [3, 4]], [[0, 0], [0, 4]])
    np.testing.assert_allclose(d, [[0, 4], [5, 3]], atol=1e-6)


def test_r_precision_identical_and_informative_pairs() -> None:
    text, motion = _paired()
    p = r_precision(text, motion, 3)
    assert p[0] > 0.9 and p[0] <= p[1] <= p[2] <= 1.0
    # identical sets: real vs "generated" copy give the same R-precision
    np.testing.assert_allclose(r_precision(text, motion.copy(), 3), p)


def test_r_precision_shuffled_pairing_is_chance() -> None:
    text, motion = _paired(n=32 * 200)
    shuffled = np.random.default_rng(1).permutation(len(motion))
    p = r_precision(text, motion[shuffled], 3)
    assert abs(p[0] - 1 / 32) < 0.01
    assert abs(p[2] - 3 / 32) < 0.015


def test_matching_score() -> None:
    assert matching_score([[0, 0], [1, 1]], [[3, 4], [1, 1]]) == pytest.approx(2.5)


def test_fid_identical_sets_is_zero() -> None:
    _, motion = _paired()
    assert abs(fid(motion, motion.copy())) < 1e-6
    assert fid(motion, motion + 1.0) == pytest.approx(16.0, rel=1e-6)  # |shift|² = d


def test_frechet_distance_closed_form() -> None:
    # Diagonal covariances: |mu1-mu2|² + Σ (sqrt(a) - sqrt(b))²
    mu1, mu2 = np.array([0.0, 1.0, 2.0]), np.array([1.0, 1.0, 0.0])
    a, b = np.array([1.0, 4.0, 9.0]), np.array([4.0, 1.0, 1.0])
    expected = 1 + 0 + 4 + (1 - 2) ** 2 + (2 - 1) ** 2 + (3 - 1) ** 2
    assert frechet_distance(mu1, np.diag(a), mu2, np.diag(b)) == pytest.approx(expected, rel=1e-9)
    # Non-commuting full covariances vs a direct formula with the matrix square root.
    rng = np.random.default_rng(0)
    x, y = rng.normal(size=(4, 4)), rng.normal(size=(4, 4))
    s1, s2 = x @ x.T + np.eye(4), y @ y.T + np.eye(4)
    w, v = np.linalg.eig(s1 @ s2)
    tr = np.sqrt(w.astype(complex)).sum().real
    assert frechet_distance(np.zeros(4), s1, np.zeros(4), s2) == pytest.approx(np.trace(s1 + s2) - 2 * tr, rel=1e-8)


def test_diversity_and_multimodality_hand_made() -> None:
    # Two clusters 10 apart: every pair is 0 or 10 apart.
    points = np.concatenate([np.zeros((200, 2)), np.full((200, 2), [6.0, 8.0])])
    div = diversity(points, 300, seed=0)
    assert 3.0 < div < 7.0 and (div * 300 / 10) == pytest.approx(round(div * 30), abs=1e-6)
    # Generations of a prompt at the corners of a unit square → distances in {0, 1, sqrt 2}.
    square = np.array([[0, 0], [1, 0], [0, 1], [1, 1]], float)
    emb = np.stack([np.repeat(square, 8, axis=0)] * 3)  # (3 prompts, 32 repeats, 2)
    mm = multimodality(emb, 10, seed=0)
    assert 0.0 < mm < math.sqrt(2)
    assert multimodality(np.zeros((3, 32, 2)), 10, seed=0) == 0.0
    with pytest.raises(ValueError):
        diversity(points[:100], 300)


def test_mean_and_interval() -> None:
    mean, interval = mean_and_interval([1.0, 2.0, 3.0, 4.0])
    assert mean == 2.5
    assert interval == pytest.approx(1.96 * math.sqrt(1.25) / 2)
    # One measurement has no spread to estimate: no interval, not "± 0.000".
    mean, interval = mean_and_interval([3.1])
    assert mean == 3.1 and np.isnan(interval)
    assert report.cell({"mean": 3.1, "interval": interval}) == "3.100"
    assert "| 3.100 |" in format_table({"generated": {"multimodality": {"mean": 3.1,
                                                                          "interval": interval}}})


def test_evaluate_generation_protocol() -> None:
    """Real row ≈ a perfect generator; a generator ignoring the text is at chance."""
    n, d, t = 96, 8, 8
    rng = np.random.default_rng(0)
    codes = torch.tensor(rng.normal(size=(n, d)), dtype=torch.float32)
    batches = []
    for s in range(0, n, 16):  # 3 captions per motion, like the datasets
        rows = list(range(s, s + 16))
        batches.append({
            "motion": codes[rows][:, None, :].expand(-1, t, -1).clone(),
            "lengths": torch.full((16,), t), "id": [f"{r:03d}" for r in rows] * 1,
            "caption": [f"c{r}" for r in rows],
        })
    batches = batches + [dict(b) for b in batches]

    def embed_text(captions, rows):
        return np.stack([codes[int(c[1:])].numpy() for c in captions])

    def embed_motion(motion, lengths):
        return motion[:, 0].numpy()

    def perfect(captions, lengths, seed):
        return torch.stack([codes[int(c[1:])] for c in captions])[:, None].expand(-1, t, -1)

    def random_gen(captions, lengths, seed):
        g = torch.Generator().manual_seed(seed)
        return (2 * torch.randn(len(captions), 1, d, generator=g) + 1).expand(-1, t, -1)

    res = evaluate_generation(embed_text, embed_motion, perfect, batches, repeats=3, diversity_pairs=50,
                              mm_prompts=4, mm_repeats=12, mm_pairs=5)
    assert res["real"]["top1"]["mean"] == 1.0 and res["generated"]["top1"]["mean"] == 1.0
    assert res["generated"]["fid"]["mean"] == pytest.approx(0.0, abs=1e-6)
    assert res["generated"]["multimodality"]["mean"] == pytest.approx(0.0, abs=1e-6)
    assert res["real"]["matching"]["mean"] == pytest.approx(0.0, abs=1e-6)
    res = evaluate_generation(embed_text, embed_motion, random_gen, batches, repeats=3, diversity_pairs=50,
                              mm_prompts=4, mm_repeats=12, mm_pairs=5)
    assert res["generated"]["top1"]["mean"] < 0.25
    assert res["generated"]["fid"]["mean"] > 5.0
    assert res["generated"]["multimodality"]["mean"] > 1.0
    real_only = evaluate_generation(embed_text, embed_motion, None, batches, repeats=2, diversity_pairs=50)
    assert set(real_only) == {"real"} and real_only["real"]["top1"]["mean"] == 1.0


def test_every_seed_the_evaluation_takes_seeds_its_generators() -> None:
    """`segmo evaluate --seed 20000000000000` (below 2^63, so accepted) derived generation
    seeds beyond 2^64: a ValueError traceback from torch after the real rows were scored."""
    from segmo.errors import LARGEST_WHOLE_NUMBER

    n, d, t = 32, 4, 4
    codes = torch.randn(n, d, generator=torch.Generator().manual_seed(0))
    batches = [{"motion": codes[s:s + 16][:, None].expand(-1, t, -1).clone(),
                "lengths": torch.full((16,), t), "id": [f"{r:03d}" for r in range(s, s + 16)],
                "caption": [f"c{r}" for r in range(s, s + 16)]} for s in (0, 16)]
    seeds = []

    def generate(captions, lengths, seed):
        seeds.append(seed)
        g = torch.Generator().manual_seed(seed)
        return torch.randn(len(captions), 1, d, generator=g).expand(-1, t, -1)

    for seed in (20_000_000_000_000, LARGEST_WHOLE_NUMBER):
        evaluate_generation(lambda c, rows: codes[[int(x[1:]) for x in c]].numpy(),
                            lambda m, lengths: m[:, 0].numpy(), generate, batches, repeats=2,
                            diversity_pairs=8, mm_prompts=2, mm_repeats=12, mm_pairs=5, seed=seed)
    assert seeds and all(0 <= s < 2**63 for s in seeds)
    from segmo.evaluation.metrics import generation_seed

    assert generation_seed(3, 10_007 + 5) == 3 * 1_000_003 + 10_007 + 5  # what it always was


def test_evaluate_generation_reconstruction_and_segment_buckets() -> None:
    """A perfect reconstruction scores as the real motions; buckets by number of segments
    add up, appear only when captions have them, and leave R-precision out of a bucket
    smaller than a batch; the overall rows do not change with buckets."""
    n, d, t = 64, 6, 4
    codes = torch.tensor(np.random.default_rng(1).normal(size=(n, d)), dtype=torch.float32)
    batches = [{"motion": codes[s:s + 16][:, None, :].expand(-1, t, -1).clone(), "lengths": torch.full((16,), t),
                "id": [f"{r:03d}" for r in range(s, s + 16)], "caption": [f"c{r}" for r in range(s, s + 16)]}
               for s in range(0, n, 16)]
    num_segments = {f"c{r}": 1 if r < 48 else 2 + r % 3 for r in range(n)}  # 48 × 1; 16 in 2, 3, 4

    def embed_text(captions, rows):
        return np.stack([codes[int(c[1:])].numpy() for c in captions])

    def embed_motion(motion, lengths):
        return motion[:, 0].numpy()

    def reconstruct(motion, lengths, ids):
        assert [int(i) for i in ids] == [int(torch.nonzero((codes == m[0]).all(1))) for m in motion]
        return motion.clone()

    kwargs = dict(repeats=2, batch_size=16, diversity_pairs=20)
    plain = evaluate_generation(embed_text, embed_motion, None, batches, **kwargs)
    res = evaluate_generation(embed_text, embed_motion, None, batches, reconstruct=reconstruct,
                              num_segments=num_segments, **kwargs)
    assert res["real"] == plain["real"]
    assert res["reconstruction"]["top1"]["mean"] == 1.0 and res["reconstruction"]["fid"]["mean"] == pytest.approx(0, abs=1e-6)
    buckets = res["by_num_segments"]
    assert list(buckets) == ["1", "2", "3", "4-5"] and sum(v["count"] for v in buckets.values()) == n
    assert buckets["1"]["count"] == 48 and buckets["1"]["per_repeat"] == 48
    assert buckets["1"]["reconstruction"]["top1"]["mean"] == 1.0 and buckets["1"]["left_out"] == []
    assert "top1" not in buckets["2"]["real"] and {"top1", "top2", "top3"} <= set(buckets["2"]["left_out"])
    assert buckets["2"]["real"]["matching"]["mean"] == pytest.approx(0.0, abs=1e-6)
    only_many = evaluate_generation(embed_text, embed_motion, None, batches, num_segments=dict.fromkeys(num_segments, 2),
                                    **kwargs)["by_num_segments"]
    # One bucket holding every caption: the overall numbers (Diversity draws its own pairs).
    assert list(only_many) == ["2"] and only_many["2"]["count"] == n
    assert {k: v for k, v in only_many["2"]["real"].items() if k != "diversity"} == {
        k: v for k, v in plain["real"].items() if k != "diversity"}
    with pytest.raises(ValueError, match="at least one segment"):
        segment_bucket(0)
    assert [segment_bucket(k) for k in (1, 2, 3, 4, 5)] == ["1", "2", "3", "4-5", "4-5"]


# ---------------------------------------------------------------------------- retrieval

def test_ties_are_broken_at_random_not_in_favour_of_the_right_answer() -> None:
    """A generator that draws one motion for every caption had R-precision 1.0 / 1.0 / 1.0,
    and a constant score matrix R@1 = 1 and MedR 1: a tie counted as a hit."""
    texts = np.random.default_rng(0).normal(size=(64, 8))
    np.testing.assert_allclose(r_precision(texts, np.zeros((64, 8))), [1 / 32, 2 / 32, 3 / 32])
    np.testing.assert_allclose(r_precision(texts, texts + 0.01), [1.0, 1.0, 1.0])  # no ties
    flat = retrieval_metrics(np.ones((10, 10)))
    assert flat["t2m/R@1"] == pytest.approx(0.1) and flat["m2t/R@5"] == pytest.approx(0.5)
    assert flat["t2m/MedR"] == flat["m2t/MedR"] == 5.5
    # one tie of two: half a hit at k = 1
    assert retrieval_metrics(np.array([[1.0, 1.0], [0.0, 1.0]]))["t2m/R@1"] == pytest.approx(0.75)


def test_retrieval_ranks_hand_made() -> None:
    sim = np.array([[0.9, 0.6, 0.0], [0.8, 0.5, 0.0], [0.0, 0.2, 0.1]])
    np.testing.assert_array_equal(text_to_motion_ranks(sim), [0, 1, 1])
    np.testing.assert_array_equal(motion_to_text_ranks(sim), [0, 1, 0])
    m = retrieval_metrics(sim)
    assert m["t2m/R@1"] == pytest.approx(1 / 3) and m["t2m/R@2"] == 1.0
    assert m["t2m/MedR"] == 2.0 and m["m2t/MedR"] == 1.0
    # distances: same ranking as negated similarities
    assert retrieval_metrics(-sim, distance=True) == m


def test_retrieval_several_texts_per_motion() -> None:
    # texts 0, 1 → motion 0; text 2 → motion 1
    sim = np.array([[0.1, 0.9], [0.8, 0.2], [0.3, 0.5]])
    index = [0, 0, 1]
    np.testing.assert_array_equal(text_to_motion_ranks(sim, index), [1, 0, 0])
    # motion 0: best own text (0.8) beaten by none; motion 1: own 0.5 beaten by text 0's 0.9
    np.testing.assert_array_equal(motion_to_text_ranks(sim, index), [0, 1])
    with pytest.raises(ValueError, match="have no text"):
        retrieval_metrics(sim[:, :2], [0, 0, 0])


def test_batched_retrieval_perfect_and_chance() -> None:
    text, motion = _paired(n=320)
    dist = euclidean_distance_matrix(text, motion)
    assert batched_retrieval_metrics(dist, distance=True)["t2m/R@1"] > 0.9
    rng = np.random.default_rng(0)
    chance = batched_retrieval_metrics(rng.normal(size=(320, 320)), batch_size=32)
    assert chance["t2m/R@1"] < 0.15 and chance["m2t/MedR"] > 8


# ---------------------------------------------------------------------------- grounding

def test_temporal_iou_hand_made() -> None:
    assert float(temporal_iou([0, 10], [5, 15])) == pytest.approx(5 / 15)
    assert float(temporal_iou([0, 10], [10, 20])) == 0.0
    assert float(temporal_iou([2, 4], [2, 4])) == 1.0
    np.testing.assert_allclose(temporal_iou([[0, 10], [0, 4]], [[0, 5], [2, 6]]), [0.5, 2 / 6])


def test_grounding_metrics() -> None:
    pred = [[0, 10], [0, 10], [0, 10]]
    gt = [[0, 10], [0, 16], [6, 20]]  # IoU 1, 0.625, 0.2
    m = grounding_metrics(pred, gt)
    assert m["R@1,IoU=0.3"] == pytest.approx(2 / 3) and m["R@1,IoU=0.5"] == pytest.approx(2 / 3)
    assert m["R@1,IoU=0.7"] == pytest.approx(1 / 3)
    assert m["mIoU"] == pytest.approx((1 + 0.625 + 0.2) / 3)


def test_sliding_windows_and_best_span() -> None:
    w = sliding_windows(10, 4, 3)
    np.testing.assert_array_equal(w, [[0, 4], [3, 7], [6, 10]])
    assert len(sliding_windows(5, [2, 8])) == 5  # 4 of size 2 + the whole sequence
    scores = np.array([[0.1, 0.9, 0.2], [0.5, 0.1, 0.1]])
    np.testing.assert_array_equal(best_span(scores, w), [[3, 7], [0, 4]])


# ---------------------------------------------------------------------------- action order

def test_edit_distance_hand_made() -> None:
    true = ["walk", "wave", "sit"]
    assert edit_distance(["walk", "sit"], true) == 1  # missing
    assert edit_distance(["walk", "wave", "sit", "jump"], true) == 1  # extra
    assert edit_distance(["walk", "sit", "wave"], true) == 2  # swapped
    assert normalised_edit_distance([["walk", "sit"], true, ["sit", "wave", "walk"]], [true] * 3) == \
        pytest.approx((1 / 3 + 0 + 2 / 3) / 3)
    assert sequence_accuracy([["walk", "sit"], true], [true, true]) == 0.5
    assert collapse(["a", "a", "b", "a"]) == ["a", "b", "a"]


def test_order_failures_named_and_short_actions_found_less() -> None:
    true = ["walk", "wave", "sit"]
    assert error_kind(true, true) is None
    assert error_kind(["walk", "sit"], true) == "missing"
    assert error_kind(["walk", "wave", "sit", "jump"], true) == "extra"
    assert error_kind(["walk", "sit", "wave"], true) == "reordered"
    assert error_kind(["walk", "kick", "sit"], true) == "substituted"
    shares = error_shares([["walk", "sit"], true, ["walk", "sit", "wave"], ["run"]], [true] * 4)
    assert shares == {"missing": 0.5, "extra": 0.0, "substituted": 0.0, "reordered": 0.25}
    # Each true action: paired with an equal prediction by an optimal edit alignment?
    assert matched_actions(["walk", "sit"], true) == [True, False, True]
    assert matched_actions(["walk", "jump", "sit"], ["walk", "sit"]) == [True, True]
    assert matched_actions(["sit", "wave", "walk"], true) == [False, True, False]
    assert matched_actions([], true) == [False, False, False]
    assert matched_actions(["punch", "walk", "punch"], ["walk", "punch"]) == [True, True]
    # Of the optimal alignments, one with the most pairs: two substitutions cost as much as
    # matching "walk" with an insertion and a deletion, and found none of the two actions.
    assert sum(matched_actions(["walk", "jump"], ["jump", "walk"])) == 1
    assert sum(matched_actions(["a", "b", "c"], ["c", "a", "b"])) == 2
    # Consecutive repeats merge with their frames; shares are of the motion's frames.
    segments = [{"action": "walk", "start": 0, "end": 60}, {"action": "walk", "start": 60, "end": 80},
                {"action": "jump", "start": 80, "end": 90}, {"action": "sit", "start": 90, "end": 100}]
    actions, share = collapse_spans(segments, 100)
    assert actions == ["walk", "jump", "sit"] and share == pytest.approx([0.8, 0.1, 0.1])
    # The short jump is lost, the long walk found: recall by share bin.
    recall = recall_by_share([["walk", "sit"], ["walk", "jump", "sit"]], [actions] * 2, [share] * 2)
    assert recall == {"<0.2": {"recall": 0.75, "actions": 4.0}, ">=0.4": {"recall": 1.0, "actions": 2.0}}
    with pytest.raises(ValueError, match="a share per true action"):
        recall_by_share([["walk"]], [["walk", "sit"]], [[1.0]])


class _ReadsFeatureZero:
    """A stand-in classifier: frame i is read as class int(features[i, 0])."""

    classes = ["walk", "jump_forward", "jump_in_place"]

    def frame_probabilities(self, features):
        return np.eye(len(self.classes))[np.asarray(features)[:, 0].astype(int)]


def test_frame_confusions_say_which_action_each_true_span_is_read_as(tmp_path):
    import json

    from segmo.data.layout import ground_truth_file

    spans = [{"action": "walk", "start": 0, "end": 10}, {"action": "jump_forward", "start": 10, "end": 20}]
    path = ground_truth_file(tmp_path, "000001")
    path.parent.mkdir(parents=True)
    path.write_text(json.dumps({"actions": spans}))
    read = np.zeros((18, 3))  # the clip ends 2 frames before the leap does: 8 of its frames
    read[10:16, 0] = 2  # 6 of the leap's 8 frames read as a jump in place
    read[16:, 0] = 1
    result = frame_confusions(_ReadsFeatureZero(), tmp_path, {"000001": read})
    assert result["frame_accuracy"] == {"jump_forward": pytest.approx(0.25), "walk": 1.0}
    assert result["confusions"] == [{"true": "jump_forward", "read_as": "jump_in_place", "frames": 6,
                                     "share": pytest.approx(0.75)}]
