"""tools/grow_train.py: a corpus' train split grown from a bigger corpus of the same seed,
val and test unchanged."""

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import load_tool, tool_failure

from segmo.data.layout import read_split
from segmo.errors import SegmoError
from segmo.synth import build_corpus
from segmo.synth.captions import HELD_OUT_TEMPLATES


def test_grown_corpus_keeps_val_and_test_and_adds_only_train_motions(tmp_path: Path, capsys):
    tool = load_tool("grow_train")
    small = build_corpus(tmp_path / "small", 20, seed=0, progress=False)
    big = build_corpus(tmp_path / "big", 60, seed=0, progress=False)
    out = tmp_path / "grown"
    tool.main(["--data", str(small), "--add", str(big), "--out", str(out)])
    result = json.loads(capsys.readouterr().out.splitlines()[-1])
    for split in ("val", "test"):
        assert read_split(out, split) == read_split(small, split)
    added = [i for i in read_split(big, "train") if int(i) >= 20]
    assert read_split(out, "train") == read_split(small, "train") + added
    assert result["added"] == len(added) > 0 and result["train"] == len(read_split(small, "train"))
    # every motion of the grown corpus is its source's, captions and ground truth included
    for mid in read_split(out, "test")[:2] + added[:2]:
        source = small if int(mid) < 20 else big
        for sub, ext in (("new_joint_vecs", "npy"), ("texts", "txt"), ("segments", "json")):
            assert (out / sub / f"{mid}.{ext}").read_bytes() == \
                (source / sub / f"{mid}.{ext}").read_bytes()
    held_out = [i for i in read_split(big, "test") if int(i) >= 20]
    assert held_out and not (out / "texts" / f"{held_out[0]}.txt").exists()
    assert (out / "Mean.npy").read_bytes() == (small / "Mean.npy").read_bytes()
    assert json.loads((out / "corpus.json").read_text())["train_added"]["motions"] == len(added)


def test_grow_train_refuses_corpora_that_do_not_match(tmp_path: Path, capsys):
    tool = load_tool("grow_train")
    small = build_corpus(tmp_path / "small", 10, seed=0, progress=False)
    other = build_corpus(tmp_path / "other", 30, seed=1, progress=False)
    fewer = build_corpus(tmp_path / "fewer", 8, seed=0, progress=False)
    for add, out, message in (
            (other, tmp_path / "a", f"--add {other}: seed 1, --data {small} has 0"),
            (fewer, tmp_path / "b", f"--add {fewer}: 8 motions, no more than --data's 10"),
            (tmp_path / "nothing", tmp_path / "c", "no corpus.json"),
            (fewer, small, "no more than"),
    ):
        with pytest.raises(SegmoError) as stop:
            tool.main(["--data", str(small), "--add", str(add), "--out", str(out)])
        assert message in str(stop.value)
        assert not out.exists() or out == small
    big = build_corpus(tmp_path / "big", 30, seed=0, progress=False)
    with pytest.raises(SegmoError) as stop:
        tool.main(["--data", str(small), "--add", str(big), "--out", str(small)])
    assert f"--out {small}: exists" in str(stop.value)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["big", "fewer", "other", "small"]


def test_segment_crops_cut_runs_of_actions_from_the_train_motions(tmp_path: Path, capsys):
    tool = load_tool("grow_train")
    data = build_corpus(tmp_path / "data", 30, seed=0, progress=False)
    out = tmp_path / "crops"
    tool.main(["--data", str(data), "--segment-crops", "--out", str(out)])
    result = json.loads(capsys.readouterr().out.splitlines()[-1])
    train = read_split(data, "train")
    crops = read_split(out, "train")[len(train):]
    assert read_split(out, "train")[:len(train)] == train and result["added"] == len(crops) > 0
    for split in ("val", "test"):
        assert read_split(out, split) == read_split(data, split)
    expected = set()
    for mid in train:
        actions = json.loads((data / "segments" / f"{mid}.json").read_text())["actions"]
        for first in range(len(actions)):
            for last in range(first + 1, len(actions) + 1):
                frames = actions[last - 1]["end"] - actions[first]["start"]
                if last - first < len(actions) and frames >= tool.MIN_FRAMES:
                    expected.add(f"{mid}_{first}_{last}")
    assert set(crops) == expected
    for crop in crops:
        mid, first, last = crop.split("_")
        source = json.loads((data / "segments" / f"{mid}.json").read_text())
        truth = json.loads((out / "segments" / f"{crop}.json").read_text())
        taken = source["actions"][int(first):int(last)]
        start = taken[0]["start"]
        # the crop's frames are the source's between its true action boundaries
        features = np.load(out / "new_joint_vecs" / f"{crop}.npy")
        assert np.array_equal(features, np.load(data / "new_joint_vecs" / f"{mid}.npy")[start:taken[-1]["end"]])
        assert np.load(out / "new_joints" / f"{crop}.npy").shape == (len(features), 22, 3)
        assert [(a["action"], a["params"], a["start"] + start, a["end"] + start) for a in truth["actions"]] \
            == [(a["action"], a["params"], a["start"], a["end"]) for a in taken]
        lines = (out / "texts" / f"{crop}.txt").read_text().splitlines()
        assert [line.split("#")[0] for line in lines] == [c["text"] for c in truth["captions"]]
        for caption in truth["captions"]:  # worded as train captions are, one segment per action
            assert caption["template"] not in HELD_OUT_TEMPLATES
            assert [s["action"] for s in caption["segments"]] == [a["action"] for a in taken]
    # the corpus' own motions are its own, byte for byte
    assert (out / "new_joint_vecs" / f"{train[0]}.npy").read_bytes() == \
        (data / "new_joint_vecs" / f"{train[0]}.npy").read_bytes()
    assert json.loads((out / "corpus.json").read_text())["segment_crops"] is True


def test_segment_crops_leave_nothing_behind_on_a_broken_motion(tmp_path: Path, capsys):
    tool = load_tool("grow_train")
    data = build_corpus(tmp_path / "data", 12, seed=0, progress=False)
    broken = read_split(data, "train")[-1]
    (data / "segments" / f"{broken}.json").write_text("{not json")
    out = tmp_path / "crops"
    with pytest.raises(SegmoError) as stop:
        tool.main(["--data", str(data), "--segment-crops", "--out", str(out)])
    assert f"motion {broken}" in str(stop.value)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data"]
    # spans past the motion's frames: named with the file, nothing written either
    other = read_split(data, "train")[0]
    path = data / "segments" / f"{other}.json"
    truth = json.loads(path.read_text())
    truth["actions"][-1]["end"] += 50
    path.write_text(json.dumps(truth))
    (data / "segments" / f"{broken}.json").write_text(json.dumps(truth))
    with pytest.raises(SegmoError) as stop:
        tool.main(["--data", str(data), "--segment-crops", "--out", str(out)])
    assert str(path) in str(stop.value) and "do not lie in" in str(stop.value)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data"]
    with pytest.raises(SegmoError, match="not allowed with"):  # one source only
        tool.main(["--data", str(data), "--segment-crops", "--add", str(data), "--out", str(out)])


def test_grow_train_fails_in_one_line_with_exit_status_2(tmp_path: Path, capsys):
    data = build_corpus(tmp_path / "data", 10, seed=0, progress=False)
    big = build_corpus(tmp_path / "big", 12, seed=0, progress=False)
    assert tool_failure("grow_train", ["--data", str(data), "--segment-crops", "--out", str(data)],
                        capsys) == f"grow_train.py: --out {data}: exists; choose a new folder"
    for split in ("test", "val"):
        (data / f"{split}.txt").unlink()
        for source in (["--segment-crops"], ["--add", str(big)]):
            line = tool_failure("grow_train", ["--data", str(data), *source, "--out", str(tmp_path / "o")],
                                capsys)
            assert line == (f"grow_train.py: --data {data}: no {split}.txt; a corpus of `segmo synth` "
                            "has train.txt, val.txt and test.txt")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["big", "data"]
