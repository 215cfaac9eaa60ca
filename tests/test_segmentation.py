"""Motion segmenters: the span contract, step-change detection, batching, the tool."""

from __future__ import annotations

import json
import signal

import numpy as np
import pytest
import torch
from conftest import load_tool

from segmo.errors import SegmoError
from segmo.segmentation import (
    CPDSegmenter,
    KMeansSegmenter,
    repair_boundaries,
    segment_batch,
    uniform_spans,
)
from segmo.segmentation import (
    get_motion_segmenter as get_segmenter,
)

METHODS = ["uniform", "cpd", "kmeans"]


def assert_contract(spans, a, n_valid):
    assert len(spans) == a
    assert spans[0][0] == 0 and spans[-1][1] == n_valid
    for (_, e), (s2, _) in zip(spans, spans[1:]):
        assert e == s2
    assert all(e > s for s, e in spans)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize(
    "n,n_valid,a",
    [(1, 1, 1), (7, 7, 1), (9, 9, 9), (12, 5, 5), (30, 17, 4), (49, 49, 5), (49, 10, 3)],
)
def test_contract_on_random_inputs(method, n, n_valid, a):
    features = torch.randn(n, 6, generator=torch.Generator().manual_seed(n * 100 + a))
    spans = get_segmenter(method)(features, a, n_valid)
    assert_contract(spans, a, n_valid)


@pytest.mark.parametrize("method", METHODS)
def test_padded_tail_is_ignored(method):
    rng = np.random.default_rng(1)
    valid = rng.normal(size=(20, 4))
    a = get_segmenter(method)(np.concatenate([valid, np.zeros((9, 4))]), 3, 20)
    b = get_segmenter(method)(np.concatenate([valid, 1e6 * np.ones((9, 4))]), 3, 20)
    assert a == b
    assert_contract(a, 3, 20)


@pytest.mark.parametrize("method", METHODS)
def test_constant_features_still_give_the_contract(method):
    assert_contract(get_segmenter(method)(np.zeros((11, 3)), 4, 11), 4, 11)


def test_uniform_gives_remainder_to_first_segments():
    assert uniform_spans(10, 3) == [(0, 4), (4, 7), (7, 10)]
    assert uniform_spans(11, 4) == [(0, 3), (3, 6), (6, 9), (9, 11)]


@pytest.mark.parametrize(
    "segmenter", [CPDSegmenter("l2"), CPDSegmenter("rbf"), KMeansSegmenter()], ids=repr
)
def test_step_changes_are_found(segmenter):
    rng = np.random.default_rng(0)
    levels = [(13, 0.0), (8, 3.0), (17, -2.0)]  # deliberately unlike the uniform split
    x = np.concatenate([np.full((k, 5), v) for k, v in levels]) + rng.normal(0, 0.2, (38, 5))
    spans = segmenter(x, 3)
    assert spans == [(0, 13), (13, 21), (21, 38)]
    assert spans != get_segmenter("uniform")(x, 3)


def test_too_many_segments_raise():
    for method in METHODS:
        with pytest.raises(ValueError, match="num_segments=4 > n_valid=3"):
            get_segmenter(method)(np.zeros((8, 2)), 4, 3)
    with pytest.raises(ValueError, match="sample 1"):
        segment_batch(None, torch.tensor([2, 5]), torch.tensor([8, 4]))
    with pytest.raises(ValueError, match="unknown segmenter"):
        get_segmenter("dtw")


def test_repair_boundaries():
    assert repair_boundaries([0, 3, 3, 12, 40], 3, 12) == [3, 7]  # dedupe, clip, split longest
    assert repair_boundaries([1, 2, 6, 9], 3, 12) == [6, 9]  # drop those leaving short pieces


def _hung(signum, frame):
    raise TimeoutError("did not return within 5 s")


@pytest.mark.parametrize("call", [lambda a, n: repair_boundaries([], a, n),
                                  lambda a, n: uniform_spans(n, a)],
                         ids=["repair_boundaries", "uniform_spans"])
def test_public_span_helpers_refuse_impossible_counts(call):
    """repair_boundaries looped forever on more segments than tokens, and uniform_spans
    returned empty spans; both raise as the segmenters do."""
    previous = signal.signal(signal.SIGALRM, _hung)
    signal.alarm(5)
    try:
        with pytest.raises(ValueError, match="num_segments=5 > n_valid=3"):
            call(5, 3)
        with pytest.raises(ValueError, match="num_segments=0 must be"):
            call(0, 3)
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)
    assert call(3, 3) in ([1, 2], [(0, 1), (1, 2), (2, 3)])  # as many segments as tokens is fine


def test_segment_batch_uniform_matches_single_and_pads():
    num, lengths = torch.tensor([3, 1, 0, 5]), torch.tensor([10, 4, 6, 5])
    spans = segment_batch(None, num, lengths, max_segments=5)
    assert spans.shape == (4, 5, 2) and spans.dtype == torch.long
    for i, (a, n) in enumerate(zip(num.tolist(), lengths.tolist())):
        if a:
            assert [tuple(s) for s in spans[i, :a].tolist()] == uniform_spans(n, a)
        assert (spans[i, a:] == 0).all()


@pytest.mark.parametrize("method", ["cpd", "kmeans"])
def test_segment_batch_with_features(method):
    features = torch.randn(3, 15, 4, generator=torch.Generator().manual_seed(0))
    num, lengths = torch.tensor([2, 4, 1]), torch.tensor([15, 9, 3])
    spans = segment_batch(features, num, lengths, method, max_segments=5)
    assert spans.shape == (3, 5, 2)
    for i, (a, n) in enumerate(zip(num.tolist(), lengths.tolist())):
        assert_contract([tuple(s) for s in spans[i, :a].tolist()], a, n)
        assert (spans[i, a:] == 0).all()
    with pytest.raises(ValueError, match="needs features"):
        segment_batch(None, num, lengths, method)


def _load_tool():
    return load_tool("segmenter_boundary_error")


@pytest.fixture
def fake_corpus(tmp_path):
    """Three motions of three step-change actions each, in the built-in corpus layout."""
    rng = np.random.default_rng(0)
    d = 6
    (tmp_path / "segments").mkdir()
    (tmp_path / "new_joint_vecs").mkdir()
    ids = ["000000", "000001", "000002"]
    for k, motion_id in enumerate(ids):
        cuts = [0, 40 + 8 * k, 100, 140 + 4 * k]  # three actions with distinct features
        features = np.concatenate(
            [np.full((e - s, d), 3.0 * i) for i, (s, e) in enumerate(zip(cuts, cuts[1:]))]
        ) + rng.normal(0, 0.1, (cuts[-1], d))
        np.save(tmp_path / "new_joint_vecs" / f"{motion_id}.npy", features.astype(np.float32))
        segs = [{"text": "x", "action": "x", "start": s, "end": e} for s, e in zip(cuts, cuts[1:])]
        record = {
            "id": motion_id,
            "fps": 20.0,
            "num_frames": cuts[-1],
            "captions": [
                {"text": "x", "template": "then", "segments": segs},
                {"text": "y", "template": "single", "segments": [segs[0]]},
            ],
        }
        (tmp_path / "segments" / f"{motion_id}.json").write_text(json.dumps(record))
    (tmp_path / "test.txt").write_text("\n".join(ids) + "\n")
    np.save(tmp_path / "Mean.npy", np.zeros(d, np.float32))
    np.save(tmp_path / "Std.npy", np.ones(d, np.float32))
    return tmp_path


def test_boundary_error_tool_on_fake_corpus(fake_corpus, capsys):
    result = _load_tool().main(["--data", str(fake_corpus), "--split", "test"])
    out = capsys.readouterr().out
    assert "| uniform |" in out and json.loads(out.strip().splitlines()[-1]) == result
    assert result["captions"] == 3
    for method in ("uniform", "cpd", "kmeans"):
        assert result[method]["boundaries"] == 6
    # Step-change features: cpd and kmeans recover the cuts (all multiples of 4).
    assert result["cpd"]["mean"] == 0.0 and result["kmeans"]["mean"] == 0.0
    assert result["uniform"]["mean"] > 0.0


def test_boundary_error_tool_with_a_tokenizer(fake_corpus, tmp_path_factory):
    rvq = pytest.importorskip("segmo.models.tokenizer", reason="tokenizer module not in this checkout")
    config = rvq.RVQConfig(feature_dim=6, width=16, code_dim=8, codebook_size=8)
    directory = rvq.RVQVAE(config).save_pretrained(tmp_path_factory.mktemp("tokenizer"))
    result = _load_tool().main(["--data", str(fake_corpus), "--tokenizer", str(directory)])
    assert result["captions"] == 3
    assert all(result[m]["boundaries"] == 6 for m in ("uniform", "cpd", "kmeans"))
    assert result["uniform"]["mean"] > 0.0  # same token grid as without a tokenizer


def test_boundary_error_tool_refuses_what_it_cannot_measure(fake_corpus):
    tool = _load_tool()
    with pytest.raises(SegmoError, match="argument --max-motions: expected a whole number >= 1"):
        tool.main(["--data", str(fake_corpus), "--max-motions", "0"])
    path = fake_corpus / "segments" / "000001.json"
    record = json.loads(path.read_text())
    record["captions"][0]["segments"][0]["start"] = -50  # would have read raw[-50:end]
    path.write_text(json.dumps(record))
    with pytest.raises(SegmoError, match=r"000001\.json: not a ground-truth file \(captions\[0\]"):
        tool.main(["--data", str(fake_corpus)])
    np.save(fake_corpus / "Std.npy", np.zeros(6, np.float32))
    with pytest.raises(SegmoError, match=r"Std\.npy: the statistics must be finite, every std > 0"):
        tool.main(["--data", str(fake_corpus)])
