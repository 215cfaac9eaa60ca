"""Typed outputs of the `SegMo` pipeline, and their export to files.

    out = model.generate(["a person walks forward, then waves"], lengths=[120])
    out.save("runs/gen", formats=("npy", "gif", "bvh"))   # sample_00.npy, ...
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from segmo.errors import SegmoError
from segmo.files import pid_alive
from segmo.generation.sampling import SamplingOptions
from segmo.models.tokenizer import FRAMES_PER_TOKEN
from segmo.motion.bvh import ANIMATION_FPS, check_bvh_fps, write_bvh
from segmo.motion.skeleton import SkeletonSpec
from segmo.motion.skeleton_fit import fit_motion
from segmo.pipeline.inputs import check_span
from segmo.render import save_animation

FORMATS = ("npy", "gif", "bvh")


@dataclass
class GenerationOutput:
    """Motions generated (or edited) from text.

    features: (b, t, d) raw HumanML3D-style features (de-normalised), zero at frames
        ≥ lengths[i]; t = max(lengths).
    joints: (b, t, j, 3) joint positions (metres for t2m, y up), zero at frames ≥ lengths[i].
    tokens: (b, n, q) long motion tokens, n = t // 4; −1 beyond a sample's length.
    lengths: (b,) long, frames of each motion (multiples of 4).
    texts: the b prompts; segments: the text segments each prompt was conditioned on.
    skeleton, fps: what the features describe (for rendering and BVH export).
    """

    features: torch.Tensor
    joints: torch.Tensor
    tokens: torch.Tensor
    lengths: torch.Tensor
    texts: list[str]
    segments: list[list[str]]
    skeleton: SkeletonSpec
    fps: float
    # How the tokens were drawn, so that an attention edit can replay the generation
    # (`SegMo.edit_text`): the sampling options, the generator's state just before the
    # tokens were drawn, the segments' durations given (`generate`'s durations as (b, a)
    # float32 shares, a row of 0 for a text without; None when no text had any) and the
    # precision the passes ran at ("fp32" or "bf16", "auto" resolved on the device). None
    # for motions that were not generated (edits, encodings).
    sampling: SamplingOptions | None = None
    generator_state: torch.Tensor | None = None
    durations: torch.Tensor | None = None
    precision: str | None = None
    # Per sample, the (start, end) frames of each of its segments where known (a
    # composition's parts, `SegMo.compose`); `save` names them in the GIF.
    spans: list[list[tuple[int, int]]] | None = None
    # `weights_fingerprint` of the model that made it: `SegMo.edit` and `edit_text` refuse
    # another model's output (None: made by hand, not checked).
    model: str | None = None

    def __len__(self) -> int:
        return len(self.texts)

    def motion(self, i: int) -> np.ndarray:
        """Features of sample i cropped to its length: (lengths[i], d) float32."""
        return self.features[i, : int(self.lengths[i])].cpu().numpy()

    def motion_joints(self, i: int) -> np.ndarray:
        """Joints of sample i cropped to its length: (lengths[i], j, 3) float32."""
        return self.joints[i, : int(self.lengths[i])].cpu().numpy()

    def save(self, directory: str | Path, formats: Sequence[str] = FORMATS,
             prefix: str = "sample", bvh_fps: float | None = ANIMATION_FPS,
             foot_lock: bool = True, spans: Sequence[Sequence[tuple[int, int]]] | None = None,
             progress: bool = False, fixed_skeleton: bool = True) -> list[Path]:
        """Write each sample as `{prefix}_{i:02d}` files into `directory`.

        npy: `_features.npy` (t, d), `_joints.npy` (t, j, 3), `_tokens.npy` (t // 4, q); gif: a stick-figure
        animation titled with the prompt; bvh: a BVH file of a fixed skeleton fitted to the joints
        (`segmo.motion.skeleton_fit.fit_motion`), at `bvh_fps` frames per second (default
        `segmo.motion.bvh.ANIMATION_FPS`, 60, resampled by slerp with the motion's frames kept;
        None: the motion's own rate, 20 for t2m; `check_bvh_fps` bounds it), with the feet locked while in contact unless
        `foot_lock` is False. With `fixed_skeleton` (default) the joints file and the GIF show that same skeleton, so
        that every file of a sample is one motion (the decoder's joints can stretch a bone;
        `motion_joints` keeps them); False writes the decoder's joints. spans: per sample, a
        (start, end) frame span per text segment (e.g. `SegMo.ground(method="attention")`),
        or None: the GIF names the segment of each frame. progress: progress bars while rendering. A `prompts.json`
        lists texts, segments and lengths (`save_outputs` writes several outputs into one
        directory with one `prompts.json`). Returns the written paths.
        """
        output = self if spans is None else replace(self, spans=spans)
        return save_outputs(directory, {prefix: output}, formats, bvh_fps=bvh_fps,
                            foot_lock=foot_lock, progress=progress, fixed_skeleton=fixed_skeleton)


def check_spans(output: GenerationOutput) -> None:
    """SegmoError naming the sample unless `output.spans` is None or, per sample, None
    (a GIF without segment labels) or one (start, end) span of whole frames in [0, length]
    per text segment (they were dropped from the GIF, or failed with an IndexError,
    without a word)."""
    spans = output.spans
    if spans is None:
        return
    if isinstance(spans, (str, bytes)) or not isinstance(spans, Sequence) \
            or len(spans) != len(output.texts):
        raise SegmoError(f"GenerationOutput.save: spans must be one list of (start, end) frame "
                         f"spans per sample ({len(output.texts)}), got {spans!r:.80}")
    for i, (row, segments) in enumerate(zip(spans, output.segments)):
        if row is None:
            continue
        if isinstance(row, (str, bytes)) or not isinstance(row, Sequence) \
                or len(row) != len(segments):
            raise SegmoError(f"GenerationOutput.save: spans[{i}] must be one (start, end) per "
                             f"segment of sample {i} ({len(segments)}), got {row!r:.80}")
        for span in row:
            check_span(span, f"GenerationOutput.save: spans[{i}]", int(output.lengths[i]))


def save_outputs(directory: str | Path, outputs: Mapping[str, GenerationOutput],
                 formats: Sequence[str] = FORMATS, bvh_fps: float | None = ANIMATION_FPS,
                 foot_lock: bool = True, progress: bool = False,
                 fixed_skeleton: bool = True) -> list[Path]:
    """Write several outputs into one directory, sample i of each as `{prefix}_{i:02d}` files
    (`GenerationOutput.save`, whose options these are; a GIF names the segments of its
    output's `spans`), and one `prompts.json` that lists every motion written, e.g.
    `segmo edit`'s {"source": ..., "edit": ...}. Returns the written paths, each once.

    Nothing is written unless all of it can be: files of the same name that an earlier save
    wrote (its `prompts.json` lists them) are replaced, other files stay, and so do their
    entries in `prompts.json` (`read_prompts`). A file of the same name that no save wrote
    (the user's) is refused before any work.
    """
    unknown = set(formats) - set(FORMATS)
    if unknown:
        raise SegmoError(f"GenerationOutput.save: unknown format(s) {sorted(unknown)}; "
                         f"choose from {FORMATS}")
    for output in outputs.values():  # before any work: a GIF label must not fail halfway
        check_spans(output)
    if bvh_fps is not None:  # before any file is written
        check_bvh_fps(bvh_fps, "GenerationOutput.save: bvh_fps")
    directory = Path(directory)
    for leftover in directory.glob(f"{STAGE_PREFIX}*"):  # of a save that was killed
        pid = leftover.name.removeprefix(STAGE_PREFIX)
        if leftover.is_dir() and pid.isdecimal() and not pid_alive(int(pid)):
            _roll_back(directory, leftover)
            shutil.rmtree(leftover, ignore_errors=True)
    earlier = check_save_target(directory, {prefix: len(output.texts)
                                            for prefix, output in outputs.items()}, formats)
    created = not directory.exists()
    directory.mkdir(parents=True, exist_ok=True)
    # Everything is rendered into a folder of its own first, and only moved beside what the
    # directory holds once all of it is written: a sample that fails (a GIF that cannot be
    # drawn, a full disk) leaves the directory as it was.
    stage = directory / f"{STAGE_PREFIX}{os.getpid()}"
    shutil.rmtree(stage, ignore_errors=True)
    stage.mkdir()
    written: list[Path] = []
    index = []
    try:
        for prefix, output in outputs.items():
            for i, text in enumerate(output.texts):
                stem = stage / f"{prefix}_{i:02d}"
                first = len(written)
                features, joints = output.motion(i), output.motion_joints(i)
                fit = None
                if fixed_skeleton or "bvh" in formats:
                    fit = fit_motion(joints, output.skeleton, foot_lock=foot_lock)
                    if fixed_skeleton:
                        joints = fit.joints.astype(np.float32)
                if "npy" in formats:
                    n = int(output.lengths[i]) // FRAMES_PER_TOKEN
                    tokens = output.tokens[i, :n].cpu().numpy().astype(np.int64)
                    for suffix, array in (("features", features.astype(np.float32)),
                                          ("joints", joints.astype(np.float32)), ("tokens", tokens)):
                        path = Path(f"{stem}_{suffix}.npy")
                        np.save(path, array)
                        written.append(path)
                if "gif" in formats:
                    labels = None if output.spans is None or output.spans[i] is None else [
                        (seg, int(s), int(e)) for seg, (s, e) in zip(output.segments[i],
                                                                     output.spans[i])]
                    written.append(save_animation(joints, f"{stem}.gif", skeleton=output.skeleton,
                                                  title=text, fps=output.fps, segments=labels,
                                                  progress=progress))
                if "bvh" in formats:
                    written.append(write_bvh(fit, f"{stem}.bvh", output.skeleton, fps=output.fps,
                                             target_fps=bvh_fps))
                index.append({"file": stem.name, "text": text, "segments": output.segments[i],
                              "frames": int(output.lengths[i]),
                              "files": [path.name for path in written[first:]]})
        # An earlier save's entries stay listed, except those of the motions written now,
        # whose earlier files of other formats stay listed under the new entry. The list
        # moves in first, so that every file a save moves in is listed even if the save is
        # killed halfway.
        replaced = {entry["file"]: entry for entry in earlier}
        for entry in index:
            if entry["file"] in replaced:
                kept = {name for name in owned_files(replaced[entry["file"]])
                        if (directory / name).exists()}
                entry["files"] = sorted(kept | set(entry["files"]))
        index = [entry for entry in earlier if entry["file"] not in
                 {new_entry["file"] for new_entry in index}] + index
        listing = stage / "prompts.json"
        listing.write_text(json.dumps(index, indent=2) + "\n", encoding="utf-8")
        written.append(listing)
        _move_in([listing, *written[:-1]], directory, stage)
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        if created:  # and nothing else was written into it meanwhile (another save's files)
            with contextlib.suppress(OSError):
                directory.rmdir()
        raise
    shutil.rmtree(stage, ignore_errors=True)
    return [directory / path.name for path in written]


SUFFIXES = {"npy": ("_features.npy", "_joints.npy", "_tokens.npy"), "gif": (".gif",),
            "bvh": (".bvh",)}  # the files of one motion, by format


def owned_files(entry: dict) -> set[str]:
    """The names of the files a prompts.json entry says its save wrote: its "files"; an
    entry of a save before segmo listed them (only "file", the motion) owns every file of
    its motion's name."""
    files = entry.get("files")
    if isinstance(files, list):
        return {name for name in files if isinstance(name, str)}
    return {f"{entry['file']}{suffix}" for suffixes in SUFFIXES.values() for suffix in suffixes}


def check_save_target(directory: str | Path, counts: Mapping[str, int],
                      formats: Sequence[str]) -> list[dict]:
    """What `save_outputs` checks before any work, for `counts[prefix]` motions of each
    prefix in `formats`: SegmoError when a prefix is no part of a file name, when
    `directory` holds a prompts.json that is not segmo's, a folder where a file goes, or a
    file of the same name that no save wrote (no prompts.json entry lists it: the user's).
    Returns the prompts.json entries."""
    for prefix in counts:
        if not isinstance(prefix, str) or any(c in prefix for c in "/\\\0"):
            raise SegmoError(f"GenerationOutput.save: prefix {prefix!r} must be part of a file "
                             "name (no '/', '\\' or NUL): choose the folder with `directory`")
    directory = Path(directory)
    earlier = read_prompts(directory)
    names = [f"{prefix}_{i:02d}{suffix}" for prefix, count in counts.items()
             for i in range(count) for kind in formats for suffix in SUFFIXES[kind]]
    blocked = [name for name in ["prompts.json", *names] if (directory / name).is_dir()]
    if blocked:
        raise SegmoError(f"{directory / blocked[0]}: a folder where the save writes a file; move "
                         "it away or write elsewhere")
    ours = set().union(*map(owned_files, earlier))
    foreign = [name for name in names if name not in ours
               and ((directory / name).exists() or (directory / name).is_symlink())]
    if foreign:
        raise SegmoError(f"{directory / foreign[0]}: a file that segmo did not write (no "
                         f"prompts.json there lists it); move it away or write elsewhere")
    return earlier


STAGE_PREFIX = ".save.tmp-"  # + the pid of the save writing into it


MOVES = ".moves.json"  # in a stage folder: the names its save moves into the directory


def _move_in(files: list[Path], directory: Path, stage: Path) -> None:
    """Move ``files`` (in ``stage``) into ``directory``, all or none: a file they replace
    is kept in ``stage`` until every move is done, and put back if one fails, or, when the
    save is killed, by the next save (`_roll_back`)."""
    kept: list[tuple[Path, Path]] = []
    moved: list[Path] = []
    (stage / MOVES).write_text(json.dumps([path.name for path in files]), encoding="utf-8")
    try:
        for path in files:
            target = directory / path.name
            if target.exists() or target.is_symlink():
                backup = stage / f".replaced-{path.name}"
                os.replace(target, backup)
                kept.append((backup, target))
            os.replace(path, target)
            moved.append(target)
    except BaseException:
        for target in moved:
            target.unlink(missing_ok=True)
        for backup, target in kept:
            os.replace(backup, target)
        raise


def _roll_back(directory: Path, stage: Path) -> None:
    """Undo the moves of a save killed while moving its files in (`_move_in`): put back
    the files they replaced and remove those they added, so that the directory and its
    prompts.json are the earlier save's again."""
    try:
        names = json.loads((stage / MOVES).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return  # killed before its moves began: nothing in the directory is its
    for name in names if isinstance(names, list) else []:
        if not isinstance(name, str) or Path(name).name != name:
            continue
        backup = stage / f".replaced-{name}"
        with contextlib.suppress(OSError):
            if backup.exists():
                os.replace(backup, directory / name)
            elif not (stage / name).exists():  # moved in, replacing nothing
                (directory / name).unlink(missing_ok=True)


def read_prompts(directory: str | Path) -> list[dict]:
    """The entries of ``directory/prompts.json`` (none when there is none), or one
    `SegmoError` when it is not a list that `save_outputs` wrote: a file of the user's
    that a save would replace."""
    path = Path(directory) / "prompts.json"
    if not path.is_file():
        return []
    try:
        entries = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError) as error:  # ValueError: JSON, UTF-8
        entries = error
    if not (isinstance(entries, list) and all(isinstance(e, dict) and isinstance(e.get("file"), str)
                                              for e in entries)):
        raise SegmoError(f"{path}: not a prompts.json written by segmo (a list of "
                         "{\"file\": ...} entries); move it away or write elsewhere")
    return entries


def weights_fingerprint(modules: Sequence[torch.nn.Module]) -> str:
    """A short digest of `modules`' weights (names and the first 64 values of each tensor):
    which model made an output, in milliseconds, without reading every weight."""
    digest = hashlib.sha256()
    for module in modules:
        for name, tensor in module.state_dict().items():
            digest.update(name.encode())
            digest.update(tensor.detach().reshape(-1)[:64].float().cpu().numpy().tobytes())
    return digest.hexdigest()[:16]


@dataclass
class GroundingOutput:
    """Where each text segment of a query happens in a motion (paper §4.4, Fig. 5).

    text: the query; segments: its a text segments (rows of `similarity`).
    windows: (w, 2) long token spans [start, end) of the candidates (columns): the sliding
        windows of search "window", every span of at least `min_tokens` tokens otherwise.
    similarity: (a, w) float: method "similarity", the cosine similarity in the learned
        segment space; method "attention", the segment's mean share of the segment
        attention over the candidate's tokens (`segmo.pipeline.grounding`).
    best_spans_frames: per segment, the chosen span in frames [start, end) (×4 tokens,
        clipped to num_frames): its best candidate, or its span of the ordered cut;
        best_scores: that span's similarity.
    num_frames: frames of the motion that was grounded.
    search: "ordered", "spans" or "window" (`segmo.pipeline.grounding`).
    method: "similarity" or "attention".
    fps: frames per second of the motion.
    """

    text: str
    segments: list[str]
    windows: torch.Tensor
    similarity: torch.Tensor
    best_spans_frames: list[tuple[int, int]]
    best_scores: list[float]
    num_frames: int
    search: str = "window"
    method: str = "similarity"
    fps: float = 20.0  # frames per second of the motion (the map's time axis)

    def __str__(self) -> str:
        lines = [f"query: {self.text!r} ({self.num_frames} frames)"]
        what = "sim" if self.method == "similarity" else "att"
        for segment, (s, e), score in zip(self.segments, self.best_spans_frames,
                                          self.best_scores):
            lines.append(f"  frames {s:4d}-{e:<4d} {what} {score:+.3f}  {segment}")
        return "\n".join(lines)
