"""`SegMo.compose`: one motion longer than the model's clips, from a list of (text,
frames) parts. Each part is generated from its text (one batch); between two parts,
`transition` new frames are drawn by masked inpainting (`segmo.generation.editing`) with
the end of the one and the start of the next visible, conditioned on both texts as two
ordered segments; parts and transitions are decoded window by window and joined with a
cross-fade of `COMPOSE_BLEND` frames at the edges of each transition.

    long = model.compose([("a man walks forward", 120), ("he jumps twice", 60)], transition=20)
"""

from __future__ import annotations

import numbers

import torch

from segmo.errors import SegmoError
from segmo.generation.editing import edit_tokens
from segmo.generation.generate import Precision
from segmo.models.tokenizer import FRAMES_PER_TOKEN
from segmo.motion.features import features_to_joints
from segmo.pipeline.editing import EditingModel
from segmo.pipeline.inputs import check_texts, whole_frames
from segmo.pipeline.outputs import GenerationOutput

# The frames drawn between two parts by default, and the cross-fade at the edges of each
# transition between the part's own decoding and the transition window's.
COMPOSE_TRANSITION = 20
COMPOSE_BLEND = 8
# The shortest part of a composition of two or more: a cross-fade at each end and a token.
COMPOSE_MIN_PART = 2 * COMPOSE_BLEND + FRAMES_PER_TOKEN
# The context a transition window keeps of each part, at least: the tokens of a cross-fade.
COMPOSE_MIN_CONTEXT = -(-COMPOSE_BLEND // FRAMES_PER_TOKEN)
# The longest composition (its memory and time grow with it: 100 parts of 196 frames,
# 16 minutes, took 2 GB and two minutes on two cores; a thousand were killed after 8).
COMPOSE_MAX_SECONDS = 20 * 60


def valid_transition(frames: object) -> bool:
    """Whether `frames` can be a transition of `compose`: whole tokens, at least one."""
    return (isinstance(frames, numbers.Integral) and not isinstance(frames, bool)
            and frames >= FRAMES_PER_TOKEN and frames % FRAMES_PER_TOKEN == 0)


# A part of a composition: (text, frames), or (text, frames, its segments' durations).
Part = tuple[str, int] | tuple[str, int, list[float]]


def compose(model: EditingModel, parts: list[Part], transition: int = COMPOSE_TRANSITION, *,
            generator: torch.Generator | None = None, precision: Precision = "auto"
            ) -> GenerationOutput:
    """`SegMo.compose` (its docstring says what comes back)."""
    if not isinstance(parts, (list, tuple)) or not parts or not all(
            isinstance(p, (list, tuple)) and len(p) in (2, 3) for p in parts):
        raise SegmoError(f"SegMo.compose: parts must be a list of (text, frames) or (text, "
                         f"frames, durations), got {parts!r:.80}")
    texts = check_texts([p[0] for p in parts], "part")
    listed = [p[1] for p in parts if not isinstance(p[1], numbers.Real)]
    if listed:  # a list would be spread over the parts by `whole_frames`
        raise SegmoError(f"SegMo.compose: a part's frames must be a whole number, got "
                         f"{listed[0]!r:.80}")
    # Whole numbers as ints (60.0 is 60 frames, as `generate` reads it) before the checks
    # below; 40.5 is refused here, as `generate` would.
    frames = whole_frames([p[1] for p in parts], len(parts), "SegMo.compose").tolist()
    durations = [p[2] if len(p) == 3 else None for p in parts]
    if not valid_transition(transition):
        raise SegmoError(f"SegMo.compose: transition must be a multiple of "
                         f"{FRAMES_PER_TOKEN} frames >= {FRAMES_PER_TOKEN}, got {transition!r}")
    blend, shortest = COMPOSE_BLEND, COMPOSE_MIN_PART
    if len(parts) > 1 and any(f < shortest for f in frames):
        raise SegmoError(f"SegMo.compose: each part of a composition needs at least "
                         f"{shortest} frames, got {frames}")
    t = int(transition) // FRAMES_PER_TOKEN
    max_tokens = model.mask.config.max_tokens
    if t > max_tokens - 2 * COMPOSE_MIN_CONTEXT:
        raise SegmoError(f"SegMo.compose: transition {transition} frames leaves too little "
                         f"room for context in the model's {model.max_frames} frames (at most "
                         f"{(max_tokens - 2 * COMPOSE_MIN_CONTEXT) * FRAMES_PER_TOKEN})")
    total = sum(frames) + transition * (len(parts) - 1)
    if total > COMPOSE_MAX_SECONDS * model.fps:
        raise SegmoError(f"SegMo.compose: {len(parts)} parts make {total} frames, more than "
                         f"{COMPOSE_MAX_SECONDS // 60} minutes at {model.fps:g} fps; compose "
                         "fewer parts at a time")
    out = model.generate(texts, frames, generator=generator, precision=precision,
                         durations=durations)
    if len(parts) == 1:
        out.spans = [[(0, int(out.lengths[0]))]]
        return out
    tokens, lengths = out.tokens, out.lengths
    counts = (lengths // FRAMES_PER_TOKEN).tolist()
    contexts = [min(counts[i], counts[i + 1], (max_tokens - t) // 2)
                for i in range(len(parts) - 1)]
    width = max(2 * c + t for c in contexts)
    q = tokens.shape[2]
    windows = tokens.new_full((len(contexts), width, q), -1)
    spans = torch.zeros(len(contexts), 2, dtype=torch.long)
    for i, c in enumerate(contexts):
        windows[i, :c] = tokens[i, counts[i] - c:counts[i]]
        windows[i, c:c + t] = 0  # placeholders, redrawn
        windows[i, c + t:2 * c + t] = tokens[i + 1, :c]
        spans[i] = torch.tensor([c, c + t])
    pairs = [f"{texts[i].rstrip('. ')}, then {texts[i + 1]}" for i in range(len(contexts))]
    segments = [[out.segments[i][-1], out.segments[i + 1][0]] for i in range(len(contexts))]
    window_lengths = torch.tensor([(2 * c + t) * FRAMES_PER_TOKEN for c in contexts],
                                  device=model.device)
    sentence, vectors, segment_mask, _ = model.text_condition(pairs, segments)
    words, word_mask = model.word_condition(pairs, segments, out.sampling.word_text)
    filled = edit_tokens(model.mask, model.residual, windows.to(model.device),
                         spans.to(model.device), sentence, vectors, segment_mask,
                         options=out.sampling, generator=generator, precision=precision,
                         words=words, word_mask=word_mask)
    decoded = model.decode(filled, window_lengths, pairs, segments, precision).features
    pieces, all_tokens, part_spans, at = [], [], [], 0
    ramp = torch.linspace(0, 1, blend + 2, dtype=out.features.dtype,
                          device=out.features.device)[1:-1, None]
    for i in range(len(parts)):
        part = out.features[i, :int(lengths[i])].clone()
        if i > 0:  # fade in from the transition window's decoding of the same frames
            c = contexts[i - 1] * FRAMES_PER_TOKEN + transition
            part[:blend] = (1 - ramp) * decoded[i - 1, c:c + blend] + ramp * part[:blend]
        if i < len(parts) - 1:
            c = contexts[i] * FRAMES_PER_TOKEN
            part[-blend:] = (1 - ramp) * part[-blend:] + ramp * decoded[i, c - blend:c]
        part_spans.append((at, at + part.shape[0]))
        pieces.append(part)
        all_tokens.append(tokens[i, :counts[i]])
        at += part.shape[0]
        if i < len(parts) - 1:
            c = contexts[i] * FRAMES_PER_TOKEN
            pieces.append(decoded[i, c:c + transition])
            all_tokens.append(filled[i, contexts[i]:contexts[i] + t].to(tokens.device))
            at += transition
    features = torch.cat(pieces)[None]
    total = torch.tensor([features.shape[1]], device=features.device)
    joints = features_to_joints(features, model.skeleton).float()
    text = ". Then ".join(x.rstrip(". ") for x in texts) + "."
    return GenerationOutput(features=features.float(), joints=joints,
                            tokens=torch.cat(all_tokens)[None], lengths=total.long(),
                            texts=[text], segments=[list(texts)], skeleton=model.skeleton,
                            fps=model.fps, spans=[part_spans], model=model.weights_fingerprint())
