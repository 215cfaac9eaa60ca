"""Attention diagnostics on maps whose answer is known, and on a recorded generation."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from test_attention_recorder import LENGTHS, STEPS, run, tiny_models

from segmo.evaluation.attention import (
    attention_grounding,
    kind_share,
    plot_segment_attention,
    prefix_share,
    sentence_share,
    sink_ratio,
)
from segmo.models.attention_recorder import AttentionMap, record_attention
from segmo.models.text_prefix import prefix_labels


def make_map(prefix: list[float], n: int = 4, prefix_valid: list[bool] | None = None,
             motion_valid: int | None = None, block: int = 0, step: int = 0) -> AttentionMap:
    """One row, one head, n queries; every query puts `prefix` on the prefix keys and the
    rest evenly on the motion keys."""
    p = len(prefix)
    rest = (1 - sum(prefix)) / n
    weights = torch.tensor([*prefix, *[rest] * n]).expand(1, 1, n, p + n).clone()
    valid = torch.tensor([*(prefix_valid or [True] * p), *[True] * n])[None]
    if motion_valid is not None:
        valid[0, p + motion_valid:] = False
    return AttentionMap("mask", step, block, torch.tensor([0]), torch.arange(n)[None], weights,
                        valid, [*prefix_labels(p - 1), *(f"motion {i}" for i in range(n))])


@pytest.mark.parametrize("prefix, valid, expected", [
    ([0.2, 0.2, 0.2], None, 0.0),                 # uniform over three keys
    ([0.6, 0.0, 0.0], None, 1.0),                 # all on one key
    ([0.45, 0.15], None, 0.5),                    # two keys, 0.75 / 0.25 of the prefix
    ([0.3, 0.1, 0.0], [True, True, False], 0.5),  # an empty slot does not count as a key
])
def test_sink_ratio_is_zero_for_uniform_and_one_for_a_single_key(prefix, valid, expected):
    assert sink_ratio([make_map(prefix, prefix_valid=valid)])["mean"] == pytest.approx(expected, abs=1e-6)


def test_sink_ratio_undefined_below_two_keys_and_top_k():
    assert math.isnan(sink_ratio([make_map([0.5, 0.0], prefix_valid=[True, False])])["mean"])
    # Top-2 of four keys: (0.4 + 0.4) of 1.0 → (0.8 − 0.5) / 0.5.
    assert sink_ratio([make_map([0.4, 0.4, 0.1, 0.1])], k=2)["mean"] == pytest.approx(0.6)
    with pytest.raises(ValueError, match="k must be"):
        sink_ratio([make_map([0.5, 0.5])], k=0)


def test_prefix_and_sentence_shares_by_block_and_step():
    maps = [make_map([0.3, 0.1], block=0, step=0), make_map([0.1, 0.1], block=1, step=0),
            make_map([0.6, 0.2], block=0, step=1, motion_valid=2)]
    shares = prefix_share(maps)
    assert shares["by_block"] == pytest.approx({0: (0.4 * 4 + 0.8 * 2) / 6, 1: 0.2})
    assert shares["by_step"] == pytest.approx({0: 0.3, 1: 0.8})
    assert sentence_share(maps)["by_block"][1] == pytest.approx(0.5)
    assert sentence_share(maps)["by_step"][1] == pytest.approx(0.75)


def test_prefix_mass_by_kind_of_key_finds_a_start_word_sink():
    # sentence, two segments, three words (start token first): the start word holds half.
    m = make_map([0.1, 0.1, 0.1, 0.4, 0.05, 0.05])
    m.key_labels[3:6] = ["word 0", "word 1", "word 2"]
    shares = kind_share([m])
    assert {kind: figures["mean"] for kind, figures in shares.items()} == pytest.approx(
        {"sentence": 0.125, "segments": 0.25, "start word": 0.5, "words": 0.125})
    assert shares["sentence"]["mean"] == pytest.approx(sentence_share([m])["mean"])
    # A model without word keys has no word kinds.
    assert set(kind_share([make_map([0.3, 0.1])])) == {"sentence", "segments"}


def test_attention_grounding_counts_tokens_on_their_segment():
    n = 6
    weights = torch.zeros(1, 2, n, 3 + n)
    weights[0, :, :3, 1] = 0.5   # segment 1 attended on tokens 0-2
    weights[0, :, 3:, 2] = 0.5   # segment 2 on tokens 3-5
    weights[..., 0] = 0.2
    labels = [*prefix_labels(2), *(f"motion {i}" for i in range(n))]
    m = AttentionMap("mask", 0, 0, torch.tensor([0]), torch.arange(n)[None], weights,
                     torch.ones(1, 3 + n, dtype=torch.bool), labels)
    assert attention_grounding([m], [[(0, 3), (3, 6)]])["mean"] == 1.0
    assert attention_grounding([m], [[(0, 2), (2, 6)]])["mean"] == pytest.approx(5 / 6)
    assert attention_grounding([m], [[(3, 6), (0, 3)]])["mean"] == 0.0
    assert attention_grounding([m], [[(0, 3), (3, 6)]])["tokens"] == 6


def test_attention_grounding_leaves_out_one_segment_captions():
    # With one segment key the largest segment weight is always on it: no evidence either way.
    n = 6
    weights = torch.zeros(2, 2, n, 3 + n)
    weights[:, :, :3, 1] = 0.5   # both rows: segment 1 attended on tokens 0-2
    weights[:, :, 3:, 2] = 0.5   # segment 2 on tokens 3-5
    labels = [*prefix_labels(2), *(f"motion {i}" for i in range(n))]
    m = AttentionMap("mask", 0, 0, torch.tensor([0, 1]), torch.arange(n).expand(2, n), weights,
                     torch.ones(2, 3 + n, dtype=torch.bool), labels)
    found = attention_grounding([m], [[(3, 6), (0, 3)], [(0, 6)]])
    assert found["mean"] == 0.0 and found["tokens"] == 6
    alone = attention_grounding([m], [[(0, 6)], [(0, 6)]])
    assert alone["tokens"] == 0 and math.isnan(alone["mean"]) and alone["by_block"] == {}


def test_diagnostics_of_a_recorded_generation(tmp_path):
    mask, residual = tiny_models()
    with record_attention({"mask": mask}) as recording:
        run(mask, residual, "fp32")
    maps = recording.of("mask")
    for figures in (sink_ratio(maps), prefix_share(maps), sentence_share(maps)):
        assert set(figures["by_step"]) == set(range(STEPS)) and set(figures["by_block"]) == {0, 1}
        assert all(0.0 <= v <= 1.0 for v in figures["by_block"].values())
    n = int(LENGTHS.max()) // 4
    found = attention_grounding(maps[:1], [[(0, 5), (5, n)], [(0, 3), (3, 6)]])
    assert found["tokens"] == n + 6 and 0.0 <= found["mean"] <= 1.0
    png = plot_segment_attention(maps[0], 0, ["walks", "jumps"], tmp_path / "a.png", spans=[(0, 5), (5, n)])
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 5000
    assert np.isfinite(sink_ratio(maps)["mean"])


def test_content_words_keep_what_a_motion_does():
    from segmo.evaluation.attention import content_words

    pieces = ["[CLS]", "first", ",", "a", "man", "walks", "straight", "then", "he", "jump", "##s",
              "twice", "with", "his", "left", "arm", ".", "[SEP]"]
    assert content_words(pieces) == [(4, "man"), (5, "walks"), (6, "straight"), (9, "jumps"),
                                     (11, "twice"), (14, "left"), (15, "arm")]
    assert content_words(["[CLS]", "[SEP]"]) == []


def test_plot_with_word_keys_adds_a_panel_of_content_words(tmp_path):
    n = 6
    labels = [*prefix_labels(2, 3), *(f"motion {i}" for i in range(n))]
    weights = torch.full((1, 1, n, len(labels)), 1.0 / len(labels))
    m = AttentionMap("mask", 0, 3, torch.tensor([0]), torch.arange(n)[None], weights,
                     torch.ones(1, len(labels), dtype=torch.bool), labels)
    spans = [(0, 3), (3, 6)]
    one = plot_segment_attention(m, 0, ["walks", "jumps"], tmp_path / "one.png", spans=spans)
    two = plot_segment_attention(m, 0, ["walks", "jumps"], tmp_path / "two.png", spans=spans,
                                 words=[(1, "walks"), (2, "jumps")])

    def height(png):  # the PNG header's IHDR height
        return int.from_bytes(png.read_bytes()[20:24], "big")
    assert height(two) == 2 * height(one)
