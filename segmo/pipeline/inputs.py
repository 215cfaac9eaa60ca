"""What a user hands the `SegMo` API, turned into tensors, or one clear error.

Every check of a text, a length, a motion array or a device lives here, so that the API's
methods read as what they do; each failure is a `SegmoError` naming what is wrong
(docs/hostile-inputs.md lists the cases the tests try).
"""

from __future__ import annotations

import math
import numbers
import warnings
from typing import Any

import numpy as np
import torch

from segmo.errors import LARGEST_WHOLE_NUMBER, SegmoError
from segmo.models.tokenizer import FRAMES_PER_TOKEN


def check_texts(texts: Any, what: str = "text", words: bool = True) -> list[str]:
    """A list of strings that each hold a word (any valid text with words=False), or
    SegmoError naming the first that does not ("text 2", or with what="text 0, segment":
    "text 0, segment 1")."""
    if isinstance(texts, str) or not isinstance(texts, (list, tuple)):
        raise SegmoError(f"SegMo: expected a list of strings ({what}s), got {texts!r:.80}")
    for i, text in enumerate(texts):
        if not isinstance(text, str):
            raise SegmoError(f"SegMo: {what} {i} is a {type(text).__name__}, not a string")
        if not text.isascii():
            try:
                text.encode("utf-8")
            except UnicodeEncodeError as error:  # a lone surrogate: bytes that were not UTF-8
                raise SegmoError(f"SegMo: {what} {i} ({text!r:.80}) is not valid Unicode at "
                                 f"character {error.start} (bytes that are not UTF-8?)") from None
        if words and not any(c.isalnum() for c in text):
            raise SegmoError(f"SegMo: {what} {i} ({text!r:.80}) holds no words; describe a motion")
    return list(texts)


def check_span(span: Any, what: str, limit: int | None = None, unit: str = "frames"
               ) -> tuple[int, int]:
    """(start, end) of a span given as two whole numbers with 0 ≤ start < end (≤ `limit`
    where given), or SegmoError naming `what`: a fraction would be cut to a whole frame, a
    negative start clamped and a reversed span dropped, each without a word."""
    if not (isinstance(span, (tuple, list)) and len(span) == 2
            and all(isinstance(v, numbers.Integral) and not isinstance(v, bool) for v in span)):
        raise SegmoError(f"{what}: span must be (start, end) whole {unit}, got {span!r:.80}")
    start, end = int(span[0]), int(span[1])
    if not 0 <= start < end or (limit is not None and end > limit):
        bound = "" if limit is None else f" ≤ {limit}"
        raise SegmoError(f"{what}: span must satisfy 0 ≤ start < end{bound} {unit}, got "
                         f"{(start, end)}")
    return start, end


def check_generator(generator: Any, what: str) -> None:
    """SegmoError unless `generator` is None or a `torch.Generator` (whose state a result
    records, so that its draws can be replayed)."""
    if generator is not None and not isinstance(generator, torch.Generator):
        raise SegmoError(f"{what}: generator must be a torch.Generator or None, got "
                         f"{generator!r:.80}")


def warn_truncated(encoder: Any, texts: list[str]) -> None:
    """Say so when a text is longer than the encoder reads: it encodes the start only, as
    `segmo encode-texts` did for the training captions, so the rest cannot steer the motion."""
    tokenizer, limit = getattr(encoder, "tokenizer", None), getattr(encoder, "max_length", None)
    if tokenizer is None or not limit:
        return
    for text in texts:
        if len(text) < limit:  # a token spans at least one character
            continue
        count = len(tokenizer(text, truncation=False, verbose=False)["input_ids"])
        if count > limit:
            warnings.warn(f"SegMo: the text {text[:60]!r}... has {count} tokens; the text encoder "
                          f"reads the first {limit}", stacklevel=4)


def resolve_device(device: str | torch.device) -> torch.device:
    """`device` as a torch.device this build can use, or SegmoError saying why not."""
    try:
        device = torch.device(device)
    except (RuntimeError, TypeError) as error:
        raise SegmoError(f"SegMo: device {device!r} is not a torch device ({error})") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise SegmoError(f"SegMo: device {str(device)!r} asked for, but this torch build sees "
                         "no CUDA GPU; use --device cpu")
    if device.type == "mps" and not torch.backends.mps.is_available():
        raise SegmoError(f"SegMo: device {str(device)!r} asked for, but MPS is not available")
    return device


def whole_frames(lengths: Any, b: int, what: str = "SegMo") -> torch.Tensor:
    """User lengths (a number for all b, or a list, array or tensor) → long tensor on the
    CPU, or SegmoError: 40.7 frames is a mistake to report, not to round; so are True,
    "40" and NaN."""
    if isinstance(lengths, (torch.Tensor, np.ndarray)):
        lengths = lengths.tolist()
    values = [lengths] * b if np.ndim(lengths) == 0 else np.ravel(
        np.asarray(lengths, dtype=object)).tolist()
    whole = [not isinstance(v, bool) and (isinstance(v, numbers.Integral) or isinstance(
        v, numbers.Real) and math.isfinite(v) and float(v).is_integer()) for v in values]
    if not all(whole):
        raise SegmoError(f"{what}: lengths must be whole numbers of frames, got "
                         f"{values[whole.index(False)]!r}")
    frames = [int(v) for v in values]
    huge = [v for v in frames if abs(v) > LARGEST_WHOLE_NUMBER]
    if huge:  # torch would fail with "Overflow when unpacking long"
        raise SegmoError(f"{what}: a length of {huge[0]!r} frames is out of range")
    return torch.tensor(frames, dtype=torch.long)


def frame_lengths(lengths: Any, b: int, max_frames: int, fps: float) -> torch.Tensor:
    """User lengths (int, list or tensor of frames) for b texts → (b,) long on the CPU."""
    out = whole_frames(lengths, b)
    if out.numel() != b:
        raise SegmoError(f"SegMo: {out.numel()} lengths for {b} texts")
    unit = FRAMES_PER_TOKEN
    bad = (out % unit != 0) | (out < unit) | (out > max_frames)
    if bool(bad.any()):
        raise SegmoError(f"SegMo: lengths must be multiples of {unit} frames in [{unit}, "
                         f"{max_frames}] ({max_frames / fps:.1f} s at {fps:g} fps); got "
                         f"{out[bad].tolist()}")
    return out


def motion_array(motion: Any, feature_dim: int, max_frames: int, skeleton: str
                 ) -> tuple[torch.Tensor, int]:
    """A (t, d) motion (numpy, torch or nested lists) → float32 (t, d) tensor and the frames
    the tokenizer can use (t rounded down to a multiple of its frames per token)."""
    if (motion.is_complex() if isinstance(motion, torch.Tensor) else np.iscomplexobj(motion)):
        raise SegmoError("SegMo: a motion must be a real (t, d) array, got complex numbers")
    try:
        x = torch.as_tensor(np.asarray(motion, dtype=np.float32)
                            if not isinstance(motion, torch.Tensor) else motion).float()
    except (TypeError, ValueError) as error:
        raise SegmoError(f"SegMo: a motion must be a numeric (t, d) array ({error})") from None
    if x.ndim != 2 or x.shape[1] != feature_dim:
        raise SegmoError(f"SegMo: a motion must be raw features (t, {feature_dim}) for skeleton "
                         f"{skeleton!r}, got shape {tuple(x.shape)}")
    t = x.shape[0]
    usable = t - t % FRAMES_PER_TOKEN
    if usable < FRAMES_PER_TOKEN or usable > max_frames:
        raise SegmoError(f"SegMo: a motion must have {FRAMES_PER_TOKEN}.."
                         f"{max_frames + FRAMES_PER_TOKEN - 1} frames, got {t}")
    return x, usable


def motion_rows(motions: Any, lengths: Any, what: str) -> list[Any]:
    """Motions as a list of (t_i, d) arrays/tensors, or as a (b, t, d) array/tensor whose
    row i holds `lengths[i]` frames (default: all t) → one (t_i, d) motion per row;
    SegmoError naming `what` for lengths that do not fit or an empty batch."""
    if isinstance(motions, (torch.Tensor, np.ndarray)) and np.ndim(motions) == 3:
        x = motions.float() if isinstance(motions, torch.Tensor) else torch.as_tensor(
            np.asarray(motions, dtype=np.float32))
        b, t = x.shape[:2]
        frames = torch.full((b,), t) if lengths is None else whole_frames(lengths, b, what)
        if frames.numel() != b:
            raise SegmoError(f"{what}: {frames.numel()} lengths for {b} motions")
        if bool(((frames < 1) | (frames > t)).any()):
            raise SegmoError(f"{what}: lengths must be in [1, {t}] frames (the tensor's "
                             f"time axis), got {frames.tolist()}")
        motions = [x[i, : int(n)] for i, n in enumerate(frames)]
    elif lengths is not None:
        raise SegmoError(f"{what}: lengths are only used with a (b, t, d) motion tensor")
    elif isinstance(motions, (torch.Tensor, np.ndarray)):
        raise SegmoError(f"{what}: motions must be a list of (t, d) motions or one (b, t, d) "
                         f"tensor, got shape {tuple(motions.shape)} (wrap one motion in a list)")
    motions = list(motions)
    if not motions:
        raise SegmoError(f"{what}: no motion given")
    return motions


def segment_durations(durations: Any, segments: list[list[str]]) -> torch.Tensor | None:
    """Per text, how long each of its segments lasts (any unit: shares of the motion), or
    None for a text whose durations the timing head predicts → (b, a) float32, 0 in empty
    slots and in the rows of None (None when no text has durations); SegmoError naming the
    text whose durations do not fit its segments."""
    if isinstance(durations, (str, bytes)) or not hasattr(durations, "__len__") \
            or len(durations) != len(segments):
        raise SegmoError(f"SegMo.generate: durations must be one list per text "
                         f"({len(segments)}), got {durations!r:.80}")
    out = torch.zeros(len(segments), max(len(s) for s in segments), dtype=torch.float32)
    for i, (values, segs) in enumerate(zip(durations, segments)):
        if values is None:
            continue
        try:
            values = [float(v) for v in values]
        except (TypeError, ValueError):
            raise SegmoError(f"SegMo.generate: durations[{i}] must be numbers, got "
                             f"{values!r:.80}") from None
        if len(values) != len(segs):
            raise SegmoError(f"SegMo.generate: durations[{i}] has {len(values)} values, "
                             f"text {i} has {len(segs)} segments {segs!r:.120}")
        if not all(math.isfinite(v) and v >= 0 for v in values) or sum(values) <= 0:
            raise SegmoError(f"SegMo.generate: durations[{i}] must be finite, ≥ 0 and not "
                             f"all 0, got {values!r:.80}")
        # As shares of the largest, in float64: 3e38 and 1e39 overflowed float32 (to spans
        # of 1 token and 11, or to an error), though they read as an even split.
        largest = max(values)
        out[i, : len(values)] = torch.tensor([v / largest for v in values])
    return None if all(values is None for values in durations) else out
