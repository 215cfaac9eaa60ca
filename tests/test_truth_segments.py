"""tools/truth_segments.py: the corpus' ground-truth segments as a segmentation source."""

import json
from pathlib import Path

import pytest
from conftest import load_tool

from segmo.cli import run
from segmo.errors import SegmoError
from segmo.synth import build_corpus
from segmo.text.extract import segment_folder
from segmo.text.rules import RuleSegmenter


def test_truth_segments_are_the_ground_truth_and_resume(tmp_path: Path):
    tool = load_tool("truth_segments")
    data = build_corpus(tmp_path / "corpus", 8, seed=0, progress=False)
    segment_folder(data, RuleSegmenter(), "rule", progress=False)
    result = tool.main(["--data", str(data)])
    assert result["summary"]["processed_files"] == 8
    agreement = result["rule_agreement"]
    assert 0.0 <= agreement["rule_equals_truth"] <= agreement["rule_count_equals_truth"] <= 1.0
    # the corpus' own captions ("raises ... and brings it back down" is one action)
    assert agreement["rule_count_equals_truth"] >= 0.95, agreement
    record = json.loads((data / "segments" / "000000.json").read_text())
    lines = (data / "text_segments" / "truth" / "000000.txt").read_text().splitlines()
    assert lines == ["#".join(s["text"] for s in c["segments"]) for c in record["captions"]]
    assert tool.main(["--data", str(data)])["summary"]["processed_files"] == 0  # nothing stale


def test_truth_segments_need_ground_truth(tmp_path: Path, capsys):
    tool = load_tool("truth_segments")
    (tmp_path / "texts").mkdir()
    with pytest.raises(SegmoError, match="no segments/<id>.json"):
        tool.main(["--data", str(tmp_path)])
    with pytest.raises(SystemExit) as stop:  # as a command: one line, exit status 2
        run("truth_segments.py", tool.main, ["--data", str(tmp_path)])
    assert stop.value.code == 2
    (line,) = capsys.readouterr().err.splitlines()
    assert line.startswith(f"truth_segments.py: --data {tmp_path}: no segments/<id>.json")


def test_truth_segments_pass_over_rule_files_of_motions_gone(tmp_path: Path):
    tool = load_tool("truth_segments")
    data = build_corpus(tmp_path / "corpus", 4, seed=0, progress=False)
    segment_folder(data, RuleSegmenter(), "rule", progress=False)
    (data / "texts" / "000003.txt").unlink()  # its rule file stays behind
    result = tool.main(["--data", str(data)])
    assert result["summary"]["motions"] == 3
    assert result["rule_agreement"]["captions"] == 3 * 3
