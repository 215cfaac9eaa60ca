"""Datasets of the HumanML3D / KIT-ML folder layout (spec §2, docs/design.md).

The folder layout is the same for every dataset (its files are read through
`segmo.data.layout`, caption lines through `segmo.text.captions`); what differs (feature
width, fps, length limits) comes from a `SkeletonSpec`. Two datasets are built on the
motion store and load report of this module:

* `MotionDataset` (here): one sample per caption line (time-tagged captions are their
  own sub-clip samples), with text segments, ground-truth spans and cached text features.
* `MotionWindowDataset` (`segmo.data.windows`): one entry per motion, for tokenizer
  training (random windows) and its validation (whole clips).

What is skipped and what raises (``strict=True`` turns every skip into a ``ValueError``):

* skipped with one ``warnings.warn`` per kind and counted in ``dataset.summary``: a motion
  file that is missing, empty (0 bytes or 0 frames) or unreadable; a text file that is
  missing; a text line that is not ``caption#tokens#from#to`` or whose caption has no words
  (``.``); a text-segment file that is missing; a motion without any usable caption;
* counted only (ordinary filtering, spec §2): samples outside ``min_frames <= t < max_frames``
  and, in window mode, motions shorter than the window;
* raised: a missing split / statistics file or text-segment folder (``FileNotFoundError``),
  motions holding NaN/inf or values more than ``max_abs_z`` standard deviations from the
  mean (`segmo.data.checks`: one `SegmoError` for the split, with the count and the first
  files, frame and dim; in lazy mode too, whose construction reads every file once for
  this), a motion of the wrong shape for the skeleton, statistics of the wrong shape or with a
  non-positive std, a text-segment file whose line count differs from its text file or
  that its folder's ``manifest.jsonl`` records as made from other captions (stale), more
  text segments than ``max_segments``, a ground-truth file that does not match its text
  file or is not valid JSON (``ValueError``; `SegmoError` where the user's files are at
  fault). Every message names the file (and line where there is one).

Randomness (crop offsets, windows) is a pure function of ``(seed, epoch, index)``
(`segmo.data.sampling.sample_rng`): the training sampler passes the epoch in its keys
``(index, epoch)``; a plain integer key uses the dataset's ``epoch`` (`set_epoch`, 0 by
default), so repeated reads of one sample in one epoch give the same crop, whatever the
process or DataLoader worker that reads it.
"""

from __future__ import annotations

import logging
import warnings
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset

from segmo.data.checks import MAX_ABS_Z, refuse_values, value_problem
from segmo.data.layout import caption_spans, motion_file, read_split, resolve_stats, split_file
from segmo.data.motion_tokens import MotionTokenCache, clip_key
from segmo.data.sampling import sample_rng, split_key
from segmo.errors import SegmoError
from segmo.files import read_npy_shape
from segmo.models.tokenizer import FRAMES_PER_TOKEN
from segmo.motion.skeleton import SkeletonSpec, get_skeleton
from segmo.text.cache import TextFeatureCache
from segmo.text.captions import (
    CaptionLine,
    has_words,
    parse_text_line,
    read_caption_lines,
    texts_file,
)
from segmo.text.manifest import load_manifest
from segmo.text.rules import MAX_SEGMENTS

log = logging.getLogger(__name__)

# Kinds of skipped items that are reported with a warning (malformed data), as opposed to
# the length filters, which are ordinary and only counted.
WARNED_KINDS = ("missing", "empty", "unreadable", "missing_text", "bad_line",
                "missing_segments", "no_captions")


# ----------------------------------------------------------------------------- reading


class LoadReport:
    """Counts what a dataset skipped and why; warns once per kind; raises when strict."""

    def __init__(self, strict: bool = False) -> None:
        self.strict = strict
        self.counts: Counter[str] = Counter()
        self.problems: list[tuple[str, str]] = []  # (kind, "path[:line]: detail")

    def skip(self, kind: str, message: str) -> None:
        if self.strict:
            raise SegmoError(f"{message} (strict=True)")
        self.counts[kind] += 1
        self.problems.append((kind, message))

    def filtered(self, kind: str) -> None:
        self.counts[kind] += 1

    def finish(self, name: str, samples: int, motions: int) -> dict[str, int]:
        for kind in WARNED_KINDS:
            msgs = [m for k, m in self.problems if k == kind]
            if msgs:
                more = f" (+{len(msgs) - 3} more)" if len(msgs) > 3 else ""
                warnings.warn(f"{name}: skipped {len(msgs)} x {kind}: " + "; ".join(msgs[:3]) + more,
                              stacklevel=3)
        skipped = ", ".join(f"{k} {v}" for k, v in sorted(self.counts.items())) or "none"
        log.info("%s: loaded %d samples from %d motions; skipped: %s", name, samples, motions, skipped)
        return {"samples": samples, "motions": motions, **dict(self.counts)}


class MotionStore:
    """Raw (un-normalised) motions of a split, preloaded as read-only arrays or read lazily.

    Every file's values are checked at construction (`segmo.data.checks.value_problem`
    against ``mean``/``std``), lazy mode included, which reads each file once for that and
    keeps only its length; the store raises one `SegmoError` naming the unusable files.
    """

    def __init__(self, root: Path, ids: list[str], spec: SkeletonSpec, report: LoadReport,
                 preload: bool = True, *, mean: np.ndarray, std: np.ndarray,
                 max_abs_z: float | None = MAX_ABS_Z, where: str = "") -> None:
        self.root = root
        self.preload = preload
        self.spec = spec
        self.mean, self.std, self.max_abs_z = mean, std, max_abs_z
        self.arrays: dict[str, np.ndarray] = {}
        self.lengths: dict[str, int] = {}
        bad: list[tuple[Path, str]] = []
        for mid in ids:
            self._add(mid, report, bad)
        refuse_values(where or str(root), bad, len(ids), max_abs_z)

    def _add(self, mid: str, report: LoadReport, bad: list[tuple[Path, str]]) -> None:
        path = motion_file(self.root, mid)
        if not path.is_file():
            report.skip("missing", f"{path}: motion file not found")
            return
        if path.stat().st_size == 0:
            report.skip("empty", f"{path}: empty file")
            return
        try:
            self._check_shape(path, read_npy_shape(path))
            arr = np.load(path)
        except (OSError, ValueError, EOFError) as err:
            if isinstance(err, SegmoError):  # the wrong shape: raised, not skipped
                raise
            report.skip("unreadable", f"{path}: {err}")
            return
        if arr.shape[0] == 0:
            report.skip("empty", f"{path}: 0 frames")
            return
        problem = value_problem(arr, self.mean, self.std, self.max_abs_z)
        if problem is not None:
            bad.append((path, problem))
            return
        if self.preload:
            arr = np.array(arr, dtype=np.float32)
            arr.setflags(write=False)
            self.arrays[mid] = arr
        self.lengths[mid] = int(arr.shape[0])

    def _check_shape(self, path: Path, shape: tuple[int, ...]) -> None:
        if len(shape) != 2 or shape[1] != self.spec.feature_dim:
            raise SegmoError(f"{path}: shape {shape}, expected (t, {self.spec.feature_dim}) "
                             f"for skeleton {self.spec.name!r}")

    def __contains__(self, mid: str) -> bool:
        return mid in self.lengths

    def get(self, mid: str) -> np.ndarray:
        """(t, d) float32 raw features."""
        if self.preload:
            return self.arrays[mid]
        path = motion_file(self.root, mid)
        arr = np.load(path).astype(np.float32, copy=False)
        self._check_shape(path, arr.shape)
        problem = value_problem(arr, self.mean, self.std, self.max_abs_z)
        if problem is not None or arr.shape[0] != self.lengths[mid]:
            # The file changed after the dataset was checked.
            raise SegmoError(f"{path}: changed while training: "
                             f"{problem or f'{arr.shape[0]} frames, was {self.lengths[mid]}'}")
        return arr


def crop_offset(t: int, size: int, random: bool, rng: np.random.Generator) -> int:
    """Start frame of a ``size``-frame crop of ``t`` frames: 0, or uniform when ``random``."""
    if not random or t == size:
        return 0
    return int(rng.integers(0, t - size + 1))


# ----------------------------------------------------------------------------- datasets


@dataclass(frozen=True)
class _Entry:
    id: str  # sample id: motion id, or "<motion id>#<caption index>" for a time-tagged sub-clip
    motion_id: str
    caption_index: int
    caption: str
    segments: tuple[str, ...]
    start: int  # frame range of the motion file covered by the caption
    end: int
    spans: tuple[tuple[int, int], ...] | None


class MotionDataset(Dataset):
    """One sample per caption line of a split (see the module docstring for skips/errors).

    A sample is a dict (docs/design.md "A sample"): ``motion`` (t, d) float32 z-scored with
    t a multiple of `FRAMES_PER_TOKEN` (4); ``length`` t; ``caption``; ``segments`` list[str]
    (``text_segments/<name>/<id>.txt``, else ``[caption]``); ``id``; ``caption_index``;
    ``spans`` list[(start, end)] frames of the returned motion, end exclusive, or None; and
    with a text-feature cache ``sentence`` (dim,), ``segment_features`` (A, dim) zero-padded,
    ``segment_mask`` (A,) bool, and with ``text_tokens="words"`` the caption's per-word
    features ``word_features`` (l, dim) (the encoder's tokens, start and end included).

    Cropping to whole tokens drops ``t % FRAMES_PER_TOKEN`` frames: at a random
    offset when ``random_crop`` (training), else from the end (start 0, evaluation). Spans
    are shifted by the offset and clipped to [0, t]. Time-tagged sub-clips carry no spans
    (ground truth is only written for whole clips, by the built-in corpus). The offset is a
    function of ``(seed, epoch, i)`` (module docstring); keys may be ``i`` or ``(i, epoch)``.
    """

    def __init__(
        self,
        root: str | Path,
        split: str = "train",
        skeleton: str | SkeletonSpec = "t2m",
        *,
        mean: np.ndarray | None = None,
        std: np.ndarray | None = None,
        random_crop: bool = False,
        seed: int = 0,
        text_segments: str | None = None,
        text_features: str | None = None,
        text_cache: Any = None,
        max_segments: int = MAX_SEGMENTS,
        max_motions: int | None = None,
        preload: bool = True,
        strict: bool = False,
        max_abs_z: float | None = MAX_ABS_Z,
        text_tokens: str = "none",
    ) -> None:
        if max_segments < 1:
            raise SegmoError(f"max_segments={max_segments} must be at least 1")
        if text_tokens not in ("none", "words"):
            raise SegmoError(f"text_tokens={text_tokens!r}: choose none or words")
        self.text_tokens = text_tokens
        self.root = Path(root)
        self.split = split
        self.skeleton = get_skeleton(skeleton)
        self.random_crop = random_crop
        self.max_segments = max_segments
        self.mean, self.std = resolve_stats(self.root, self.skeleton, mean, std)
        self.seed, self.epoch = seed, 0
        seg_dir = None
        if text_segments is not None:
            seg_dir = self.root / "text_segments" / text_segments
            if not seg_dir.is_dir():
                raise FileNotFoundError(f"text-segment folder not found: {seg_dir}")

        ids = read_split(self.root, split)[:max_motions]
        report = LoadReport(strict)
        self.motions = MotionStore(self.root, ids, self.skeleton, report, preload, mean=self.mean,
                                   std=self.std, max_abs_z=max_abs_z,
                                   where=str(split_file(self.root, split)))
        self.entries: list[_Entry] = []
        for mid in ids:
            if mid in self.motions:
                self.entries += self._read_motion(mid, seg_dir, report)
        used = len({e.motion_id for e in self.entries})
        self.summary = report.finish(f"{self.root.name}/{split}", len(self.entries), used)
        self.problems = report.problems

        if text_cache is None and text_features is not None:
            text_cache = TextFeatureCache.open(self.root, text_features)
        self.text_cache = text_cache
        # The frozen tokenizer's codes of every crop, attached by the mask/residual tasks
        # (segmo.data.motion_tokens); samples then carry `tokens` (t // 4, q) long.
        self.motion_tokens: MotionTokenCache | None = None
        self._clip_keys: list[str] | None = None

    def _read_motion(self, mid: str, seg_dir: Path | None, report: LoadReport) -> list[_Entry]:
        spec = self.skeleton
        text_path = texts_file(self.root, mid)
        if not text_path.is_file():
            report.skip("missing_text", f"{text_path}: text file not found")
            return []
        lines = read_caption_lines(text_path)
        segments = self._read_segments(seg_dir, mid, text_path, lines, report)
        if segments is None:
            return []
        t_full = self.motions.lengths[mid]
        spans = caption_spans(self.root, mid, len(lines), t_full)
        out, parsed = [], 0
        for index, line in enumerate(lines):
            try:
                cap = parse_text_line(line.text, text_path, line.lineno)
            except ValueError as err:
                report.skip("bad_line", str(err))
                continue
            parsed += 1
            if cap.whole_clip:
                start, end, sid, sp = 0, t_full, mid, spans[index] if spans else None
            else:
                start = int(cap.start * spec.fps)
                end = min(int(cap.end * spec.fps), t_full)
                sid, sp = f"{mid}#{index}", None
            t = end - start
            if t < spec.min_frames:
                report.filtered("too_short")
                continue
            if t >= spec.max_frames:
                report.filtered("too_long")
                continue
            segs = segments[index] if segments else (cap.text,)
            out.append(_Entry(sid, mid, index, cap.text, segs, start, end, sp))
        if parsed == 0:  # (captions that were only too short/long are counted above)
            report.skip("no_captions", f"{text_path}: no usable caption line")
        return out

    def _read_segments(self, seg_dir: Path | None, mid: str, text_path: Path,
                       lines: list[CaptionLine], report: LoadReport
                       ) -> list[tuple[str, ...]] | None:
        """Per caption line, its text segments; [] when no segment folder was asked for.

        A folder written by `segment-texts` has a ``manifest.jsonl`` recording the captions
        each file was made from: a file made from other captions (edited in place since)
        raises. Without a manifest (made by hand) only the line counts are compared."""
        if seg_dir is None:
            return []
        path = seg_dir / f"{mid}.txt"
        if not path.is_file():
            report.skip("missing_segments", f"{path}: text-segment file not found")
            return None
        stale = load_manifest(seg_dir).stale_reason(mid, [line.caption for line in lines])
        if stale is not None:
            raise SegmoError(f"{path} is stale: {stale} ({text_path}); re-run `segmo segment-texts "
                             f"--data {self.root}` with the backend that made {seg_dir.name}/")
        seg_lines = read_caption_lines(path)
        if len(seg_lines) != len(lines):
            raise SegmoError(f"{path} has {len(seg_lines)} lines but {text_path} has "
                             f"{len(lines)}; line i of one must match line i of the other")
        out = []
        for line, caption in zip(seg_lines, lines, strict=True):
            segs = tuple(s.strip() for s in line.text.split("#") if s.strip())
            if not segs:
                raise SegmoError(f"{path}:{line.lineno}: no text segment on the line")
            # `segmo encode-texts` encodes no text without words, as the model takes none; a
            # caption without words has a placeholder line, and its caption line is skipped.
            wordless = [s for s in segs if not has_words(s)]
            if wordless and has_words(caption.caption):
                raise SegmoError(f"{path}:{line.lineno}: text segment {wordless[0]!r} holds no "
                                 "words; describe a motion or remove the segment")
            if len(segs) > self.max_segments:
                raise SegmoError(f"{path}:{line.lineno}: {len(segs)} text segments, more than "
                                 f"max_segments={self.max_segments}")
            out.append(segs)
        return out

    def __len__(self) -> int:
        return len(self.entries)

    def set_epoch(self, epoch: int) -> None:
        """The epoch whose crops plain integer keys get."""
        self.epoch = epoch

    # -- crops (the motion-token cache encodes each one: segmo.data.motion_tokens) --------

    def clip(self, i: int) -> np.ndarray:
        """(t_clip, d) raw frames of entry i: the motion, or its time-tagged sub-clip."""
        e = self.entries[i]
        return self.motions.get(e.motion_id)[e.start:e.end]

    def crop_length(self, i: int) -> int:
        """Frames of entry i's crops: the clip's length down to whole tokens."""
        t_clip = self.entries[i].end - self.entries[i].start
        return t_clip - t_clip % FRAMES_PER_TOKEN

    def crop_offsets(self, i: int) -> range:
        """The start frames entry i's crop can have: 0 .. t_clip % 4 with `random_crop`, else 0."""
        spare = self.entries[i].end - self.entries[i].start - self.crop_length(i)
        return range(spare + 1 if self.random_crop else 1)

    def crop(self, i: int, offset: int) -> torch.Tensor:
        """(t, d) float32 z-scored crop of entry i starting at `offset` frames."""
        raw = self.clip(i)
        t = self.crop_length(i)
        return torch.from_numpy((raw[offset:offset + t] - self.mean) / self.std)

    def clip_keys(self) -> list[str]:
        """`segmo.data.motion_tokens.clip_key` of every entry (computed once)."""
        if self._clip_keys is None:
            self._clip_keys = [clip_key(self.clip(i)) for i in range(len(self))]
        return self._clip_keys

    def __getitem__(self, key: int | tuple[int, int]) -> dict[str, Any]:
        i, epoch = split_key(key, self.epoch)
        e = self.entries[i]
        t = self.crop_length(i)
        off = crop_offset(e.end - e.start, t, self.random_crop, sample_rng(self.seed, epoch, i))
        motion = self.crop(i, off)
        spans = None
        if e.spans is not None:
            spans = [(min(max(s - off, 0), t), min(max(x - off, 0), t)) for s, x in e.spans]
        sample: dict[str, Any] = {
            "motion": motion, "length": t, "caption": e.caption, "segments": list(e.segments),
            "id": e.id, "caption_index": e.caption_index, "spans": spans,
        }
        if self.text_cache is not None:
            sample.update(self._text_features(e))
        if self.motion_tokens is not None:
            sample["tokens"] = self.motion_tokens.tokens(self.clip_keys()[i], off)
        return sample

    def _text_features(self, e: _Entry) -> dict[str, torch.Tensor]:
        cache = self.text_cache
        seg = cache.sentence(list(e.segments)).float()
        features = torch.zeros(self.max_segments, cache.dim)
        features[: seg.shape[0]] = seg
        mask = torch.zeros(self.max_segments, dtype=torch.bool)
        mask[: seg.shape[0]] = True
        out = {"sentence": cache.sentence([e.caption])[0].float(), "segment_features": features,
               "segment_mask": mask}
        if self.text_tokens == "words":
            out["word_features"] = cache.tokens(e.caption)
        return out

