"""tools/grow_train.py: a corpus' train split grown from a bigger corpus of the same seed,
val and test unchanged."""

import json
from pathlib import Path

import pytest
from conftest import load_tool

from segmo.data.layout import read_split
from segmo.synth import build_corpus


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
        with pytest.raises(SystemExit) as stop:
            tool.main(["--data", str(small), "--add", str(add), "--out", str(out)])
        assert message in str(stop.value)
        assert not out.exists() or out == small
    big = build_corpus(tmp_path / "big", 30, seed=0, progress=False)
    with pytest.raises(SystemExit) as stop:
        tool.main(["--data", str(small), "--add", str(big), "--out", str(small)])
    assert f"--out {small}: exists" in str(stop.value)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["big", "fewer", "other", "small"]
