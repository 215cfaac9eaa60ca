"""Tests of segmo.data: reader, datasets, collate and the DataModule, on tiny random folders."""

from __future__ import annotations

import json
import math
import re
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import SHARED

from segmo.data import (
    MotionDataset,
    MotionWindowDataset,
    collate,
    load_stats,
    parse_text_line,
    read_split,
)
from segmo.errors import SegmoError
from segmo.motion.skeleton import get_skeleton

D = 263  # t2m feature width


def write_dataset(root: Path, lengths: dict[str, int], *, d: int = D, splits=None,
                  captions: dict[str, list[str]] | None = None, seed: int = 0) -> dict[str, np.ndarray]:
    """A HumanML3D-layout folder with random motions; returns the raw arrays by id."""
    rng = np.random.default_rng(seed)
    (root / "new_joint_vecs").mkdir(parents=True, exist_ok=True)
    (root / "texts").mkdir(exist_ok=True)
    arrays = {}
    for mid, t in lengths.items():
        arrays[mid] = rng.normal(size=(t, d)).astype(np.float32)
        np.save(root / "new_joint_vecs" / f"{mid}.npy", arrays[mid])
        lines = (captions or {}).get(mid, [f"a person does {mid}#a/DET person/NOUN#0.0#0.0",
                                           f"someone does {mid}#someone/PRON#nan#nan"])
        (root / "texts" / f"{mid}.txt").write_text("\n".join(lines) + "\n")
    splits = splits or {"train": list(lengths), "val": list(lengths), "test": list(lengths)}
    for name, ids in splits.items():
        (root / f"{name}.txt").write_text("\n".join(ids) + "\n")
    np.save(root / "Mean.npy", rng.normal(size=d).astype(np.float32))
    np.save(root / "Std.npy", rng.uniform(0.5, 2.0, size=d).astype(np.float32))
    return arrays


class FakeCache:
    """The interface of segmo.text.cache.TextFeatureCache, with deterministic features."""

    dim = 8

    def _vec(self, text: str) -> torch.Tensor:
        g = torch.Generator().manual_seed(sum(map(ord, text)))
        return torch.randn(self.dim, generator=g)

    def sentence(self, texts: list[str]) -> torch.Tensor:
        return torch.stack([self._vec(t) for t in texts])

    def tokens(self, text: str) -> torch.Tensor:
        return torch.stack([self._vec(w) for w in text.split()])


# --------------------------------------------------------------------------- reading


def test_parse_text_line():
    cap = parse_text_line("a man walks#a/DET man/NOUN walk/VERB#1.5#4.0", "x.txt", 3)
    assert (cap.text, cap.start, cap.end, cap.whole_clip) == ("a man walks", 1.5, 4.0, False)
    assert parse_text_line("a man walks#a/DET#nan#nan").whole_clip
    assert parse_text_line("a man walks#a/DET#0.0#0.0").whole_clip
    with pytest.raises(ValueError, match=r"x\.txt:7"):
        parse_text_line("a man walks without tags", "x.txt", 7)
    with pytest.raises(ValueError, match=r"x\.txt:2: bad time tags"):
        parse_text_line("a man walks#a/DET#3.0#1.0", "x.txt", 2)
    for tags in ("0.0#inf", "nan#inf", "-inf#2.0"):  # `inf` was an OverflowError at loading
        with pytest.raises(ValueError, match=r"x\.txt:4: time tags must be finite"):
            parse_text_line(f"a man walks#a/DET#{tags}", "x.txt", 4)


def test_missing_split_file_names_path(tmp_path):
    write_dataset(tmp_path, {"a": 60}, splits={"train": ["a"]})
    with pytest.raises(FileNotFoundError, match=r"val\.txt"):
        read_split(tmp_path, "val")
    with pytest.raises(FileNotFoundError, match=r"test\.txt"):
        MotionDataset(tmp_path, "test")


def test_a_split_file_that_cannot_be_read_is_one_line_naming_it(tmp_path):
    """A split file of Latin-1 bytes was a UnicodeDecodeError traceback from `segmo fit`, and
    a folder or a pipe named train.txt was 'not found'."""
    import os

    write_dataset(tmp_path, {"a": 60}, splits={"train": ["a"]})
    (tmp_path / "train.txt").write_bytes(b"a\nmotion_\xe9t\xe9\n")
    with pytest.raises(SegmoError, match=r"train\.txt:2: not UTF-8 text"):
        read_split(tmp_path, "train")
    (tmp_path / "train.txt").unlink()
    os.mkfifo(tmp_path / "train.txt")
    with pytest.raises(SegmoError, match=r"train\.txt: not a regular file"):
        read_split(tmp_path, "train")
    (tmp_path / "train.txt").unlink()
    (tmp_path / "train.txt").mkdir()
    with pytest.raises(SegmoError, match=r"train\.txt: is a folder, not a split file"):
        read_split(tmp_path, "train")
    (tmp_path / "train.txt").rmdir()
    (tmp_path / "train.txt").write_bytes(b"\xef\xbb\xbfa\r\n")  # a Windows editor's file
    assert read_split(tmp_path, "train") == ["a"]


def test_an_id_listed_twice_is_refused_and_shared_splits_are_told(tmp_path):
    """A split listing one motion twice (sampled twice as often, counted twice in a score)
    and test motions that are also train motions were read without a word."""
    from segmo.data import MotionDataModule

    write_dataset(tmp_path, {"a": 60, "b": 60, "c": 60},
                  splits={"train": ["a", "b"], "val": ["c"], "test": ["c", "a"]})
    (tmp_path / "train.txt").write_text("a\nb\n\n a \n")
    with pytest.raises(SegmoError, match=r"train\.txt:4: id 'a' again \(first on line 1\)"):
        read_split(tmp_path, "train")
    (tmp_path / "train.txt").write_text("a\nb\n")
    with pytest.warns(UserWarning) as told:
        MotionDataModule(str(tmp_path), batch_size=2).setup("fit")
    shared = [str(w.message) for w in told if "share" in str(w.message)]
    assert shared == [f"{tmp_path}: the splits share motions: 1 in both train.txt and test.txt "
                      "(first: a); 1 in both val.txt and test.txt (first: c)"]


def test_samples_are_zscored_cropped_and_stats_untouched(tmp_path):
    raw = write_dataset(tmp_path, {"a": 61, "b": 80})
    mean_file, std_file = np.load(tmp_path / "Mean.npy"), np.load(tmp_path / "Std.npy")
    mean, std = mean_file.copy(), std_file.copy()
    ds = MotionDataset(tmp_path, "train", mean=mean, std=std)
    # the caller's arrays are unchanged and still writable; the dataset holds read-only copies
    assert np.array_equal(mean, mean_file) and np.array_equal(std, std_file)
    assert mean.flags.writeable and not ds.mean.flags.writeable and not ds.std.flags.writeable
    assert len(ds) == 4 and ds.summary["samples"] == 4 and ds.summary["motions"] == 2
    s = ds[0]
    assert s["id"] == "a" and s["caption_index"] == 0 and s["segments"] == [s["caption"]]
    assert s["motion"].dtype == torch.float32 and s["motion"].shape == (60, D) and s["length"] == 60
    expected = (raw["a"][:60] - mean_file) / std_file  # evaluation crop starts at frame 0
    assert torch.allclose(s["motion"], torch.from_numpy(expected))
    assert ds[1]["caption"] == "someone does a" and ds[1]["spans"] is None
    # stats files and the preloaded raw motions are not modified by reading samples
    _ = [ds[i] for i in range(len(ds))]
    assert np.array_equal(np.load(tmp_path / "Mean.npy"), mean_file)
    assert np.array_equal(ds.motions.get("a"), raw["a"]) and not ds.motions.get("a").flags.writeable
    m, sd = load_stats(tmp_path)
    assert not m.flags.writeable and m.dtype == np.float32 and sd.shape == (D,)


def test_time_tagged_captions_become_subclips(tmp_path):
    lines = ["whole#w/X#0.0#0.0", "middle part#m/X#1.0#4.0", "too short#s/X#1.0#2.0"]
    raw = write_dataset(tmp_path, {"a": 120}, captions={"a": lines})
    ds = MotionDataset(tmp_path)
    assert [s["id"] for s in ds] == ["a", "a#1"]
    sub = ds[1]
    assert sub["caption_index"] == 1 and sub["length"] == 60  # frames 20..80 at 20 fps
    expected = (raw["a"][20:80] - ds.mean) / ds.std
    assert torch.allclose(sub["motion"], torch.from_numpy(expected))
    assert ds.summary["too_short"] == 1


def test_length_filter_per_skeleton(tmp_path):
    write_dataset(tmp_path, {"short": 39, "min": 40, "max": 199, "long": 200})
    ds = MotionDataset(tmp_path)
    assert sorted({s["id"] for s in ds}) == ["max", "min"]
    assert {s["id"]: s["length"] for s in ds} == {"min": 40, "max": 196}
    assert ds.summary["too_short"] == 2 and ds.summary["too_long"] == 2
    # KIT: another width, fps and minimum length, from the spec alone
    kit = get_skeleton("kit")
    root = tmp_path / "kit"
    write_dataset(root, {"k": 30, "s": 20}, d=kit.feature_dim)
    ds = MotionDataset(root, skeleton="kit")
    assert [s["motion"].shape for s in ds] == [(28, 251), (28, 251)]
    with pytest.raises(ValueError, match=r"Mean\.npy: shape \(251,\), expected \(263,\)"):
        MotionDataset(root, skeleton="t2m")


def test_random_crop_is_a_function_of_seed_epoch_and_index(tmp_path):
    raw = write_dataset(tmp_path, {"a": 43}, captions={"a": ["x#x/X#0#0"]})

    def offset(ds, key):
        m = ds[key]["motion"].numpy() * ds.std + ds.mean
        return int(np.argmin([np.abs(raw["a"][o:o + 40] - m).max() for o in range(4)]))

    def offsets(seed):
        ds = MotionDataset(tmp_path, random_crop=True, seed=seed)
        return [offset(ds, (0, epoch)) for epoch in range(12)]

    a, b = offsets(1), offsets(1)
    assert a == b and len(set(a)) > 1 and offsets(2) != a
    ds = MotionDataset(tmp_path, random_crop=True, seed=1)
    assert {offset(ds, 0) for _ in range(5)} == {a[0]}  # one epoch, one crop per sample
    ds.set_epoch(3)
    assert offset(ds, 0) == a[3]
    assert all(MotionDataset(tmp_path)[0]["motion"].shape == (40, D) for _ in range(2))


# --------------------------------------------------------------------------- malformed


def test_bad_motion_files_are_skipped_and_counted(tmp_path):
    write_dataset(tmp_path, {"ok": 60, "zero": 60, "frames0": 60, "notext": 60, "badline": 60})
    for mid in ("ok2", "gone"):  # "gone" is listed but has no motion file
        (tmp_path / "texts" / f"{mid}.txt").write_text("x#x/X#0#0\n")
    (tmp_path / "new_joint_vecs" / "zero.npy").write_bytes(b"")
    np.save(tmp_path / "new_joint_vecs" / "frames0.npy", np.zeros((0, D), np.float32))
    (tmp_path / "texts" / "notext.txt").unlink()
    (tmp_path / "texts" / "badline.txt").write_text("fine#f/X#0#0\nno fields here\n")
    ids = ["ok", "gone", "zero", "frames0", "notext", "badline"]
    (tmp_path / "train.txt").write_text("\n".join(ids))
    with pytest.warns(UserWarning) as record:
        ds = MotionDataset(tmp_path)
    text = " | ".join(str(w.message) for w in record)
    assert "gone.npy" in text and "zero.npy" in text
    assert "notext.txt" in text and "badline.txt:2" in text
    assert [s["id"] for s in ds] == ["ok", "ok", "badline"]
    summary = ds.summary
    assert (summary["missing"], summary["empty"], summary["missing_text"],
            summary["bad_line"]) == (1, 2, 1, 1)
    with pytest.raises(ValueError, match="gone.npy"):
        MotionDataset(tmp_path, strict=True)


@pytest.mark.parametrize("preload", [True, False])
def test_non_finite_and_absurd_values_are_refused_naming_the_files(tmp_path, preload):
    write_dataset(tmp_path, {f"m{i}": 60 for i in range(6)})
    mean, std = np.load(tmp_path / "Mean.npy"), np.load(tmp_path / "Std.npy")
    for mid, (frame, dim, value) in {"m1": (10, 5, 1e30), "m3": (0, 7, np.nan),
                                     "m4": (59, 262, -np.inf)}.items():
        arr = np.load(tmp_path / "new_joint_vecs" / f"{mid}.npy")
        arr[frame, dim] = value
        np.save(tmp_path / "new_joint_vecs" / f"{mid}.npy", arr)
    with pytest.raises(SegmoError) as error:
        MotionDataset(tmp_path, preload=preload)
    message = str(error.value)
    assert "\n" not in message and "train.txt: 3 of 6 motion files" in message
    assert "m1.npy: frame 10 dim 5 is 1e+30" in message and "m3.npy: frame 0 dim 7 is nan" in message
    assert "m4.npy: frame 59 dim 262 is -inf" in message
    # A finite value just inside the bound is accepted; one beyond it is refused.
    for mid in ("m3", "m4"):
        np.save(tmp_path / "new_joint_vecs" / f"{mid}.npy", np.zeros((60, D), np.float32))
    arr = np.load(tmp_path / "new_joint_vecs" / "m1.npy")
    arr[10, 5] = mean[5] + 999 * std[5]
    np.save(tmp_path / "new_joint_vecs" / "m1.npy", arr)
    assert len(MotionWindowDataset(tmp_path, window=32, preload=preload)) == 6
    with pytest.raises(SegmoError, match=r"1 of 6 .*m1\.npy: frame 10 dim 5 .*max_abs_z=500"):
        MotionWindowDataset(tmp_path, window=32, preload=preload, max_abs_z=500)


@pytest.mark.parametrize("preload", [True, False])
def test_motions_of_other_values_than_real_numbers_are_refused_naming_them(tmp_path, preload):
    """A complex motion trained on its real part with only a ComplexWarning; one of text
    was a TypeError from numpy."""
    write_dataset(tmp_path, {f"m{i}": 60 for i in range(4)})
    np.save(tmp_path / "new_joint_vecs" / "m1.npy", np.zeros((60, D), np.complex64) + 1j)
    np.save(tmp_path / "new_joint_vecs" / "m2.npy", np.full((60, D), "a"))
    with pytest.raises(SegmoError) as error:
        MotionDataset(tmp_path, preload=preload)
    message = str(error.value)
    assert "\n" not in message and "2 of 4 motion files" in message
    assert "m1.npy: values of type complex64, not real numbers" in message
    assert "m2.npy: values of type <U1, not real numbers" in message


def test_a_header_claiming_more_frames_than_the_file_holds_is_skipped_unread(tmp_path):
    """Such a 4 KB file made np.load ask for 1.9 TiB (MemoryError) before it failed."""
    write_dataset(tmp_path, {"ok": 60, "liar": 60})
    path = tmp_path / "new_joint_vecs" / "liar.npy"
    with open(path, "wb") as f:
        np.lib.format.write_array_header_1_0(f, {"descr": "<f4", "fortran_order": False,
                                                 "shape": (2_000_000_000, D)})
        f.write(b"\0" * 4096)
    with pytest.warns(UserWarning, match=r"liar\.npy: its header claims \(2000000000, 263\)"):
        ds = MotionDataset(tmp_path)
    assert {s["id"] for s in ds} == {"ok"} and ds.summary["unreadable"] == 1


def test_statistics_of_other_values_than_real_numbers_are_refused_naming_the_file(tmp_path):
    write_dataset(tmp_path, {"a": 60})
    np.save(tmp_path / "Std.npy", np.full(D, "a"))
    with pytest.raises(SegmoError, match=r"Std\.npy: values of type <U1, not real numbers"):
        load_stats(tmp_path)
    np.save(tmp_path / "Std.npy", np.ones(D, np.complex64))
    with pytest.raises(SegmoError, match=r"Std\.npy: values of type complex64"):
        load_stats(tmp_path)


@pytest.mark.skipif(not (SHARED / "fixtures" / "humanml3d").is_dir(),
                    reason="../shared/fixtures/humanml3d (real HumanML3D data) not present")
def test_real_humanml3d_values_are_well_inside_the_bound():
    from segmo.data.checks import MAX_ABS_Z, value_problem

    folder = SHARED / "fixtures" / "humanml3d"
    features = np.load(folder / "012314_features.npy")
    mean, std = np.load(folder / "Mean.npy"), np.load(folder / "Std.npy")
    z = np.abs((features - mean) / std).max()
    assert 20 < z < MAX_ABS_Z / 40  # measured 24.3
    assert value_problem(features, mean, std, MAX_ABS_Z) is None


def test_wrong_width_raises_naming_file(tmp_path):
    write_dataset(tmp_path, {"a": 60, "b": 60})
    np.save(tmp_path / "new_joint_vecs" / "b.npy", np.zeros((60, 251), np.float32))
    for preload in (True, False):
        with pytest.raises(ValueError, match=r"b\.npy.*\(60, 251\)"):
            MotionDataset(tmp_path, preload=preload)
    np.save(tmp_path / "Std.npy", np.ones(10, np.float32))
    with pytest.raises(ValueError, match=r"Std\.npy"):
        load_stats(tmp_path)


def test_lazy_loading_matches_preload(tmp_path):
    write_dataset(tmp_path, {"a": 60, "b": 97, "c": 44})
    eager, lazy = MotionDataset(tmp_path), MotionDataset(tmp_path, preload=False)
    assert len(eager) == len(lazy) == 6 and not lazy.motions.arrays
    for i in range(len(eager)):
        assert torch.equal(eager[i]["motion"], lazy[i]["motion"])
    lazy = MotionDataset(tmp_path, preload=False)
    arr = np.zeros((60, D), np.float32)
    arr[0, 0] = np.nan
    np.save(tmp_path / "new_joint_vecs" / "a.npy", arr)  # changed after the check
    with pytest.raises(SegmoError, match=r"a\.npy: changed while training: frame 0 dim 0 is nan"):
        lazy[0]


# --------------------------------------------------------------------------- text side


def test_text_segments_and_errors(tmp_path):
    write_dataset(tmp_path, {"a": 60, "b": 60, "c": 60})
    seg = tmp_path / "text_segments" / "rule"
    seg.mkdir(parents=True)
    (seg / "a.txt").write_text("walks#waves\nonly one\n")
    (seg / "b.txt").write_text("x\ny\n")
    with pytest.warns(UserWarning, match=r"c\.txt: text-segment file not found"):
        ds = MotionDataset(tmp_path, text_segments="rule")
    assert [s["segments"] for s in ds] == [["walks", "waves"], ["only one"], ["x"], ["y"]]
    assert ds.summary["missing_segments"] == 1
    with pytest.raises(FileNotFoundError, match="text_segments/other"):
        MotionDataset(tmp_path, text_segments="other")
    (seg / "b.txt").write_text("x\n")
    with pytest.raises(ValueError, match=r"rule/b\.txt has 1 lines but .*texts/b\.txt has 2"):
        MotionDataset(tmp_path, text_segments="rule")
    (seg / "b.txt").write_text("x\n1#2#3#4#5#6\n")
    with pytest.raises(ValueError, match=r"rule/b\.txt:2: 6 text segments"):
        MotionDataset(tmp_path, text_segments="rule")
    (seg / "b.txt").write_text(" # \nx\n")
    with pytest.raises(ValueError, match=r"rule/b\.txt:1: no text segment"):
        MotionDataset(tmp_path, text_segments="rule")
    # A segment without words on a caption's line (made by hand) was reported missing from
    # the text-feature cache, with advice to run encode-texts, which never encodes one.
    (seg / "b.txt").write_text("x\ny#...\n")
    with pytest.raises(SegmoError, match=r"rule/b\.txt:2: text segment '\.\.\.' holds no words"):
        MotionDataset(tmp_path, text_segments="rule")
    # The placeholder line of a caption without words is no segment of anything: the caption
    # line is skipped, as before.
    (tmp_path / "texts" / "b.txt").write_text("a person does b#a/DET#0.0#0.0\n...#.#0.0#0.0\n")
    (seg / "b.txt").write_text("x\n...\n")
    with pytest.warns(UserWarning, match=r"caption without words"):
        ds = MotionDataset(tmp_path, text_segments="rule")
    assert [s["segments"] for s in ds][2:] == [["x"]]


def test_ground_truth_spans_follow_the_crop(tmp_path):
    lines = ["walk then wave#w/X#0#0", "sub clip#s/X#0.5#3.0"]
    write_dataset(tmp_path, {"a": 63}, captions={"a": lines})
    gt = {"id": "a", "fps": 20.0, "num_frames": 63, "captions": [
        {"text": "walk then wave", "segments": [{"text": "walk", "start": 0, "end": 30},
                                                {"text": "wave", "start": 30, "end": 63}]},
        {"text": "sub clip", "segments": [{"text": "sub clip", "start": 0, "end": 63}]}]}
    (tmp_path / "segments").mkdir()
    (tmp_path / "segments" / "a.json").write_text(json.dumps(gt))
    ds = MotionDataset(tmp_path)
    assert ds[0]["spans"] == [(0, 30), (30, 60)] and ds[1]["spans"] is None
    ds = MotionDataset(tmp_path, random_crop=True, seed=0)
    seen = set()
    for epoch in range(20):
        (s0, e0), (s1, e1) = ds[(0, epoch)]["spans"]
        assert s0 == 0 and e0 == s1 and e1 == 60 and 27 <= e0 <= 30
        seen.add(e0)
    assert len(seen) > 1
    gt["captions"].pop()
    (tmp_path / "segments" / "a.json").write_text(json.dumps(gt))
    with pytest.raises(SegmoError, match=r"a\.json has 1 captions"):
        MotionDataset(tmp_path)
    (tmp_path / "segments" / "a.json").write_text('{"captions": [\n  {"segments": [}]}')
    with pytest.raises(SegmoError, match=r"segments/a\.json:2: not valid JSON"):
        MotionDataset(tmp_path)
    (tmp_path / "segments" / "a.json").write_text('{"captions": [{"spans": []}, {}]}')
    with pytest.raises(SegmoError, match=r"a\.json: not a ground-truth file \(captions\[0\]: "
                                         r"expected an object with segments\)"):
        MotionDataset(tmp_path)
    # spans that cannot be frames of the motion: named with their place in the file
    for caption, problem in ((
            [{"text": "x", "segments": [{"start": 0, "end": 30}, {"start": 20, "end": 63}]}],
            r"captions\[0\]\.segments\[1\]: start 20, end 63: expected 30 <= start < end <= "
            r"num_frames 63"), (
            [{"text": "x", "segments": [{"start": 0, "end": 64}]}], r"captions\[0\]\.segments\[0\]: start 0, end 64"), (
            [{"text": "x", "segments": [{"start": 0, "end": 1.5}]}], r"captions\[0\]\.segments\[0\]: start 0, end 1\.5: "
                                                                    r"expected whole frames"), (
            [{"text": "x", "segments": []}], r"captions\[0\]\.segments: expected a non-empty list")):
        (tmp_path / "segments" / "a.json").write_text(json.dumps({**gt, "captions": caption * 2}))
        with pytest.raises(SegmoError, match=r"a\.json: not a ground-truth file \(" + problem):
            MotionDataset(tmp_path)
    (tmp_path / "segments" / "a.json").write_text(json.dumps({**gt, "num_frames": "x"}))
    with pytest.raises(SegmoError, match=r"num_frames 'x': expected a whole number >= 1"):
        MotionDataset(tmp_path)
    (tmp_path / "Std.npy").write_bytes(b"garbage")
    with pytest.raises(SegmoError, match=r"Std\.npy: not a readable \.npy array"):
        MotionDataset(tmp_path)


def test_the_ground_truth_of_another_motion_is_refused_naming_both_files(tmp_path):
    """A segments file of another motion (164 frames beside a 63-frame motion) was read
    without a word: its spans were cut to the motion, [(0, 63), (63, 63)], empty ones too."""
    from segmo.data.actions import ActionFrameDataset

    write_dataset(tmp_path, {"a": 63}, captions={"a": ["walk then wave#w/X#0#0"]})
    gt = {"id": "b", "fps": 20.0, "num_frames": 164,
          "actions": [{"action": "walk", "start": 0, "end": 80},
                      {"action": "wave", "start": 80, "end": 164}],
          "captions": [{"text": "walk then wave", "segments": [
              {"text": "walk", "start": 0, "end": 80}, {"text": "wave", "start": 80, "end": 164}]}]}
    (tmp_path / "segments").mkdir()
    (tmp_path / "segments" / "a.json").write_text(json.dumps(gt))
    named = (r"segments/a\.json: num_frames 164, but \S*new_joint_vecs/a\.npy has 63 frames")
    with pytest.raises(SegmoError, match=named):
        MotionDataset(tmp_path)
    with pytest.raises(SegmoError, match=named):
        ActionFrameDataset(tmp_path, "train", classes=["walk", "wave"])


def test_an_action_that_is_no_name_is_refused_naming_the_file(tmp_path):
    """`"action": null` in a ground-truth file was a TypeError traceback from sorting the
    action names, when the action classifier's fit began."""
    from segmo.data.actions import ActionFrameDataset, action_classes

    write_dataset(tmp_path, {"a": 63}, captions={"a": ["walk then wave#w/X#0#0"]})
    (tmp_path / "segments").mkdir()
    for action, segment_action in ((None, "walk"), (7, "walk"), ("", "walk"), ("walk", None)):
        gt = {"id": "a", "fps": 20.0, "num_frames": 63,
              "actions": [{"action": action, "start": 0, "end": 30},
                          {"action": "wave", "start": 30, "end": 63}],
              "captions": [{"text": "walk then wave", "segments": [
                  {"text": "walk", "action": segment_action, "start": 0, "end": 30},
                  {"text": "wave", "action": "wave", "start": 30, "end": 63}]}]}
        (tmp_path / "segments" / "a.json").write_text(json.dumps(gt))
        where, bad = ("actions[0]", action) if segment_action else \
            ("captions[0].segments[0]", segment_action)
        named = re.escape(f"segments/a.json: not a ground-truth file ({where}: action {bad!r}: "
                          "expected a name")
        with pytest.raises(SegmoError, match=named):
            action_classes(tmp_path, "train")
        with pytest.raises(SegmoError, match=named):
            ActionFrameDataset(tmp_path, "train", classes=["walk", "wave"])


def test_text_cache_features_and_collate(tmp_path):
    write_dataset(tmp_path, {"a": 60, "b": 81})
    seg = tmp_path / "text_segments" / "rule"
    seg.mkdir(parents=True)
    (seg / "a.txt").write_text("walks#waves#sits\nonly one\n")
    (seg / "b.txt").write_text("x#y\ny\n")
    cache = FakeCache()
    # text_cache takes precedence: "missing-encoder" is never opened
    ds = MotionDataset(tmp_path, text_segments="rule", text_features="missing-encoder",
                       text_cache=cache, max_segments=4)
    s = ds[0]
    assert s["sentence"].shape == (8,) and torch.equal(s["sentence"], cache.sentence([s["caption"]])[0])
    assert s["segment_features"].shape == (4, 8) and s["segment_mask"].tolist() == [1, 1, 1, 0]
    assert torch.equal(s["segment_features"][1], cache.sentence(["waves"])[0])
    assert s["segment_features"][3].abs().sum() == 0
    batch = collate([ds[i] for i in range(len(ds))])
    assert batch["motion"].shape == (4, 80, D) and batch["lengths"].tolist() == [60, 60, 80, 80]
    assert batch["mask"].dtype == torch.bool and batch["mask"].sum(1).tolist() == [60, 60, 80, 80]
    assert batch["motion"][0, 60:].abs().sum() == 0
    assert batch["sentence"].shape == (4, 8) and batch["segment_features"].shape == (4, 4, 8)
    assert batch["segment_mask"].sum(1).tolist() == [3, 1, 2, 1]
    assert batch["id"] == ["a", "a", "b", "b"] and batch["segments"][0] == ["walks", "waves", "sits"]
    assert batch["spans"] == [None] * 4 and batch["caption_index"] == [0, 1, 0, 1]


def test_collate_rejects_mixed_samples():
    a = {"motion": torch.zeros(4, 3), "length": 4, "id": "a"}
    b = {"motion": torch.zeros(8, 3), "length": 8, "id": "b", "caption": "x"}
    with pytest.raises(ValueError, match="different keys"):
        collate([a, b])
    with pytest.raises(ValueError, match="empty"):
        collate([])


# --------------------------------------------------------------------------- windows


def test_window_dataset(tmp_path):
    raw = write_dataset(tmp_path, {"a": 70, "b": 50, "c": 130, "d": 230})
    (tmp_path / "train.txt").write_text("a\nb\nc\nd\nmissing\n")
    with pytest.warns(UserWarning, match="missing"):
        ds = MotionWindowDataset(tmp_path, window=64, seed=3)
    assert ds.ids == ["a", "c", "d"] and ds.summary["shorter_than_window"] == 1
    assert all(ds[i]["motion"].shape == (64, D) for i in range(3))
    with pytest.warns(UserWarning, match="missing"):
        one = MotionWindowDataset(tmp_path, window=64, seed=3)
        two = MotionWindowDataset(tmp_path, window=64, seed=3)
    first = [one[(2, epoch)]["motion"] for epoch in range(5)]
    assert all(torch.equal(x, two[(2, e)]["motion"]) for e, x in enumerate(first))  # same seed
    assert len({float(x[0, 0]) for x in first}) > 1  # ... windows that differ between epochs
    (tmp_path / "train.txt").write_text("a\nb\nc\nd\n")
    whole = MotionWindowDataset(tmp_path, window=None, random_crop=False)
    assert whole.ids == ["a", "b", "c"] and whole[2]["length"] == 128  # d: 230 >= max_frames
    assert torch.allclose(whole[0]["motion"], torch.from_numpy((raw["a"][:68] - whole.mean) / whole.std))
    with pytest.raises(ValueError, match="multiple of unit_length"):
        MotionWindowDataset(tmp_path, window=30)


# --------------------------------------------------------------------------- DataModule


def test_datamodule(tmp_path):
    from segmo.data import MotionDataModule

    lengths = {f"{i:03d}": 40 + 7 * i for i in range(12)}
    write_dataset(tmp_path, lengths, splits={"train": list(lengths)[:8], "val": list(lengths)[8:10],
                                              "test": list(lengths)[10:]})
    dm = MotionDataModule(str(tmp_path), batch_size=5, seed=1)
    assert dm.feature_dim == D and dm.skeleton.name == "t2m"
    assert dm.mean.dtype == torch.float32 and dm.mean.shape == (D,)
    assert torch.equal(dm.std, torch.from_numpy(np.load(tmp_path / "Std.npy")))
    dm.setup("fit")
    train = dm.train_dataloader()
    assert train.drop_last and len(train) == 3  # 16 samples, batch 5
    ids1 = [i for b in train for i in b["id"]]
    ids2 = [i for b in MotionDataModule(str(tmp_path), batch_size=5, seed=1).train_dataloader()
            for i in b["id"]]
    assert ids1 == ids2 and len(ids1) == 15 and ids1 != sorted(ids1)
    val = next(iter(dm.val_dataloader()))
    assert val["id"] == ["008", "008", "009", "009"] and val["motion"].shape[0] == 4
    small = MotionDataModule(str(tmp_path), batch_size=64, max_motions=3)
    assert not small.train_dataloader().drop_last and len(small.dataset("train")) == 6
    assert [b["id"] for b in small.predict_dataloader()] == [["010", "010", "011", "011"]]
    win = MotionDataModule(str(tmp_path), batch_size=4, window=48)
    batch = next(iter(win.train_dataloader()))
    assert batch["motion"].shape == (4, 48, D) and "caption" not in batch
    assert win.dataset("val").ids == ["008", "009"]  # whole clips, one per motion
    with pytest.raises(ValueError, match="unknown split"):
        dm.dataset("dev")


def test_unit_length_of_older_configs_is_accepted_only_as_the_token_stride(tmp_path):
    """A token is FRAMES_PER_TOKEN frames, fixed by the tokenizer; configs written when
    `unit_length` was a DataModule option hold `unit_length: 4` and still load."""
    from segmo.data import MotionDataModule
    from segmo.models.tokenizer import FRAMES_PER_TOKEN

    write_dataset(tmp_path, {"a": 70, "b": 90}, splits={"train": ["a", "b"]})
    assert FRAMES_PER_TOKEN == 4
    old = MotionDataModule(str(tmp_path), unit_length=4)
    assert old.dataset("train")[0]["length"] % FRAMES_PER_TOKEN == 0
    with pytest.raises(ValueError, match=r"unit_length=8: a motion token is always 4 frames"):
        MotionDataModule(str(tmp_path), unit_length=8)


def test_datamodule_batches_do_not_depend_on_the_worker_count(tmp_path):
    from segmo.data import MotionDataModule

    lengths = {f"{i:03d}": 150 for i in range(8)}
    write_dataset(tmp_path, lengths)
    same = np.zeros((150, D), np.float32)
    same[:, 0] = np.arange(150)  # identical motions: feature 0 reveals the window offset
    for mid in lengths:
        np.save(tmp_path / "new_joint_vecs" / f"{mid}.npy", same)

    def epochs(workers):
        dm = MotionDataModule(str(tmp_path), batch_size=4, window=32, num_workers=workers, seed=5)
        loader = dm.train_dataloader()
        out = []
        for epoch in range(2):
            loader.sampler.set_epoch(epoch)  # as Lightning does at each epoch start
            out.append([(b["id"], b["motion"][:, 0, 0].tolist()) for b in loader])
        return out

    a = epochs(0)
    assert a == epochs(2)  # the same ids and windows with 0 or 2 workers
    assert a[0] != a[1]  # another order and other windows in the next epoch
    assert len({o for _, offsets in a[0] for o in offsets}) > 2


def test_train_loader_resumes_mid_epoch(tmp_path):
    from segmo.data import MotionDataModule

    write_dataset(tmp_path, {f"{i:03d}": 60 + i for i in range(10)})
    dm = MotionDataModule(str(tmp_path), batch_size=3, seed=2)

    def run(stop=None, state=None):
        loader, seen = dm.train_dataloader(), []
        if state is not None:
            loader.load_state_dict(state)
        for epoch in range(state["epoch"] if state else 0, 3):
            loader.sampler.set_epoch(epoch)
            for batch in loader:
                seen.append((batch["id"], batch["motion"].sum().item()))
                if len(seen) == stop:
                    return seen, loader.state_dict()
        return seen, None

    whole, _ = run()
    assert len(whole) == 3 * 6  # 20 samples, batches of 3, the last incomplete one dropped
    plain = dm.train_dataloader()  # without set_epoch, each full pass is the next epoch
    assert [[b["id"] for b in plain] for _ in range(3)] == [[i for i, _ in whole[k:k + 6]]
                                                           for k in (0, 6, 12)]
    head, state = run(stop=8)
    assert state == {"epoch": 1, "batches": 2}
    tail, _ = run(state=state)
    assert head + tail == whole


def test_sampler_shares_an_epoch_between_ranks(tmp_path):
    from segmo.data.sampling import EpochSampler

    data = list(range(11))
    ranks = [EpochSampler(data, seed=3, num_replicas=2, rank=r) for r in (0, 1)]
    for sampler in ranks:
        sampler.set_epoch(4)
    keys = [list(s) for s in ranks]
    assert len(keys[0]) == len(keys[1]) == 6 and all(e == 4 for k in keys for _, e in k)
    indices = [i for k in keys for i, _ in k]
    assert set(indices) == set(data)  # one index repeated to even out the shares
    single = EpochSampler(data, seed=3, num_replicas=1, rank=0)
    single.set_epoch(4)
    order = [i for i, _ in single]
    order.append(order[0])  # the padding
    assert [i for i, _ in keys[0]] == order[0::2] and [i for i, _ in keys[1]] == order[1::2]


def test_missing_text_features_are_reported_at_setup(tmp_path):
    from segmo.data import MotionDataModule

    write_dataset(tmp_path, {"a": 60, "b": 60})
    seg = tmp_path / "text_segments" / "rule"
    seg.mkdir(parents=True)
    for mid in ("a", "b"):
        (seg / f"{mid}.txt").write_text("walks#waves\nonly one\n")

    class Partial(FakeCache):
        folder = tmp_path / "text_features" / "fake"

        def __contains__(self, text):  # a caption and a segment are missing
            return text not in ("waves", "a person does b")

    dm = MotionDataModule(str(tmp_path), text_segments="rule", text_features="fake")
    dm.text_cache = Partial()  # (a cached_property: the instance attribute wins)
    with pytest.raises(SegmoError) as error:
        dm.setup("fit")
    assert str(error.value) == (
        f"{tmp_path}/text_features/fake: 2 of 7 texts of the train split are not in the "
        "text-feature cache (first: 'a person does b'); update it with "
        f"`segmo encode-texts --data {tmp_path} --encoder fake --segments rule`")


@pytest.mark.slow
def test_builtin_corpus_through_datamodule(tmp_path):
    synth = pytest.importorskip("segmo.synth", reason="segmo.synth (built-in corpus) not available yet")
    if not hasattr(synth, "build_corpus"):
        pytest.skip("segmo.synth.build_corpus not available yet")
    from segmo.data import MotionDataModule

    root = synth.build_corpus(tmp_path / "corpus", num_motions=20, seed=0, progress=False)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the built-in corpus must load without any skip
        dm = MotionDataModule(str(root), batch_size=4)
        dm.setup("fit")
    ds = dm.dataset("train")
    assert len(ds) > 0 and ds.summary["motions"] > 0
    batch = next(iter(dm.train_dataloader()))
    assert batch["motion"].shape[-1] == D and not math.isnan(float(batch["motion"].sum()))
    assert all(s is not None for s in batch["spans"])


def test_real_text_feature_cache(tmp_path):
    """The dataset opens segmo.text.cache by encoder name (built here with a tiny fake encoder)."""
    cache_mod = pytest.importorskip("segmo.text.cache", reason="segmo.text.cache not available")
    from segmo.text.encoders import TextEncoder, TextEncoding

    class TinyEncoder(TextEncoder):
        def __init__(self):
            super().__init__("tiny", torch.nn.Identity(), None, FakeCache.dim, 16, "none")

        def encode(self, texts, batch_size=64):
            fake = FakeCache()
            toks = [fake.tokens(t) for t in texts]
            tokens = torch.zeros(len(texts), max(len(x) for x in toks), fake.dim)
            mask = torch.zeros(tokens.shape[:2], dtype=torch.bool)
            for i, x in enumerate(toks):
                tokens[i, : len(x)], mask[i, : len(x)] = x, True
            return TextEncoding(fake.sentence(list(texts)), tokens, mask)

    write_dataset(tmp_path, {"a": 60, "b": 64})
    seg = tmp_path / "text_segments" / "rule"
    seg.mkdir(parents=True)
    (seg / "a.txt").write_text("walks#waves\nonly one\n")
    (seg / "b.txt").write_text("x#y\ny\n")
    cache_mod.update_cache(tmp_path, TinyEncoder(), progress=False)
    ds = MotionDataset(tmp_path, text_segments="rule", text_features="tiny")
    batch = collate([ds[i] for i in range(len(ds))])
    expected = FakeCache().sentence(batch["caption"])
    assert torch.allclose(batch["sentence"], expected, atol=1e-2)  # stored as float16
    assert batch["segment_mask"].sum(1).tolist() == [2, 1, 2, 1]


def test_group_by_length_keeps_every_index_and_groups_lengths():
    from segmo.data.sampling import group_by_length

    rng = np.random.default_rng(0)
    lengths = rng.integers(10, 200, size=1003)
    order = rng.permutation(1003)
    out = group_by_length(order, lengths, 32, np.random.default_rng(1))
    assert sorted(out.tolist()) == list(range(1003))
    full = out[: len(out) // 32 * 32].reshape(-1, 32)
    spread = (lengths[full].max(1) - lengths[full].min(1)).mean()
    shuffled = order[: len(order) // 32 * 32].reshape(-1, 32)
    assert spread < 0.2 * (lengths[shuffled].max(1) - lengths[shuffled].min(1)).mean()
    assert len(out) - len(full.reshape(-1)) == 1003 % 32  # the short block is last


def _former_group_by_length(order, lengths, block, rng):
    """`group_by_length` as the published runs drew it (the short block: the shortest clips)."""
    pool = block * 50
    ranked = np.concatenate([chunk[np.argsort(-lengths[chunk], kind="stable")]
                             for chunk in np.split(order, range(pool, len(order), pool))])
    blocks = np.split(ranked, range(block, len(ranked), block))
    full = [b for b in blocks if len(b) == block]
    short = [b for b in blocks if len(b) < block]
    return np.concatenate([full[i] for i in rng.permutation(len(full))] + short)


@pytest.mark.parametrize("n,block", [(2400, 32), (4800, 64), (320, 16), (6400, 64)])
def test_group_by_length_order_of_whole_batches_is_unchanged(n, block):
    """With n a multiple of the batch the order is the one the published runs trained on."""
    from segmo.data.sampling import group_by_length

    lengths = np.random.default_rng(n).integers(40, 197, size=n)  # ties included
    for epoch in range(3):
        draws = [np.random.default_rng((7, epoch)) for _ in range(2)]
        orders = [rng.permutation(n) for rng in draws]
        assert np.array_equal(group_by_length(orders[0], lengths, block, draws[0]),
                              _former_group_by_length(orders[1], lengths, block, draws[1]))


def test_group_by_length_drops_random_clips_not_the_shortest():
    """drop_last drops the n % batch clips that go last; they were the shortest of the last
    pool every epoch, so the shortest clips were missed in about a third of the epochs."""
    from segmo.data.sampling import EpochSampler

    class Toy(torch.utils.data.Dataset):
        def __len__(self):
            return 203

    lengths = np.arange(40, 243)  # all distinct: the shortest are indices 0..
    for world in (1, 2):
        ranks = [EpochSampler(Toy(), seed=1, lengths=lengths, batch_size=8, num_replicas=world, rank=r)
                 for r in range(world)]
        left_out = []
        for epoch in range(60):
            kept = set()
            for sampler in ranks:
                sampler.set_epoch(epoch)
                order = sampler.order()
                kept |= set(order[: len(order) // 8 * 8].tolist())  # drop_last
                # every rank's batch k is one block's share: lengths stay grouped
                batches = order[: len(order) // 8 * 8].reshape(-1, 8)
                assert (lengths[batches].max(1) - lengths[batches].min(1)).max() < 60
            dropped = sorted(set(range(203)) - kept)
            assert len(dropped) == 203 % (8 * world)
            left_out += dropped
        assert len(set(left_out)) > 60  # not the same few clips every epoch
        assert abs(lengths[left_out].mean() - lengths.mean()) < 20  # nor the shortest ones


def test_group_by_length_sampler_is_a_function_of_seed_and_epoch(tmp_path):
    from segmo.data.sampling import EpochSampler

    class Toy(torch.utils.data.Dataset):
        def __len__(self):
            return 300

    lengths = np.random.default_rng(0).integers(40, 197, size=300)
    a = EpochSampler(Toy(), seed=3, lengths=lengths, batch_size=16, num_replicas=1, rank=0)
    b = EpochSampler(Toy(), seed=3, lengths=lengths, batch_size=16, num_replicas=1, rank=0)
    a.set_epoch(2), b.set_epoch(2)
    assert list(a) == list(b)
    b.set_epoch(3)
    assert list(a) != list(b)
    # Two ranks: each rank's batch is one block's share, so it still holds similar lengths.
    ranks = [EpochSampler(Toy(), seed=3, lengths=lengths, batch_size=16, num_replicas=2, rank=r)
             for r in (0, 1)]
    orders = [r.order() for r in ranks]
    assert sorted(np.concatenate(orders).tolist()) == list(range(300))
    first = lengths[orders[0][:16]]
    assert first.max() - first.min() < 40
    with pytest.raises(ValueError, match="needs batch_size"):
        EpochSampler(Toy(), lengths=lengths, num_replicas=1, rank=0)


def test_datamodule_groups_batches_by_length_and_still_resumes(tmp_path):
    from segmo.data import MotionDataModule
    from segmo.errors import SegmoError

    lengths = {f"{i:03d}": 40 + 13 * (i % 12) for i in range(60)}
    write_dataset(tmp_path, lengths)
    plain = MotionDataModule(str(tmp_path), batch_size=8, seed=4)
    grouped = MotionDataModule(str(tmp_path), batch_size=8, seed=4, group_by_length=True)

    def padded(dm):
        return sum(b["motion"].shape[0] * b["motion"].shape[1] for b in dm.train_dataloader())

    assert padded(grouped) < 0.8 * padded(plain)
    ids = sorted(i for b in grouped.train_dataloader() for i in b["id"])
    assert len(ids) == 120 // 8 * 8  # every sample once but the dropped short batch
    loader = grouped.train_dataloader()
    loader.sampler.set_epoch(1)
    whole = [b["id"] for b in loader]
    loader = grouped.train_dataloader()
    loader.load_state_dict({"epoch": 1, "batches": 5})
    assert [b["id"] for b in loader] == whole[5:]
    windows = MotionDataModule(str(tmp_path), batch_size=4, window=32, group_by_length=True)
    with pytest.raises(SegmoError, match="group_by_length: the MotionWindowDataset"):
        windows.train_dataloader()


def test_action_attributes_and_the_modifiers_a_text_names():
    from segmo.data.attributes import ATTRIBUTES, attribute_labels, named_attributes
    from segmo.data.collate import IGNORE

    assert attribute_labels("kick", {"side": "left", "height": 0.6}) == (0, IGNORE, IGNORE)
    assert attribute_labels("wave", {"hand": "both", "count": 3}) == (2, 2, IGNORE)
    assert attribute_labels("hop", {"foot": "right", "count": 2}) == (1, 1, IGNORE)
    assert attribute_labels("turn", {"direction": "left", "angle": 90}) == (0, IGNORE, IGNORE)
    assert attribute_labels("walk_forward", {"speed": 0.9}) == (IGNORE, IGNORE, 0)
    assert attribute_labels("run", {"speed": 3.9, "steps": 8}) == (IGNORE, IGNORE, 2)  # steps is no count
    assert attribute_labels("walk_backward", {"speed": 1.0}) == (IGNORE, IGNORE, 1)
    assert named_attributes("a man kicks with his left foot twice") == ["side", "count"]
    assert named_attributes("she walks forward slowly") == ["speed"]
    assert named_attributes("a person walks in a circle counterclockwise") == ["side"]
    assert named_attributes("he jumps three times") == ["count"]
    assert named_attributes("someone leftovers fastener") == []  # whole words only
    assert list(ATTRIBUTES) == ["side", "count", "speed"]


@pytest.mark.parametrize("content", ["5", "[" * 100_000, '{"version": 1'])
def test_a_broken_corpus_json_leaves_the_model_card_without_it(tmp_path, content):
    """`segmo export` reads the corpus' version for the model card: a corpus.json of `5`
    was a TypeError, and one nested 100,000 deep a RecursionError, after training."""
    from segmo.export import training_data

    (tmp_path / "corpus.json").write_text(content)
    card = training_data({"root": str(tmp_path), "text_segments": "rule"})
    assert "corpus" not in card and card["text_segments"] == "rule"


def test_the_model_card_reads_the_corpus_where_the_fit_found_it(tmp_path):
    """The checkpoint's resolved data folder wins over a relative `root`; a value of another
    type in a hand-made checkpoint falls back to `root` (it was a TypeError)."""
    from segmo.export import training_data

    fit = tmp_path / "fit" / "data"
    fit.mkdir(parents=True)
    (fit / "corpus.json").write_text('{"name": "synthetic", "version": 3}')
    card = training_data({"root": "data"}, str(fit))
    assert card == {"root": "data", "corpus": {"name": "synthetic", "version": 3}}
    assert "corpus" not in training_data({"root": str(tmp_path / "nope")}, 5)
    assert training_data({"root": str(fit)}, 5)["corpus"]["version"] == 3


@pytest.mark.parametrize("content, expected", [
    (None, "motion file not found"),
    ("npz", "an .npz archive"),
    ("text", "not a .npy file"),
    (np.zeros((0, 263), np.float32), "shape (0, 263), expected (frames, features)"),
    (np.full((8, 263), np.nan, np.float32), "holds NaN or inf"),
    (np.array(["a"] * 4), "holds <U1 values, not real numbers"),
])
def test_read_motion_names_the_file_it_cannot_use(tmp_path, content, expected):
    """Grounding and action-order evaluation read motions with a bare np.load: an .npz
    named .npy and a motion of 0 frames were skipped without a word (R@1 0.667 against
    0.333), a text file or a pickle was a traceback."""
    from segmo.data.layout import read_motion

    (tmp_path / "new_joint_vecs").mkdir()
    path = tmp_path / "new_joint_vecs" / "a.npy"
    if isinstance(content, np.ndarray):
        np.save(path, content)
    elif content == "npz":
        with open(path, "wb") as handle:
            np.savez(handle, x=np.zeros((8, 263)))
    elif content == "text":
        path.write_text("a person walks\n")
    with pytest.raises(SegmoError) as caught:
        read_motion(tmp_path, "a")
    assert str(caught.value).startswith(str(path)) and expected in str(caught.value)


def test_read_npy_of_a_file_it_cannot_open_is_one_segmo_error(tmp_path):
    """Reading the header first let the OSError of a folder (or a file this user may not
    read) out of `read_npy`, whose callers expect SegmoError naming the file."""
    from segmo.files import read_npy

    with pytest.raises(SegmoError, match=r"not a readable \.npy array \(Is a directory\)"):
        read_npy(tmp_path)
