"""The motion-token cache at ``ROOT/motion_tokens/<key>/``: every training clip encoded once
by the frozen tokenizer, so the mask and residual stages do not run its encoder each step.

What is cached, and why it is exact: a `MotionDataset` sample is a clip (a whole motion or
a time-tagged sub-clip, ``frames [start, end)`` of the file) cropped to whole tokens, at an
offset of 0 .. ``len % 4`` frames (random in training: `MotionDataset.crop_offsets`). There
are no crops at whole-token offsets, so instead of slicing the tokens of a longer encoding
(whose tokens near the crop's edges would differ: the encoder is convolutional, its
receptive field spans dozens of frames), the cache holds the encoding of *every crop the
data path can draw*: each clip at each of its offsets, encoded on its own. A sample's
cached tokens are then ``tokenizer.encode`` of exactly the frames the on-the-fly path
feeds it, and a random draw (`sample_rng(seed, epoch, index)`) picks the same crop in both
paths. What differs is batching: on the fly, a batch is zero-padded to its longest motion,
and the encoder's later layers see those padded frames, so the last tokens of the shorter
motions depend on the batch they happen to be in (tools/bench_train.py measures how many;
docs/design.md has the figure). The cache gives every crop the tokens of the crop alone.

Keys: the folder is named by `cache_key`, a hash of the tokenizer's config and weights and
of the dataset's Mean/Std (the encoder reads z-scored features), so another tokenizer, or
retrained weights, get a new folder and never reuse tokens; a clip is keyed by a hash of
its raw frames (`clip_key`), so a changed motion file is re-encoded, not trusted.

Layout (arrays ``.npy``; tokens memory-mapped on read)::

    meta.json                 format, key, tokenizer (path, codebook_size, num_quantizers), stats hash
    index.json                {"format": 1, "shards": [{"name", "items"}]}
    shard-00000.tokens.npy    (L, q) int16, all items' tokens one after another
    shard-00000.offsets.npy   (k + 1,) int64, item j's tokens are rows offsets[j]:offsets[j+1]

An item is ``"<clip key>:<offset>"``. Updates are incremental and crash-safe as the
text-feature cache's (`segmo.text.cache`): only missing items are encoded, each shard's
files are written atomically and only then published in ``index.json`` (atomically
replaced), under the dataset folder's `FolderLock`; files of a killed build that never
reached the index are ignored, then cleared by the next build.
"""

from __future__ import annotations

import errno
import hashlib
import json
import re
import time
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm.auto import tqdm

from segmo.errors import SegmoError
from segmo.files import FolderLock, atomic_open, remove_temporaries, write_atomic

FORMAT = 1
INDEX, META = "index.json", "meta.json"
FOLDER = "motion_tokens"
BATCH = 64  # crops of one length encoded together
SHARD_ITEMS = 8192


def cache_key(tokenizer: torch.nn.Module, mean: np.ndarray, std: np.ndarray) -> str:
    """16 hex digits naming the tokenizer (config and every weight and buffer) and the
    statistics the data are z-scored with."""
    h = hashlib.sha256(json.dumps(vars(tokenizer.config), sort_keys=True).encode())
    for name, value in sorted(tokenizer.state_dict().items()):
        h.update(name.encode())
        h.update(value.detach().cpu().contiguous().numpy().tobytes())
    h.update(np.asarray(mean, np.float32).tobytes())
    h.update(np.asarray(std, np.float32).tobytes())
    return h.hexdigest()[:16]


def tokenizer_digest(tokenizer: torch.nn.Module) -> str:
    """16 hex digits naming a tokenizer alone (config, weights, its own statistics): the
    cache key of data z-scored as it z-scores them. Exported mask and residual transformers
    record it in meta ("tokenizer_digest"); `segmo bundle` refuses another tokenizer."""
    return cache_key(tokenizer, tokenizer.mean.cpu(), tokenizer.std.cpu())


def clip_key(raw: np.ndarray) -> str:
    """The key of a clip: a hash of its raw (t, d) frames."""
    h = hashlib.blake2b(str(raw.shape).encode(), digest_size=12)
    h.update(np.ascontiguousarray(raw, np.float32).tobytes())
    return h.hexdigest()


def cache_folder(root: str | Path, key: str) -> Path:
    return Path(root) / FOLDER / key


def _read_json(path: Path) -> dict:
    try:
        value = json.loads(path.read_text(encoding="utf-8"))
        if not isinstance(value, dict):
            raise ValueError("not a JSON object")
        return value
    except (OSError, ValueError) as err:
        raise SegmoError(f"{path}: corrupt motion-token cache file ({err}); delete {path.parent} "
                         "and run again (it is rebuilt)") from None


def _read_index(folder: Path) -> dict:
    index = _read_json(folder / INDEX)
    shards = index.get("shards")
    if index.get("format") != FORMAT or not isinstance(shards, list) or not all(
            isinstance(s, dict) and {"name", "items"} <= set(s) for s in shards):
        raise SegmoError(f"{folder / INDEX}: not a format-{FORMAT} motion-token index; delete "
                         f"{folder} and run again (it is rebuilt)")
    return index


def _load(path: Path, mmap_mode: str | None = None) -> np.ndarray:
    try:
        return np.load(path, mmap_mode=mmap_mode)
    except (OSError, ValueError, EOFError) as err:
        raise SegmoError(f"{path}: unreadable shard of the motion-token cache ({err}); delete "
                         f"{path.parent} and run again (it is rebuilt)") from None


def shard_problem(tokens: np.ndarray, offsets: np.ndarray, items: int, meta: dict) -> str | None:
    """What makes a shard unusable (None when nothing): tokens that are not (L, q) whole
    numbers in [0, codebook_size) of the tokenizer meta.json names, or offsets that do not
    cut them into ``items`` spans from row 0 to row L. Read in full (a few MB for a
    corpus): a truncated or overwritten file would otherwise give crops of no tokens, or
    codes the transformer has no embedding for."""
    codes, quantizers = meta.get("codebook_size"), meta.get("num_quantizers")
    if tokens.ndim != 2 or not np.issubdtype(tokens.dtype, np.integer) \
            or (isinstance(quantizers, int) and tokens.shape[1] != quantizers):
        return (f"tokens of shape {tokens.shape} and type {tokens.dtype}, expected (rows, "
                f"{quantizers}) whole numbers")
    if offsets.shape != (items + 1,) or not np.issubdtype(offsets.dtype, np.integer):
        return f"offsets of shape {offsets.shape} for {items} items"
    if offsets[0] != 0 or offsets[-1] != len(tokens) or (np.diff(offsets) < 0).any():
        return (f"offsets from {offsets[0]} to {offsets[-1]} (not rising from 0 to the "
                f"{len(tokens)} rows of tokens)")
    if len(tokens) and isinstance(codes, int):
        low, high = int(tokens.min()), int(tokens.max())
        if low < 0 or high >= codes:
            return f"codes from {low} to {high}, outside the tokenizer's [0, {codes})"
    return None


class MotionTokenCache:
    """Read-only view of a built cache.

    Example::

        cache = MotionTokenCache(cache_folder("data/synth", key))
        cache.tokens(clip_key(raw), offset)   # (n, q) long
    """

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)
        self.meta = _read_json(self.folder / META)
        redo = f"delete {self.folder} and run again (it is rebuilt)"
        sizes = [self.meta.get(k) for k in ("codebook_size", "num_quantizers")]
        if not all(isinstance(v, int) and not isinstance(v, bool) and v >= 1 for v in sizes) \
                or self.meta.get("key", self.folder.name) != self.folder.name:
            # a string turned the code-range check off; a copied folder of another key
            # (another tokenizer or statistics) would be trusted
            raise SegmoError(f"{self.folder / META}: not this folder's motion-token metadata "
                             f"(whole-number codebook_size and num_quantizers, key "
                             f"{self.folder.name!r}); {redo}")
        self._tokens: list[np.ndarray] = []
        self._spans: dict[str, tuple[int, int, int]] = {}  # item -> (shard, start, end)
        for s, shard in enumerate(_read_index(self.folder)["shards"]):
            name, items = shard["name"], shard["items"]
            if not (isinstance(name, str) and re.fullmatch(r"shard-\d{5}", name)
                    and isinstance(items, list) and all(isinstance(i, str) for i in items)):
                raise SegmoError(f"{self.folder / INDEX}: shard {str(name)[:40]!r} is not an "
                                 f"entry of segmo's (name shard-NNNNN, a list of items); {redo}")
            stem = self.folder / name
            tokens = _load(Path(f"{stem}.tokens.npy"), mmap_mode="r")
            offsets = _load(Path(f"{stem}.offsets.npy"), mmap_mode="r")
            problem = shard_problem(tokens, offsets, len(shard["items"]), self.meta)
            if problem:
                raise SegmoError(f"{stem}.*.npy: {problem}: a damaged motion-token cache; delete "
                                 f"{self.folder} and run again (it is rebuilt)")
            self._tokens.append(tokens)
            bounds = offsets.tolist()
            self._spans.update((item, (s, bounds[j], bounds[j + 1]))
                               for j, item in enumerate(shard["items"]))

    def tokens(self, clip: str, offset: int) -> torch.Tensor:
        """(n, q) long tokens of the clip cropped at `offset`; KeyError when not cached."""
        shard, start, end = self._spans[f"{clip}:{offset}"]
        return torch.from_numpy(self._tokens[shard][start:end].astype(np.int64))

    def __contains__(self, item: object) -> bool:
        return item in self._spans

    def __len__(self) -> int:
        return len(self._spans)

    # Memory maps do not pickle; DataLoader workers re-open the folder instead.
    def __getstate__(self) -> dict:
        return {"folder": str(self.folder)}

    def __setstate__(self, state: dict) -> None:
        self.__init__(Path(state["folder"]))

    def __repr__(self) -> str:
        return f"MotionTokenCache({str(self.folder)!r}, items={len(self)})"


@dataclass
class TokenCacheSummary:
    folder: Path
    total: int
    new: int
    seconds: float

    def __str__(self) -> str:
        return (f"{self.folder}: {self.total} crops, {self.new} encoded now, "
                f"{self.total - self.new} reused, {self.seconds:.1f} s")


# How long a fit waits for another fit's build of the same folder's cache (seconds).
LOCK_WAIT = 3600.0


def update_motion_tokens(root: str | Path, tokenizer: Any, tokenizer_path: str,
                         datasets: list[Any], progress: bool = True) -> TokenCacheSummary:
    """Encode every crop of `datasets` (`MotionDataset`s of `root`, one statistics) that the
    cache of `tokenizer` does not hold yet; holds the folder's `FolderLock` while it writes.

    `tokenizer`: the frozen `RVQVAE`; `tokenizer_path` is recorded in meta.json only.
    """
    start = time.perf_counter()
    if tokenizer.codebook_size > np.iinfo(np.int16).max:
        raise SegmoError(f"{tokenizer_path}: {tokenizer.codebook_size} codes do not fit the "
                         "cache's int16 tokens; use model.init_args.motion_tokens=on_the_fly")
    root = Path(root)
    mean, std = datasets[0].mean, datasets[0].std
    key = cache_key(tokenizer, mean, std)
    folder = cache_folder(root, key)
    wanted = {f"{clip}:{offset}": (ds, i, offset) for ds in datasets
              for i, clip in enumerate(ds.clip_keys()) for offset in ds.crop_offsets(i)}
    if (folder / INDEX).is_file():  # published atomically: safe to read without the lock
        have = {item for shard in _read_index(folder)["shards"] for item in shard["items"]}
        if have >= set(wanted):  # nothing to write: several fits may share the cache
            return TokenCacheSummary(folder, len(wanted), 0, time.perf_counter() - start)
    # Two fits started together both find it missing; the second waits for the first's
    # build instead of failing, then encodes only what is still missing.
    try:
        with FolderLock(root, "segmo fit (motion tokens)", wait=LOCK_WAIT):
            folder.mkdir(parents=True, exist_ok=True)
            remove_temporaries(folder)  # from a killed build; never referenced
            if (folder / INDEX).is_file():
                index = _read_index(folder)
            else:
                index = {"format": FORMAT, "shards": []}
                write_atomic(folder / META, json.dumps({
                    "format": FORMAT, "key": key, "tokenizer": str(tokenizer_path),
                    "codebook_size": tokenizer.codebook_size, "num_quantizers": tokenizer.num_quantizers,
                    "stats_sha256": hashlib.sha256(np.asarray(mean, np.float32).tobytes()
                                                   + np.asarray(std, np.float32).tobytes()).hexdigest(),
                }, indent=2) + "\n")
                write_atomic(folder / INDEX, json.dumps(index))
            have = {item for shard in index["shards"] for item in shard["items"]}
            # item -> (dataset, entry index, offset)
            todo: dict[str, tuple[Any, int, int]] = {k: v for k, v in wanted.items() if k not in have}
            if todo:
                _encode(folder, index, tokenizer, todo, key, progress)
    except OSError as error:
        if error.errno not in (errno.EACCES, errno.EPERM, errno.EROFS):
            raise
        # a shared, read-only copy of a dataset (the lock file is its first write)
        raise SegmoError(f"{error.filename or root}: {error.strerror}: the motion-token cache "
                         "is written into the data folder; build it once where the folder is "
                         "writable, or set model.init_args.motion_tokens=on_the_fly") from error
    return TokenCacheSummary(folder, len(wanted), len(todo), time.perf_counter() - start)


def _encode(folder: Path, index: dict, tokenizer: Any, todo: dict, key: str,
            progress: bool) -> None:
    """Encode the `todo` crops in batches of one length; publish a shard every
    `SHARD_ITEMS` items."""
    by_length: dict[int, list[str]] = defaultdict(list)
    for item, (ds, i, _) in todo.items():
        by_length[ds.crop_length(i)].append(item)
    device = next(tokenizer.parameters()).device
    tokenizer.eval()
    bar = tqdm(total=len(todo), desc=f"motion tokens [{key}]", unit="crop", disable=not progress)
    items: list[str] = []
    arrays: list[np.ndarray] = []
    for length in sorted(by_length):
        group = by_length[length]
        for first in range(0, len(group), BATCH):
            chunk = group[first:first + BATCH]
            motion = torch.stack([todo[item][0].crop(*todo[item][1:]) for item in chunk])
            with torch.no_grad():
                codes = tokenizer.encode(motion.to(device)).cpu().numpy().astype(np.int16)
            items += chunk
            arrays += list(codes)
            bar.update(len(chunk))
            if len(items) >= SHARD_ITEMS:
                _append_shard(folder, index, items, arrays)
                items, arrays = [], []
    if items:
        _append_shard(folder, index, items, arrays)
    bar.close()


def _append_shard(folder: Path, index: dict, items: list[str], arrays: list[np.ndarray]) -> None:
    """Write one shard's files, then publish it in index.json (the commit point)."""
    stem = f"shard-{len(index['shards']):05d}"
    lengths = [len(a) for a in arrays]
    offsets = np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64)
    for kind, array in (("tokens", np.concatenate(arrays)), ("offsets", offsets)):
        with atomic_open(folder / f"{stem}.{kind}.npy", "wb") as f:
            np.save(f, array)
    shards = [*index["shards"], {"name": stem, "items": list(items)}]
    write_atomic(folder / INDEX, json.dumps({**index, "shards": shards}))
    index["shards"] = shards
