"""The motion-token cache (`segmo.data.motion_tokens`): cached tokens are the tokenizer's
encoding of the very crop a sample draws, the cache is keyed by the tokenizer, a killed
build is never trusted, and the mask stage trains on it."""

from __future__ import annotations

import errno
import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import REPO, build_text_dataset

from segmo.data import collate
from segmo.data import motion_tokens as mt
from segmo.data.humanml3d import MotionDataset
from segmo.errors import SegmoError
from segmo.models.tokenizer import RVQVAE
from segmo.training.cli import main as cli_main


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    return build_text_dataset(tmp_path_factory.mktemp("tokens") / "data", motions=10,
                              encoders={"minilm": 384})


def train_set(root: Path) -> MotionDataset:
    return MotionDataset(root, "train", random_crop=True, text_features="minilm", seed=3)


def attach(ds: MotionDataset, tokenizer: RVQVAE, path) -> mt.TokenCacheSummary:
    summary = mt.update_motion_tokens(ds.root, tokenizer, str(path), [ds], progress=False)
    ds.motion_tokens = mt.MotionTokenCache(summary.folder)
    return summary


def test_cached_tokens_are_the_encoding_of_the_drawn_crop(data, tokenizer_dir):
    tokenizer = RVQVAE.from_pretrained(tokenizer_dir["t2m"]).eval()
    ds = train_set(data)
    summary = attach(ds, tokenizer, tokenizer_dir["t2m"])
    crops = {(ds.clip_keys()[i], o) for i in range(len(ds)) for o in ds.crop_offsets(i)}
    assert summary.new == summary.total == len(crops)  # two captions of a clip share its crops
    offsets = set()
    for epoch in range(3):
        for i in range(len(ds)):
            sample = ds[(i, epoch)]
            raw = ds.clip(i)
            t = sample["length"]
            off = next(o for o in ds.crop_offsets(i)
                       if np.array_equal((raw[o:o + t] - ds.mean) / ds.std, sample["motion"].numpy()))
            offsets.add(off)
            expected = tokenizer.encode(sample["motion"][None])[0]
            assert sample["tokens"].shape == (t // 4, tokenizer.num_quantizers)
            assert torch.equal(sample["tokens"], expected), (i, epoch, off)
    assert len(offsets) > 1  # several frame phases were drawn, each from its own encoding
    batch = collate([ds[0], ds[1], ds[2]])
    assert batch["tokens"].shape == (3, batch["motion"].shape[1] // 4, tokenizer.num_quantizers)


def test_the_cache_is_keyed_by_the_tokenizer_and_reused(data, tokenizer_dir, tmp_path):
    path = tokenizer_dir["t2m"]
    tokenizer = RVQVAE.from_pretrained(path)
    ds = train_set(data)
    first = attach(ds, tokenizer, path)
    again = attach(ds, RVQVAE.from_pretrained(shutil.copytree(path, tmp_path / "copy")), path)
    assert again.folder == first.folder and again.new == 0  # same weights elsewhere: reused
    other = RVQVAE.from_pretrained(path)
    with torch.no_grad():
        other.encoder.layers[0].weight.mul_(1.5)
    other.save_pretrained(tmp_path / "retrained")
    changed = attach(ds, RVQVAE.from_pretrained(tmp_path / "retrained"), tmp_path / "retrained")
    assert changed.folder != first.folder and changed.new == changed.total > 0
    assert json.loads((changed.folder / "meta.json").read_text())["tokenizer"].endswith("retrained")


@pytest.mark.parametrize("damage, expected", [
    (lambda t, o: (t[: len(t) // 2], o), "offsets from 0 to"),  # a cut tokens file: crops of no tokens
    (lambda t, o: (t + 30000, o), "outside the tokenizer's"),  # codes with no embedding
    (lambda t, o: (t - t.max() - 1, o), "outside the tokenizer's"),
    (lambda t, o: (t[:, 0], o), "tokens of shape"),
    (lambda t, o: (t, o[::-1].copy()), "offsets from"),
    (lambda t, o: (t, o[:-1]), "offsets of shape"),
])
def test_a_damaged_shard_is_refused_naming_it(data, tokenizer_dir, tmp_path, damage, expected):
    """Such a shard used to train silently: 46 of 117 crops came back empty (padded with
    code 0) from a tokens file cut in half, and codes out of range failed at the first
    batch with an IndexError."""
    root = tmp_path / "data"
    shutil.copytree(data, root, ignore=shutil.ignore_patterns("motion_tokens"))  # to build
    ds = train_set(root)
    folder = attach(ds, RVQVAE.from_pretrained(tokenizer_dir["t2m"]), tokenizer_dir["t2m"]).folder
    tokens_file, offsets_file = folder / "shard-00000.tokens.npy", folder / "shard-00000.offsets.npy"
    tokens, offsets = damage(np.load(tokens_file).astype(np.int16), np.load(offsets_file))
    np.save(tokens_file, tokens.astype(np.int16))
    np.save(offsets_file, offsets)
    with pytest.raises(SegmoError) as caught:
        mt.MotionTokenCache(folder)
    message = str(caught.value)
    assert expected in message and "shard-00000" in message and f"delete {folder}" in message
    assert "\n" not in message


def _huge_header(path):
    """A .npy of a few bytes whose header claims 1e11 int64s (np.load asked for 745 GiB)."""
    with open(path, "wb") as f:
        np.lib.format.write_array_header_1_0(f, {"descr": "<i8", "fortran_order": False,
                                                 "shape": (10**11,)})


@pytest.mark.parametrize("edit, expected", [
    (lambda meta, index, folder: meta.update(codebook_size="256"), "not this folder's motion-token metadata"),
    (lambda meta, index, folder: meta.update(key="0" * 16), "key"),
    (lambda meta, index, folder: index["shards"][0].update(name="../../elsewhere"),
     "shard '../../elsewhere' is not an entry of segmo's"),
    (lambda meta, index, folder: index["shards"][0].update(items=[[1]]), "is not an entry of segmo's"),
    (lambda meta, index, folder: _huge_header(folder / "shard-00000.offsets.npy"),
     "shard-00000.offsets.npy: unreadable shard"),
])
def test_damaged_metadata_and_index_are_refused(data, tokenizer_dir, tmp_path, edit, expected):
    """A codebook_size of "256" turned the code-range check off (an IndexError in fit), a
    folder of another key was trusted, a shard name outside the folder was read there, and
    items given as lists were a TypeError."""
    root = tmp_path / "data"
    shutil.copytree(data, root, ignore=shutil.ignore_patterns("motion_tokens"))  # to build
    folder = attach(train_set(root), RVQVAE.from_pretrained(tokenizer_dir["t2m"]),
                    tokenizer_dir["t2m"]).folder
    meta = json.loads((folder / "meta.json").read_text())
    index = json.loads((folder / "index.json").read_text())
    edit(meta, index, folder)
    (folder / "meta.json").write_text(json.dumps(meta))
    (folder / "index.json").write_text(json.dumps(index))
    with pytest.raises(SegmoError) as caught:
        mt.MotionTokenCache(folder)
    assert expected in str(caught.value) and f"delete {folder}" in str(caught.value)


def test_a_killed_build_is_not_trusted_and_resumes(data, tokenizer_dir, tmp_path, monkeypatch):
    root = tmp_path / "data"
    shutil.copytree(data, root, ignore=shutil.ignore_patterns("motion_tokens"))  # to build
    shutil.rmtree(root / mt.FOLDER, ignore_errors=True)
    tokenizer = RVQVAE.from_pretrained(tokenizer_dir["t2m"])
    ds = train_set(root)
    monkeypatch.setattr(mt, "SHARD_ITEMS", 1)  # one shard per encoded batch
    monkeypatch.setattr(mt, "BATCH", 2)
    encode, calls = tokenizer.encode, []

    def killed(motion):
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt  # a kill between two shards
        return encode(motion)

    monkeypatch.setattr(tokenizer, "encode", killed)
    with pytest.raises(KeyboardInterrupt):
        mt.update_motion_tokens(root, tokenizer, "tok", [ds], progress=False)
    folder = mt.cache_folder(root, mt.cache_key(tokenizer, ds.mean, ds.std))
    (folder / ".shard-00002.tokens.npy.999.0.tmp").write_bytes(b"\x93NUMPY half")  # a cut write
    published = mt.MotionTokenCache(folder)
    assert 0 < len(published) < len({(k, o) for i, k in enumerate(ds.clip_keys())
                                      for o in ds.crop_offsets(i)})
    monkeypatch.setattr(tokenizer, "encode", encode)
    resumed = mt.update_motion_tokens(root, tokenizer, "tok", [ds], progress=False)
    assert resumed.new == resumed.total - len(published)
    assert not list(folder.glob(".*.tmp"))
    ds.motion_tokens = mt.MotionTokenCache(folder)
    for i in range(len(ds)):
        sample = ds[i]
        assert torch.equal(sample["tokens"], encode(sample["motion"][None])[0])


@pytest.mark.parametrize("mode", ["cached", "on_the_fly"])
def test_a_mask_fit_trains_on_the_cache(mode, data, tokenizer_dir, tmp_path):
    cli = cli_main(["fit", "--config", str(REPO / "configs/mask/synthetic.yaml"),
                    f"--data.root={data}", f"--runs_dir={tmp_path / 'runs'}",
                    f"--model.init_args.tokenizer={tokenizer_dir['t2m']}",
                    f"--model.init_args.motion_tokens={mode}",
                    "--model.init_args.dim=32", "--model.init_args.depth=1",
                    "--model.init_args.heads=2", "--model.init_args.ff_dim=32",
                    "--model.init_args.alignment_dim=16", "--data.init_args.batch_size=2",
                    "--trainer.max_steps=3", "--trainer.limit_val_batches=1",
                    "--trainer.enable_progress_bar=false", "--trainer.enable_model_summary=false",
                    "--trainer.accelerator=cpu", "--trainer.devices=1"])
    assert cli.trainer.global_step == 3
    train = cli.datamodule.dataset("train")
    assert (train.motion_tokens is not None) == (mode == "cached")
    if mode == "cached":
        assert "tokens" in next(iter(cli.datamodule.train_dataloader()))
        assert cli.datamodule.dataset("val").motion_tokens is train.motion_tokens


def _hold_lock(root: Path, command: str, seconds: float):
    import subprocess
    import sys

    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys, time; from segmo.files import FolderLock; "
         "FolderLock(sys.argv[1], sys.argv[2]).acquire(); print('HELD', flush=True); "
         "time.sleep(float(sys.argv[3]))", str(root), command, str(seconds)],
        stdout=subprocess.PIPE, text=True, cwd=REPO)
    assert holder.stdout.readline().strip() == "HELD"
    return holder


def test_fits_share_the_cache_and_wait_for_a_peer_build(data, tokenizer_dir, tmp_path):
    from segmo.errors import FolderBusyError

    root = Path(shutil.copytree(data, tmp_path / "data"))
    shutil.rmtree(root / "motion_tokens", ignore_errors=True)  # built by the tests above
    path = tokenizer_dir["t2m"]
    tokenizer = RVQVAE.from_pretrained(path)
    ds = train_set(root)
    # Another kind of writer holds the folder: refused at once.
    other = _hold_lock(root, "segmo encode-texts", 60)
    try:
        with pytest.raises(FolderBusyError, match="segmo encode-texts"):
            attach(ds, tokenizer, path)
    finally:
        other.kill()
        other.wait()
    # A peer fit building the same cache: waited for (here it holds the lock 2 s).
    peer = _hold_lock(root, "segmo fit (motion tokens)", 2)
    try:
        built = attach(ds, tokenizer, path)
    finally:
        peer.wait()
    assert built.new == built.total > 0
    # Complete: read without the lock, even while another writer holds the folder.
    other = _hold_lock(root, "segmo encode-texts", 60)
    try:
        assert attach(ds, tokenizer, path).new == 0
    finally:
        other.kill()
        other.wait()


@pytest.mark.parametrize("code", [errno.EACCES, errno.EROFS])
def test_a_read_only_data_folder_says_what_to_do(data, tokenizer_dir, monkeypatch, tmp_path, code):
    """A shared, read-only copy of a dataset failed on the lock file with the OS's words
    only ("Permission denied"), without saying that the cache is written there, or how to
    train without it."""
    root = tmp_path / "data"
    shutil.copytree(data, root, ignore=shutil.ignore_patterns("motion_tokens"))  # to build

    def refused(self):
        raise OSError(code, os.strerror(code), str(self.path))
    monkeypatch.setattr(mt.FolderLock, "acquire", refused)
    tokenizer = RVQVAE.from_pretrained(tokenizer_dir["t2m"]).eval()
    with pytest.raises(SegmoError, match=r"\.segmo-writer\.lock: .*: the motion-token cache is "
                                         r"written into the data folder; .*motion_tokens=on_the_fly"):
        mt.update_motion_tokens(root, tokenizer, "tok", [train_set(root)], progress=False)
