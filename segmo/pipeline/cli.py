"""`segmo generate`, `segmo edit`, `segmo compose`, `segmo ground` and `segmo bundle`
(registered in segmo/cli.py).

    segmo bundle --tokenizer models/rvq --mask models/mask --residual models/residual \
        --length models/length --out models/segmo
    segmo generate --model models/segmo --text "a person walks forward, then waves" \
        --length 120 --seed 0 --out runs/gen --formats npy,gif,bvh
    segmo ground --model models/segmo --text "a person walks, then waves" \
        --motion runs/gen/sample_00_features.npy --out map.png     # ordered spans
    segmo ground ... --window 5                                     # the paper's window
    segmo edit --model models/segmo --source-text "a person walks, then jumps" \
        --target-text "a person walks, then kicks" --seed 0 --out runs/edit   # attention swap
    segmo compose --model models/segmo --text "a person walks forward" --length 160 \
        --text "he jumps twice" --length 80 --transition 20 --out runs/long
"""

from __future__ import annotations

import argparse
import math
import os
from pathlib import Path
from typing import get_args

import torch

from segmo.errors import (
    ArgumentParser,
    SegmoError,
    ascii_whole_number,
    finite_float,
    non_negative_float,
    non_negative_int,
    parse_durations,
    positive_int,
)
from segmo.files import (
    atomic_open,
    file_above,
    npy_argument,
    output_folder,
    remove_stale_temporaries,
    replaced_folder,
)
from segmo.generation.allocator import keep_freed_memory
from segmo.generation.attention_edit import EDIT_MODES, INJECT_UNTIL
from segmo.generation.sampling import Remasking, SamplingOptions, WordText
from segmo.models.hub import is_hub_id
from segmo.models.tokenizer import FRAMES_PER_TOKEN
from segmo.motion.bvh import ANIMATION_FPS, MAX_BVH_FPS, MIN_BVH_FPS, check_bvh_fps
from segmo.pipeline.bundle import KIT_GUIDANCE_SCALE, TEXT_SEGMENTERS
from segmo.pipeline.compose import COMPOSE_TRANSITION
from segmo.pipeline.grounding import (
    METHODS,
    MIN_TOKENS,
    PAPER_WINDOW,
    SEARCHES,
    plot_similarity_map,
)
from segmo.pipeline.model_card import read_metrics
from segmo.pipeline.outputs import FORMATS, check_save_target, save_outputs
from segmo.pipeline.segmo import SegMo


def _load(parser: argparse.ArgumentParser, directory: str):
    if not Path(directory).is_dir() and not is_hub_id(directory):
        parser.error(f"--model {directory}: no such directory (a bundle made by `segmo bundle`, "
                     "or a hub id like owner/name)")
    try:
        return SegMo.from_pretrained(directory)
    except (FileNotFoundError, ValueError) as error:
        raise SegmoError(f"--model {directory}: {error}") from error


def _check_output_dir(parser: argparse.ArgumentParser, flag: str, value: str,
                      saves: dict[str, int] | None = None, formats: tuple[str, ...] = ()) -> None:
    """Refuse an output path that cannot become a directory before any work is done (and,
    for the commands that write motions, `saves[prefix]` of them in `formats`, one that
    `save_outputs` would refuse: `check_save_target`)."""
    path = Path(value)
    if path.is_symlink() and not path.exists():
        parser.error(f"{flag} {value}: a symbolic link to {os.readlink(path)}, which does not exist")
    if path.exists() and not path.is_dir():
        parser.error(f"{flag} {value}: exists and is not a directory")
    above = file_above(path)
    if above is not None:
        parser.error(f"{flag} {value}: {above} is a file, not a directory")
    try:
        if saves:
            check_save_target(path, saves, formats)
    except SegmoError as error:
        parser.error(f"{flag}: {error}")


def _formats(parser: argparse.ArgumentParser, value: str) -> tuple[str, ...]:
    formats = tuple(f.strip() for f in value.split(",") if f.strip())
    unknown = sorted(set(formats) - set(FORMATS))
    if unknown or not formats:
        parser.error(f"--formats {value!r}: choose a comma-separated subset of {','.join(FORMATS)}")
    return formats


def _bvh_fps(text: str) -> float:
    """argparse type of --bvh-fps: a frame rate the BVH writer takes (`check_bvh_fps`)."""
    finite_float(text)  # NaN and inf: "expected a finite number"
    try:
        return check_bvh_fps(text, "--bvh-fps")
    except SegmoError as error:
        raise argparse.ArgumentTypeError(str(error).removeprefix("--bvh-fps: ")) from None


def _output_arguments(parser: argparse.ArgumentParser) -> None:
    """--precision, --out, --formats, --bvh-fps and --no-foot-lock of the commands that
    write motions (generate, edit, compose)."""
    parser.add_argument("--precision", choices=("auto", "fp32", "bf16"), default="auto",
                        help="auto: bf16 on CPUs with native bf16 (AVX512-BF16, AMX), else fp32")
    parser.add_argument("--out", type=output_folder, required=True, help="output directory")
    parser.add_argument("--formats", default=",".join(FORMATS),
                        help=f"comma-separated subset of {','.join(FORMATS)}")
    parser.add_argument("--bvh-fps", type=_bvh_fps, default=ANIMATION_FPS,
                        help=f"frame rate of the BVH files, {MIN_BVH_FPS:g} to {MAX_BVH_FPS:g} "
                        f"(default {ANIMATION_FPS:g}: the motion's frames kept, slerp between "
                        "them; 20 writes t2m motions' own frames)")
    parser.add_argument("--no-foot-lock", action="store_true",
                        help="BVH: do not hold the feet still while they touch the ground")


def generate_main(argv: list[str] | None = None) -> None:
    parser = ArgumentParser(prog="segmo generate",
                                     description="generate motions from text with a SegMo bundle")
    parser.add_argument("--model", required=True, help="bundle directory (`segmo bundle`)")
    parser.add_argument("--text", action="append", required=True,
                        help="prompt; repeat for several motions")
    parser.add_argument("--length", type=positive_int, action="append", default=None,
                        help="frames (multiple of 4); once for all prompts or once per prompt; "
                             "default: sampled by the length estimator")
    parser.add_argument("--seed", type=non_negative_int, default=0)
    parser.add_argument("--guidance", type=finite_float, default=None,
                        help="classifier-free guidance scale of the base tokens (bundle default)")
    parser.add_argument("--residual-guidance", type=finite_float, default=None,
                        help="the same for the residual tokens (bundle default)")
    parser.add_argument("--guidance-mode", choices=("cfg", "sink_ctrl"), default=None,
                        help="base-token guidance: cfg, or MLA-Gen's sink_ctrl (bundle default)")
    # Unset options take the bundle's sampling defaults (SegMo.sampling), and those of
    # SamplingOptions for what a bundle does not record (the temperature).
    parser.add_argument("--steps", type=positive_int, default=None,
                        help=f"masked-decoding steps (bundle default; {SamplingOptions.steps} "
                             "unless it says otherwise)")
    parser.add_argument("--residual-guided-layers", type=non_negative_int, default=None,
                        help="how many residual layers, from the first, are guided (bundle "
                             "default; all unless it says otherwise)")
    parser.add_argument("--temperature", type=finite_float, default=None,
                        help=f"sampling temperature, 0 = greedy (default "
                             f"{SamplingOptions.temperature:g})")
    parser.add_argument("--word-text", choices=get_args(WordText), default=None,
                        help="what a words model's word keys read: the caption or its text "
                             "segments joined in execution order (default: the bundle's)")
    parser.add_argument("--durations", action="append", default=None, metavar="D1,D2,...",
                        help="how long each text segment lasts, e.g. 1,4 (any unit, read as "
                             "shares of the motion), for a model trained with segment timing; "
                             "once per --text, 'auto' for a text whose durations its timing "
                             "head predicts (the default for all)")
    parser.add_argument("--device", default="cpu")
    _output_arguments(parser)
    args = parser.parse_args(argv)
    formats = _formats(parser, args.formats)
    durations = _durations_per_text(parser, args.durations, len(args.text))
    lengths = args.length
    if lengths is not None and len(lengths) not in (1, len(args.text)):
        parser.error(f"--length given {len(lengths)} times for {len(args.text)} --text; "
                     "give it once or once per --text")
    if lengths is not None and len(lengths) == 1:
        lengths = lengths * len(args.text)
    if args.temperature is not None and args.temperature < 0:
        parser.error(f"argument --temperature: expected a number >= 0, got {args.temperature:g}")
    _check_output_dir(parser, "--out", args.out, {"sample": len(args.text)}, formats)
    model = _load(parser, args.model)
    try:
        model = model.to(args.device)
    except SegmoError as error:
        raise SegmoError(f"--device: {error}") from None
    if args.word_text is not None:  # this run's default: the generation and the GIF's grounding
        model.config.word_text = args.word_text
    generator = torch.Generator(device=args.device).manual_seed(args.seed)
    keep_freed_memory()
    out = model.generate(args.text, lengths, guidance_scale=args.guidance,
                         residual_guidance_scale=args.residual_guidance, steps=args.steps,
                         residual_guided_layers=args.residual_guided_layers,
                         guidance=args.guidance_mode,
                         temperature=args.temperature, generator=generator,
                         precision=args.precision, durations=durations)
    spans = _gif_spans(model, out) if "gif" in formats else None
    for path in out.save(args.out, formats, bvh_fps=args.bvh_fps, foot_lock=not args.no_foot_lock,
                         spans=spans, progress=True):
        print(path)


def _gif_spans(model: SegMo, out) -> list[list[tuple[int, int]] | None]:
    """Which segment each frame of each GIF shows, from the model's own attention
    (`SegMo.ground`, method "attention"). A motion with fewer than MIN_TOKENS tokens a
    segment (a short --length, or a short predicted one) is grounded with one-token spans,
    and one with fewer tokens than segments gets no labels (None): its files are written
    all the same."""
    spans = []
    for i, text in enumerate(out.texts):
        tokens, count = int(out.lengths[i]) // FRAMES_PER_TOKEN, len(out.segments[i])
        if tokens < count:
            spans.append(None)
            continue
        grounding = model.ground(text, out.motion(i), segments=out.segments[i],
                                 method="attention",
                                 min_tokens=MIN_TOKENS if tokens >= count * MIN_TOKENS else 1)
        spans.append(grounding.best_spans_frames)
    return spans


def _durations_per_text(parser: argparse.ArgumentParser, values: list[str] | None,
                        texts: int) -> list[list[float] | None] | None:
    """`--durations`, given once per --text or not at all → one entry per text (None:
    predicted), or None when it is not given; one error line for a wrong count."""
    if values is None:
        return None
    if len(values) != texts:
        parser.error(f"--durations given {len(values)} times for {texts} --text; give it once "
                     "per --text")
    return [_durations(parser, value) for value in values]


def _durations(parser: argparse.ArgumentParser, value: str) -> list[float] | None:
    """`--durations 1,4` → [1.0, 4.0], `--durations auto` → None (predicted); one error
    line for anything else."""
    if value.strip() == "auto":
        return None
    try:
        return parse_durations(value)
    except ValueError as error:
        parser.error(f"--durations {error}")


def _weight(parser: argparse.ArgumentParser, value: str) -> tuple[str | int, float]:
    """`--weight KEY=C` → (segment number or text or key label, factor)."""
    key, sep, factor = value.rpartition("=")
    try:
        number = float(factor)
    except ValueError:
        number = None
    if not sep or not key.strip() or number is None or not math.isfinite(number):
        parser.error(f"--weight {value!r:.80}: expected SEGMENT=FACTOR, e.g. 2=1.5 or jumps=-1")
    key = key.strip()
    segment = ascii_whole_number(key)
    return (key if segment is None else segment), number


def edit_main(argv: list[str] | None = None) -> None:
    parser = ArgumentParser(
        prog="segmo edit",
        description="edit a generated motion by its attention: swap, add or refine a segment's "
                    "text, or reweight a segment")
    parser.add_argument("--model", required=True, help="bundle directory (`segmo bundle`)")
    parser.add_argument("--source-text", required=True, help="the prompt of the source motion")
    parser.add_argument("--target-text", default=None,
                        help="the edited prompt (swap, add, refine; reweight edits the "
                             "--source-text and takes none)")
    parser.add_argument("--mode", choices=EDIT_MODES, default="swap")
    parser.add_argument("--weight", action="append", default=None, metavar="SEGMENT=FACTOR",
                        help="reweight: a segment (number from 1, or its text) and its factor; "
                             "repeat for several")
    parser.add_argument("--inject-until", type=finite_float, default=None,
                        help=f"share of decoding steps with the source's attention, for swap, "
                             f"add and refine (default {INJECT_UNTIL:g})")
    parser.add_argument("--keep-outside", action="store_true",
                        help="keep every token outside the changed segment's attended span")
    parser.add_argument("--length", type=positive_int, default=None,
                        help="frames (multiple of 4); default: sampled by the length estimator")
    parser.add_argument("--seed", type=non_negative_int, default=0)
    _output_arguments(parser)
    args = parser.parse_args(argv)
    formats = _formats(parser, args.formats)
    if args.mode == "reweight" and not args.weight:
        parser.error("--mode reweight needs --weight SEGMENT=FACTOR")
    if args.mode != "reweight" and args.weight:  # it would be ignored without a word
        parser.error(f"--weight is for --mode reweight; --mode {args.mode} takes none")
    if args.mode != "reweight" and args.target_text is None:
        parser.error(f"--mode {args.mode} needs --target-text")
    # Each would be ignored without a word: a reweight edits the source's text, every pass.
    if args.mode == "reweight" and args.inject_until is not None:
        parser.error("--inject-until is for --mode swap, add and refine; --mode reweight edits "
                     "every pass")
    if args.mode == "reweight" and args.target_text not in (None, args.source_text):
        parser.error("--target-text is for --mode swap, add and refine; --mode reweight edits "
                     "the --source-text")
    if args.inject_until is not None and not 0.0 <= args.inject_until <= 1.0:
        parser.error(f"argument --inject-until: expected a number in [0, 1], got "
                     f"{args.inject_until:g}")
    pairs = [_weight(parser, w) for w in args.weight or []]
    weights = dict(pairs)
    if len(weights) < len(pairs):  # the last factor of a segment won without a word
        parser.error("--weight names one segment twice; give each segment one factor")
    _check_output_dir(parser, "--out", args.out, {"source": 1, "edit": 1}, formats)
    model = _load(parser, args.model)
    keep_freed_memory()
    generator = torch.Generator().manual_seed(args.seed)
    source = model.generate([args.source_text], None if args.length is None else [args.length],
                            generator=generator, precision=args.precision)
    out = model.edit_text(source, args.target_text, args.mode, weights=weights or None,
                          inject_until=args.inject_until, keep_outside=args.keep_outside,
                          precision=args.precision)
    for path in save_outputs(args.out, {"source": source, "edit": out}, formats,
                             bvh_fps=args.bvh_fps, foot_lock=not args.no_foot_lock, progress=True):
        print(path)


def compose_main(argv: list[str] | None = None) -> None:
    parser = ArgumentParser(
        prog="segmo compose",
        description="one motion longer than a clip from a list of prompts, joined by "
                    "inpainted transitions")
    parser.add_argument("--model", required=True, help="bundle directory (`segmo bundle`)")
    parser.add_argument("--text", action="append", required=True,
                        help="a part's prompt, in order; repeat for each part")
    parser.add_argument("--length", type=positive_int, action="append", required=True,
                        help="a part's frames (multiple of 4); once per --text")
    parser.add_argument("--transition", type=positive_int, default=COMPOSE_TRANSITION,
                        help=f"frames drawn between two parts (default {COMPOSE_TRANSITION})")
    parser.add_argument("--durations", action="append", default=None, metavar="D1,D2,...",
                        help="how long each segment of a part lasts, e.g. 1,4, for a model "
                             "trained with segment timing; once per --text, 'auto' for a part "
                             "whose durations its timing head predicts (the default for all)")
    parser.add_argument("--seed", type=non_negative_int, default=0)
    _output_arguments(parser)
    args = parser.parse_args(argv)
    formats = _formats(parser, args.formats)
    if len(args.length) != len(args.text):
        parser.error(f"--length given {len(args.length)} times for {len(args.text)} --text; "
                     "give one per --text")
    durations = _durations_per_text(parser, args.durations, len(args.text))
    parts = list(zip(args.text, args.length, durations or [None] * len(args.text)))
    _check_output_dir(parser, "--out", args.out, {"sample": 1}, formats)
    model = _load(parser, args.model)
    keep_freed_memory()
    out = model.compose(parts, args.transition,
                        generator=torch.Generator().manual_seed(args.seed),
                        precision=args.precision)
    for path in out.save(args.out, formats, bvh_fps=args.bvh_fps, foot_lock=not args.no_foot_lock,
                         progress=True):
        print(path)


def _true_spans(motion: Path, text: str, segments: list[str]) -> list[tuple[int, int]] | None:
    """The ground-truth frame spans of `text` when `motion` is DATA/new_joint_vecs/<id>.npy
    of a dataset with DATA/segments/<id>.json (the built-in corpus) holding that caption
    with as many segments; None otherwise."""
    from segmo.data.layout import read_ground_truth

    if motion.parent.name != "new_joint_vecs":
        return None
    try:
        record = read_ground_truth(motion.parent.parent, motion.stem)
    except (FileNotFoundError, SegmoError):
        return None
    wanted = " ".join(text.lower().split()).rstrip(".!? ")
    for caption in record.get("captions", []):
        if " ".join(str(caption.get("text", "")).lower().split()).rstrip(".!? ") == wanted:
            spans = [(int(s["start"]), int(s["end"])) for s in caption.get("segments", [])]
            return spans if len(spans) == len(segments) else None
    return None


# What `segmo ground --out` writes the similarity map as: file types matplotlib saves with
# no more than it needs itself (pgf wants LaTeX, avif a Pillow plugin).
MAP_FORMATS = ("png", "pdf", "svg", "jpg", "jpeg")


def _map_format(parser: argparse.ArgumentParser, value: str, overwrite: bool) -> str:
    """The image format of `segmo ground --out`, from its suffix, refused before any work
    (matplotlib would fail after the grounding, or write DIR.png for a folder), as is a file
    or symbolic link already there unless `overwrite` (the map replaces a link, never
    writing through it)."""
    path = Path(value)
    if path.is_dir():
        parser.error(f"--out {value}: is a directory; name an image file, e.g. "
                     f"{path / 'map.png'}")
    suffix = path.suffix.lower().removeprefix(".")
    if suffix not in MAP_FORMATS:
        parser.error(f"--out {value}: name an image file ending in "
                     f"{', '.join('.' + f for f in MAP_FORMATS)}")
    if not overwrite and (path.is_symlink() or path.exists()):
        found = f"a symbolic link to {os.readlink(path)}" if path.is_symlink() else "exists"
        parser.error(f"--out {value}: {found}; pass --overwrite to replace it, or name "
                     "another file")
    _check_output_dir(parser, "--out", str(path.parent))
    return suffix


def ground_main(argv: list[str] | None = None) -> None:

    parser = ArgumentParser(
        prog="segmo ground", description="find where each segment of a text happens in a motion")
    parser.add_argument("--model", required=True, help="bundle directory (`segmo bundle`)")
    parser.add_argument("--text", required=True, help="query text (split into segments)")
    parser.add_argument("--segments", default=None,
                        help="the query's segments separated by '#' (default: rule segmenter)")
    parser.add_argument("--motion", required=True,
                        help="raw motion features .npy (t, d), e.g. new_joint_vecs/<id>.npy")
    parser.add_argument("--search", choices=SEARCHES, default=None,
                        help="ordered (default): one span per segment in caption order, cutting "
                             "the motion; spans: each segment's best span of any length; window: "
                             "the paper's sliding window (default when --window is given)")
    parser.add_argument("--window", type=positive_int, default=None,
                        help=f"sliding-window size in tokens (4 frames) of --search window "
                             f"(default {PAPER_WINDOW}, the paper's)")
    parser.add_argument("--stride", type=positive_int, default=None,
                        help="window stride in tokens of --search window (default 1)")
    parser.add_argument("--min-tokens", type=positive_int, default=None,
                        help=f"shortest span of --search ordered/spans, in tokens (default "
                             f"{MIN_TOKENS})")
    parser.add_argument("--method", choices=METHODS, default="similarity",
                        help="similarity (default): the learned segment space; attention: where "
                             "the mask transformer's motion tokens look")
    parser.add_argument("--out", default=None,
                        help=f"save the similarity map, an image file ending in "
                             f"{', '.join('.' + f for f in MAP_FORMATS)} (e.g. map.png)")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace a file already at --out (a symbolic link there is "
                             "replaced, not written through)")
    args = parser.parse_args(argv)
    motion = npy_argument(parser, "--motion", args.motion)
    if motion.ndim == 3:
        parser.error(f"--motion {args.motion}: holds joints {motion.shape}; pass the raw "
                     "features (t, d) (new_joint_vecs/<id>.npy or *_features.npy)")
    if args.window is not None and args.search not in (None, "window"):
        parser.error(f"--window is for --search window, not --search {args.search}")
    search = args.search or ("ordered" if args.window is None else "window")
    if args.stride is not None and search != "window":  # it would be ignored without a word
        parser.error(f"--stride is for --search window, not --search {search}")
    if args.min_tokens is not None and search == "window":
        parser.error("--min-tokens is for --search ordered or spans, not --search window")
    image_format = _map_format(parser, args.out, args.overwrite) if args.out else None
    model = _load(parser, args.model)
    segments = None if args.segments is None else [s.strip() for s in args.segments.split("#")]
    try:
        model.normalize_motion(motion)  # the checks of a motion, here naming its file
    except SegmoError as error:
        raise SegmoError(f"--motion {args.motion}: {error}") from None
    out = model.ground(args.text, motion, search=args.search, window=args.window,
                       stride=args.stride, min_tokens=args.min_tokens, segments=segments,
                       method=args.method)
    print(out)
    if args.out:
        # matplotlib on use, its file backend chosen before plotting imports pyplot.
        import matplotlib

        matplotlib.use("Agg")
        truth = _true_spans(Path(args.motion), args.text, out.segments)
        if truth is not None:
            print(f"true spans (frames) from the dataset's segments/: {truth}")
        ax = plot_similarity_map(out, truth=truth)
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        remove_stale_temporaries(args.out)  # of a run writing this map that was killed
        with atomic_open(args.out, "wb") as f:  # a killed run leaves no half image
            ax.figure.savefig(f, format=image_format, dpi=120, bbox_inches="tight")
        print(f"similarity map: {args.out}")


def bundle_main(argv: list[str] | None = None) -> None:
    parser = ArgumentParser(
        prog="segmo bundle",
        description="assemble exported stage directories into one SegMo bundle directory")
    parser.add_argument("--tokenizer", required=True,
                        help="exported RVQ-VAE directory: the one the mask and residual stages "
                             "were trained with (checked where they record its digest)")
    parser.add_argument("--mask", required=True, help="exported mask transformer directory")
    parser.add_argument("--residual", default=None, help="exported residual transformer")
    parser.add_argument("--length", default=None, help="exported length estimator")
    parser.add_argument("--segmenter", default="rule", help="text-segmenter backend at inference")
    parser.add_argument("--guidance", type=finite_float, default=None,
                        help=f"default CFG scale of the base tokens (default "
                             f"{SamplingOptions.guidance_scale:g}, KIT {KIT_GUIDANCE_SCALE:g})")
    parser.add_argument("--residual-guidance", type=finite_float, default=None,
                        help=f"default CFG scale of the residual tokens (default "
                             f"{SamplingOptions.residual_guidance_scale:g})")
    parser.add_argument("--steps", type=positive_int, default=None,
                        help=f"default masked-decoding steps (default {SamplingOptions.steps})")
    parser.add_argument("--residual-guided-layers", type=non_negative_int, default=None,
                        help="default number of guided residual layers, from the first "
                             "(default: all)")
    parser.add_argument("--guidance-mode", choices=("cfg", "sink_ctrl"), default=None,
                        help="default base-token guidance (default cfg)")
    parser.add_argument("--unconditional", choices=("none", "local"), default=None,
                        help="what guidance's unconditional rows keep: none, or local (segments "
                             "and words; models trained with local_uncond_prob)")
    parser.add_argument("--word-text", choices=get_args(WordText), default=None,
                        help="what the word keys of a words model read: the caption (default) or "
                             "its text segments joined in execution order")
    parser.add_argument("--remasking", choices=get_args(Remasking), default=None,
                        help="which tokens each decoding step masks again: the least confident "
                             "of the motion (default, MoMask) or of each segment (models with "
                             "segment timing)")
    parser.add_argument("--segment-guidance", type=non_negative_float, default=None,
                        help="default per-segment guidance weight w (0 = off, the default; mask "
                             "transformers trained with segment_drop_prob)")
    parser.add_argument("--choice-temperature", type=non_negative_float, default=None,
                        help="default MaskGIT choice temperature: Gumbel noise on the confidence "
                             "that picks the tokens each decoding step masks again (0 = off, "
                             "the default, MoMask's choice)")
    parser.add_argument("--sink-ratio", type=finite_float, default=None,
                        help="the mask transformer's measured SinkRatio, for sink_ctrl "
                             "(tools/attention_report.py; default 0)")
    for name in ("ctrl_lambda", "ctrl_k_base", "ctrl_alpha"):
        parser.add_argument("--" + name.replace("_", "-"), type=finite_float, default=None,
                            help=f"sink_ctrl's {name[5:]} (default "
                                 f"{getattr(SamplingOptions, name):g}, MLA-Gen's)")
    parser.add_argument("--metrics", default=None,
                        help="metrics.json of `segmo evaluate` (or its folder) for the model card")
    parser.add_argument("--push-to-hub", metavar="REPO_ID", default=None,
                        help="also upload the bundle to this Hugging Face hub repository")
    parser.add_argument("--out", type=replaced_folder, required=True,
                        help="bundle directory to write")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace a folder that holds something else than this bundle")
    args = parser.parse_args(argv)
    _check_output_dir(parser, "--out", args.out)
    for flag in ("tokenizer", "mask", "residual", "length"):
        value = getattr(args, flag)
        if value is not None and not Path(value).is_dir() and not is_hub_id(value):
            parser.error(f"--{flag} {value}: no such directory (a model made by `segmo export`, "
                         "or a hub id)")
    metrics = None
    if args.metrics is not None:
        try:
            metrics = read_metrics(args.metrics)
        except (FileNotFoundError, OSError) as error:
            parser.error(f"--metrics {args.metrics}: {error.strerror or error}")
    if args.segmenter not in TEXT_SEGMENTERS:
        parser.error(f"--segmenter {args.segmenter!r}: choose {', '.join(TEXT_SEGMENTERS)}")
    model = SegMo.from_stages(args.tokenizer, args.mask, args.residual, args.length,
                              segmenter=args.segmenter)
    # The sampling defaults the bundle records: SegMoConfig field ← argument.
    for field, argument in (("guidance_scale", "guidance"),
                            ("residual_guidance_scale", "residual_guidance"), ("steps", "steps"),
                            ("residual_guided_layers", "residual_guided_layers"),
                            ("guidance", "guidance_mode"), ("sink_ratio", "sink_ratio"),
                            ("unconditional", "unconditional"), ("word_text", "word_text"),
                            ("remasking", "remasking"), ("ctrl_lambda", "ctrl_lambda"),
                            ("segment_guidance", "segment_guidance"),
                            ("choice_temperature", "choice_temperature"),
                            ("ctrl_k_base", "ctrl_k_base"), ("ctrl_alpha", "ctrl_alpha")):
        if getattr(args, argument) is not None:
            setattr(model.config, field, getattr(args, argument))
    print(model.save_pretrained(args.out, metrics=metrics, push_to_hub=args.push_to_hub is not None,
                                repo_id=args.push_to_hub, overwrite=args.overwrite))
