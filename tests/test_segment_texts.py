"""`segmo segment-texts`: outputs on a tiny dataset folder, resumability, freshness by
content (manifest.jsonl), captions without words, and the dataset reader's side of both."""

from __future__ import annotations

import json
import shutil

import pytest
from conftest import build_text_dataset

from segmo.cli import main as segmo_main
from segmo.data.humanml3d import MotionDataset
from segmo.errors import SegmoError
from segmo.text.captions import captions_hash, read_caption_lines
from segmo.text.extract import format_line, segment_folder
from segmo.text.manifest import SegmentManifest
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
    with pytest.raises(SegmoError, match=r"000002\.txt:2: not UTF-8 text .* at byte 7 of the line"):
        segment_folder(root, RuleSegmenter(), progress=False)
    with pytest.raises(SegmoError, match="nowhere: no such folder"):
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
    path.write_text("a man  walks#a/DET#0#0\n\n  \nno tags here\n.#x#0#0\n")
    lines = read_caption_lines(path)
    assert [(c.lineno, c.caption) for c in lines] == [(1, "a man walks"), (4, "no tags here"), (5, ".")]
    shutil.rmtree(tmp_path)


# ---------------------------------------------------------------- freshness by content
def test_a_caption_edited_in_place_is_resegmented(tmp_path, capsys):
    root = _dataset(tmp_path / "data")
    segment_folder(root, RuleSegmenter(), progress=False)
    before = _outputs(root)
    text = root / "texts" / "000004.txt"  # same number of lines, one caption changed
    text.write_text("a man runs after walking#x#0.0#0.0\na person kneels then prays#x#0.0#0.0\n")
    summary = segment_folder(root, RuleSegmenter(), progress=False)
    assert summary["processed_files"] == 1 and summary["skipped_files"] == 4
    after = _outputs(root)
    assert after["000004.txt"] == "a man walks#a man runs\na person kneels#a person prays\n"
    assert {k: v for k, v in after.items() if k != "000004.txt"} == \
        {k: v for k, v in before.items() if k != "000004.txt"}
    record = SegmentManifest(root / "text_segments" / "rule").get("000004")
    assert record["captions"] == captions_hash(["a man runs after walking", "a person kneels then prays"])
    assert record["lines"] == 2 and record["fallbacks"] == []


def test_a_huge_caption_edited_in_place_is_segmented(tmp_path):
    root = _dataset(tmp_path / "data")
    segment_folder(root, RuleSegmenter(), progress=False)
    words = ("a person walks forward then turns around and waves with the left hand " * 715).split()[:10_000]
    (root / "texts" / "000002.txt").write_text(" ".join(words) + "#x#0#0\n")
    assert segment_folder(root, RuleSegmenter(), progress=False)["processed_files"] == 1
    line = _outputs(root)["000002.txt"]
    assert line.count("\n") == 1 and 1 <= len(line.split("#")) <= 5
    assert line.startswith("a person walks forward#a person turns around")


def test_manifest_records_and_compaction(tmp_path):
    root = _dataset(tmp_path / "data")
    folder = root / "text_segments" / "rule"
    segment_folder(root, RuleSegmenter(), progress=False)
    (root / "texts" / "000002.txt").write_text("a man jumps#x#0#0\n")
    segment_folder(root, RuleSegmenter(), progress=False)
    lines = (folder / "manifest.jsonl").read_text().splitlines()
    assert [json.loads(x)["id"] for x in lines] == sorted(TEXTS)  # one record per id, compacted


def test_a_torn_last_record_is_ignored_and_cut_off(tmp_path):
    root = _dataset(tmp_path / "data")
    folder = root / "text_segments" / "rule"
    segment_folder(root, RuleSegmenter(), progress=False)
    manifest = folder / "manifest.jsonl"
    records = manifest.read_text().splitlines()
    last = json.loads(records[-1])["id"]
    # as a kill -9 leaves it: the last record never finished
    manifest.write_text("\n".join(records[:-1]) + "\n" + records[-1][:25])
    assert SegmentManifest(folder).get(last) is None and SegmentManifest(folder).get("000001")
    summary = segment_folder(root, RuleSegmenter(), progress=False)
    assert summary["processed_files"] == 1  # the unrecorded file is redone
    assert manifest.read_text().splitlines() == records


def test_a_corrupt_record_names_the_manifest_line(tmp_path):
    root = _dataset(tmp_path / "data")
    folder = root / "text_segments" / "rule"
    segment_folder(root, RuleSegmenter(), progress=False)
    manifest = folder / "manifest.jsonl"
    records = manifest.read_text().splitlines()
    manifest.write_text("\n".join([records[0], "{oops", *records[2:]]) + "\n")
    with pytest.raises(SegmoError, match=r"manifest\.jsonl:2: not a segment record"):
        segment_folder(root, RuleSegmenter(), progress=False)


def test_files_without_a_record_are_redone(tmp_path):
    root = _dataset(tmp_path / "data")
    folder = root / "text_segments" / "rule"
    segment_folder(root, RuleSegmenter(), progress=False)
    manifest = folder / "manifest.jsonl"
    manifest.write_text("".join(r + "\n" for r in manifest.read_text().splitlines() if '"000002"' not in r))
    (folder / "000002.txt").write_text("someone's old segments\n")  # written, record lost (a kill)
    assert segment_folder(root, RuleSegmenter(), progress=False)["processed_files"] == 1
    assert _outputs(root)["000002.txt"] == "a man waves#a man sits down\n"


def test_a_caption_without_words_is_reported_not_blank(tmp_path, capsys, caplog):
    root = _dataset(tmp_path / "data")
    (root / "texts" / "000002.txt").write_text("a man waves then sits#x#0#0\n.#x#0#0\n!!!#x#0#0\n")
    segmo_main(["segment-texts", "--data", str(root), "--quiet"])
    captured = capsys.readouterr()
    assert _outputs(root)["000002.txt"] == "a man waves#a man sits\n.\n!!!\n"  # no blank line
    assert "2 caption(s) without words, not segmented: texts/000002.txt:2, texts/000002.txt:3" \
        in captured.out
    assert "000002.txt:2: caption '.' has no words; not segmented" in caplog.text
    summary = json.loads((root / "text_segments" / "rule" / "summary.json").read_text())
    assert summary["no_words"] == ["texts/000002.txt:2", "texts/000002.txt:3"]
    assert summary["captions"] == 9  # those with words
    record = SegmentManifest(root / "text_segments" / "rule").get("000002")
    assert record["no_words"] == [{"line": 2, "index": 1}, {"line": 3, "index": 2}]


# ---------------------------------------------------------------- the dataset reader's side
@pytest.fixture
def motion_data(tmp_path):
    return build_text_dataset(tmp_path / "data", motions=6, encoders={})


def test_reader_refuses_a_stale_segment_file(motion_data):
    train = (motion_data / "train.txt").read_text().split()
    text = motion_data / "texts" / f"{train[0]}.txt"
    lines = text.read_text().splitlines()
    text.write_text("a person crawls then stands up#x#0.0#0.0\n" + "\n".join(lines[1:]) + "\n")
    stale = motion_data / "text_segments" / "rule" / f"{train[0]}.txt"
    with pytest.raises(SegmoError, match=rf"{stale} is stale: its captions were edited .*re-run "
                                         r"`segmo segment-texts --data"):
        MotionDataset(motion_data, "train", text_segments="rule")
    segment_folder(motion_data, RuleSegmenter(), progress=False)  # the fix the message names
    ds = MotionDataset(motion_data, "train", text_segments="rule")
    assert ds[0]["segments"] == ["a person crawls", "a person stands up"]


def test_reader_skips_a_caption_without_words_as_a_bad_line(motion_data):
    train = (motion_data / "train.txt").read_text().split()
    text = motion_data / "texts" / f"{train[0]}.txt"
    lines = text.read_text().splitlines()
    text.write_text(lines[0] + "\n.#x#0.0#0.0\n" + "\n".join(lines[1:]) + "\n")
    segment_folder(motion_data, RuleSegmenter(), progress=False)
    with pytest.warns(UserWarning, match=r"bad_line: .*\.txt:2: caption without words: '\.'"):
        ds = MotionDataset(motion_data, "train", text_segments="rule")
    assert ds.summary["bad_line"] == 1
    mine = [ds.entries[i] for i in range(len(ds)) if ds.entries[i].motion_id == train[0]]
    assert [e.caption_index for e in mine] == [0, 2]  # line 3's caption keeps its segments
    assert mine[1].segments == tuple(RuleSegmenter().segment_one(mine[1].caption))


def test_reader_keeps_the_line_count_check_without_a_manifest(motion_data):
    folder = motion_data / "text_segments" / "rule"
    (folder / "manifest.jsonl").unlink()  # a hand-made folder, as the reference code writes
    assert len(MotionDataset(motion_data, "train", text_segments="rule")) > 0
    train = (motion_data / "train.txt").read_text().split()
    (folder / f"{train[0]}.txt").write_text("a person walks\n")
    with pytest.raises(SegmoError, match=r"has 1 lines but .* has 2"):
        MotionDataset(motion_data, "train", text_segments="rule")


def test_segment_texts_with_the_rules_starts_without_torch(tmp_path):
    """Extraction with the rules or a server needs no torch; importing it (through the
    text package and the LLM module) took 2 of the command's 3 s to start, in every rank
    of a preprocessing job and every resumed run."""
    import subprocess
    import sys

    root = build_text_dataset(tmp_path / "data")
    code = ("import sys; from segmo.cli import main\n"
            "try:\n    main(['segment-texts', '--data', sys.argv[1], '--quiet'])\n"
            "except SystemExit as e:\n    assert not e.code, e.code\n"
            "print(sorted(m for m in ('torch', 'transformers') if m in sys.modules))")
    done = subprocess.run([sys.executable, "-c", code, str(root)], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip().splitlines()[-1] == "[]"
    assert any((root / "text_segments" / "rule").glob("*.txt"))
