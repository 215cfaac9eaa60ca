"""RuleSegmenter: golden captions, paper examples, robustness on real and random text."""

from __future__ import annotations

import json
import random
from pathlib import Path

import pytest

from segmo.text.rules import MAX_SEGMENTS, RuleSegmenter, TextSegmenter

GOLDEN = Path(__file__).with_name("golden_segments.json")
SHARED = Path(__file__).resolve().parents[1].parent / "shared"
KIT = SHARED / "fixtures" / "kitml" / "annotations.json"


def _golden() -> list[dict]:
    return json.loads(GOLDEN.read_text(encoding="utf-8"))


def test_golden_set_is_large_enough_and_well_formed():
    golden = _golden()
    assert len(golden) >= 60
    for entry in golden:
        assert 1 <= len(entry["segments"]) <= MAX_SEGMENTS, entry
        assert all("#" not in s for s in entry["segments"]), entry


@pytest.mark.parametrize("entry", _golden(), ids=lambda e: e["caption"][:40] or "<empty>")
def test_golden_exact_match(entry):
    assert RuleSegmenter().segment_one(entry["caption"]) == entry["segments"]


def test_batch_interface_and_protocol():
    segmenter = RuleSegmenter()
    assert isinstance(segmenter, TextSegmenter)
    assert segmenter.name == "rule"
    out = segmenter.segment(["a man runs after walking.", "a person waves."])
    assert out == [["a man walks", "a man runs"], ["a person waves"]]


def test_single_action_is_the_caption_minus_final_punctuation():
    caption = "  A person, slowly, walks forward!  "
    assert RuleSegmenter().segment_one(caption) == ["A person, slowly, walks forward"]


def test_tail_is_merged_beyond_max_segments():
    caption = "a person walks, stops, turns, jumps, bows, claps and then lies down"
    out = RuleSegmenter().segment_one(caption)
    assert len(out) == MAX_SEGMENTS
    # the clauses are joined before the subject is restored, so it is said once
    assert out[-1] == "a person bows, then claps, then lies down"
    assert RuleSegmenter(max_segments=2).segment_one(caption) == [
        "a person walks", "a person stops, then turns, then jumps, then bows, then claps, then lies down"]
    assert RuleSegmenter(max_segments=1).segment_one("a man walks. then he sits down, then waves") == [
        "a man walks, then he sits down, then waves"]  # a clause's own subject stays


def test_rejects_bad_arguments():
    with pytest.raises(ValueError, match="max_segments"):
        RuleSegmenter(max_segments=0)
    with pytest.raises(TypeError, match="must be str"):
        RuleSegmenter().segment([None])  # type: ignore[list-item]


def test_never_raises_on_random_strings():
    rng = random.Random(0)
    words = ("a person walks then and after before while , . as if the he runs walking "
             "sits down up # ; ! 3 steps next to being is followed by finally stands kneeling "
             "waving raises lowers his arms at same time afterwards two back that who").split()
    alphabet = "abc ,.;#!?'-/\t\néü0"
    segmenter = RuleSegmenter()
    for _ in range(3000):
        if rng.random() < 0.5:
            text = " ".join(rng.choice(words) for _ in range(rng.randint(0, 14)))
        else:
            text = "".join(rng.choice(alphabet) for _ in range(rng.randint(0, 30)))
        out = segmenter.segment_one(text)
        assert 1 <= len(out) <= MAX_SEGMENTS and all(isinstance(s, str) for s in out)


def test_all_real_kit_captions():
    if not KIT.is_file():
        pytest.skip(f"KIT-ML annotations not found at {KIT} (shared fixtures absent)")
    data = json.loads(KIT.read_text(encoding="utf-8"))
    captions = [a["text"] for entry in data.values() for a in entry["annotations"]]
    assert len(captions) > 6000
    results = RuleSegmenter().segment(captions)
    multi = 0
    for caption, segments in zip(captions, results):
        assert 1 <= len(segments) <= MAX_SEGMENTS, caption
        assert all(s.strip() for s in segments), caption
        if len(segments) == 1:
            assert segments[0] == caption.strip().rstrip(".,;:!? \t\n")
        multi += len(segments) > 1
    # most KIT captions describe one action, but sequences must be found
    assert 0.05 < multi / len(captions) < 0.5
