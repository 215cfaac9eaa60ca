"""`segmo segment-texts`: outputs on a tiny dataset folder, resumability, errors."""

from __future__ import annotations

import json
import shutil

import pytest

from segmo.cli import main as segmo_main
from segmo.text.extract import format_line, read_captions, segment_folder
from segmo.text.rules import RuleSegmenter

TEXTS = {
    "000001": ["a person walks forward, then waves twice.#a/DET person/NOUN#0.0#0.0",
               "someone jumps after walking#someone/PRON#0.0#0.0",
               "a person waves#a/DET#1.0#3.5"],
    "000002": ["before sitting down, a man waves#before/ADP#0.0#0.0"],
    "000003": ["a person stands and waves#a/DET#0.0#0.0", "a person walks while waving#x#0.0#0.0"],
    "M000003": ["a person walks forward, turns around, and walks back#x#0.0#0.0"],
    "000004": ["a man runs after walking#x#0.0#0.0", "a person crawls then stands up then jumps#x#0.0#0.0"],
}


def _dataset(root):
    (root / "texts").mkdir(parents=True)
    for motion_id, lines in TEXTS.items():
        (root / "texts" / f"{motion_id}.txt").write_text("\n".join(lines) + "\n", encoding="utf-8")
    return root


def _outputs(root, name="rule"):
    folder = root / "text_segments" / name
    return {p.name: p.read_text(encoding="utf-8") for p in sorted(folder.glob("*.txt"))}


def test_cli_on_a_tiny_dataset(tmp_path, capsys):
    root = _dataset(tmp_path / "data")
    segmo_main(["segment-texts", "--data", str(root)])
    out = _outputs(root)
    assert set(out) == {f"{i}.txt" for i in TEXTS}
    assert out["000001.txt"] == ("a person walks forward#a person waves twice\n"
                                 "someone walks#someone jumps\na person waves\n")
    assert out["000002.txt"] == "a man waves#a man sits down\n"
    assert out["M000003.txt"] == "a person walks forward#a person turns around#a person walks back\n"
    for motion_id, lines in TEXTS.items():  # line i <-> line i
        assert len(out[f"{motion_id}.txt"].splitlines()) == len(lines)
    folder = root / "text_segments" / "rule"
    meta = json.loads((folder / "meta.json").read_text())
    assert meta["backend"] == "rule" and meta["name"] == "rule" and meta["prompt_hash"] is None
    summary = json.loads((folder / "summary.json").read_text())
    assert summary["motions"] == 5 and summary["captions"] == 9
    assert summary["segment_histogram"] == {"1": 3, "2": 4, "3": 2}
    assert summary["fallbacks"] == 0 and summary["processed_files"] == 5
    assert "9 captions" in capsys.readouterr().out
    assert not list(folder.glob(".*.tmp"))

    segmo_main(["segment-texts", "--data", str(root)])  # nothing left to do
    assert json.loads((folder / "summary.json").read_text())["skipped_files"] == 5
    assert _outputs(root) == out


class _Dying(RuleSegmenter):
    """Dies (as a killed process would) on its k-th call."""

    def __init__(self, k: int):
        super().__init__()
        self.calls, self.k = 0, k

    def segment(self, texts):
        self.calls += 1
        if self.calls == self.k:
            raise KeyboardInterrupt("killed")
        return super().segment(texts)


def test_killed_run_resumes_to_identical_files(tmp_path):
    whole = _dataset(tmp_path / "whole")
    segment_folder(whole, RuleSegmenter(), progress=False)
    killed = _dataset(tmp_path / "killed")
    with pytest.raises(KeyboardInterrupt):
        segment_folder(killed, _Dying(k=3), batch_captions=1, progress=False)
    assert len(_outputs(killed)) == 2  # two files done before the kill
    (killed / "text_segments" / "rule" / ".000004.txt.tmp").write_text("half a fi")  # torn write
    summary = segment_folder(killed, RuleSegmenter(), batch_captions=1, progress=False)
    assert summary["skipped_files"] == 2 and summary["processed_files"] == 3
    assert _outputs(killed) == _outputs(whole)
    assert not list((killed / "text_segments" / "rule").glob(".*.tmp"))


def test_changed_texts_file_is_redone_and_overwrite_redoes_all(tmp_path):
    root = _dataset(tmp_path / "data")
    segment_folder(root, RuleSegmenter(), progress=False)
    (root / "texts" / "000002.txt").write_text("a man jumps then sits#x#0#0\na man claps#x#0#0\n")
    summary = segment_folder(root, RuleSegmenter(), progress=False)
    assert summary["processed_files"] == 1
    assert _outputs(root)["000002.txt"] == "a man jumps#a man sits\na man claps\n"
    assert segment_folder(root, RuleSegmenter(), overwrite=True, progress=False)["processed_files"] == 5


def test_errors_name_the_file_and_line(tmp_path):
    root = _dataset(tmp_path / "data")
    bad = root / "texts" / "000002.txt"
    bad.write_bytes(b"a man waves#x#0#0\na man \xff jumps#x#0#0\n")
    with pytest.raises(ValueError, match=r"000002\.txt:2: not UTF-8"):
        segment_folder(root, RuleSegmenter(), progress=False)
    with pytest.raises(FileNotFoundError, match="no texts/ folder"):
        segment_folder(tmp_path / "nowhere", RuleSegmenter(), progress=False)


def test_other_model_in_the_same_folder_is_refused(tmp_path):
    root = _dataset(tmp_path / "data")
    segment_folder(root, RuleSegmenter(), progress=False)
    meta_path = root / "text_segments" / "rule" / "meta.json"
    meta = json.loads(meta_path.read_text())
    meta_path.write_text(json.dumps({**meta, "prompt_hash": "0123"}))
    with pytest.raises(ValueError, match="prompt_hash"):
        segment_folder(root, RuleSegmenter(), progress=False)
    assert segment_folder(root, RuleSegmenter(), overwrite=True, progress=False)["processed_files"] == 5


def test_cli_argument_errors(tmp_path, capsys):
    root = _dataset(tmp_path / "data")
    with pytest.raises(SystemExit):
        segmo_main(["segment-texts", "--data", str(root), "--backend", "openai", "--model", "m"])
    assert "--base-url" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        segmo_main(["segment-texts", "--data", str(root), "--model", "m"])
    assert "--backend rule takes none" in capsys.readouterr().err


def test_helpers(tmp_path):
    assert format_line(["a # b", "c\nd  e"]) == "a b#c d e"
    path = tmp_path / "x.txt"
    path.write_text("a man walks#a/DET#0#0\n\nno tags here\n")
    assert read_captions(path) == ["a man walks", "", "no tags here"]
    shutil.rmtree(tmp_path)
