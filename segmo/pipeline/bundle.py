"""The bundle directory: every stage `SegMo` needs, and `segmo.json` saying how to use them.

    DIR/segmo.json     {"format": 1, "segmo_version", "stages", "text_encoder",
                        "text_segmenter", "skeleton", "fps", "guidance_scale",
                        "residual_guidance_scale", "motion_segmenter", ...}
    DIR/README.md      the model card (`segmo.pipeline.model_card`)
    DIR/tokenizer/     RVQ-VAE model directory (its buffers hold the feature statistics)
    DIR/mask/          mask transformer (+ alignment head)
    DIR/residual/      residual transformer (optional)
    DIR/length/        length estimator (optional)

Each stage directory is a `segmo.models.pretrained` model directory (`segmo export`). A
bundle is read from a folder or a Hugging Face hub id (`segmo.models.hub`). It is written
whole (`segmo.files.replacing_folder`): `SegMo.from_pretrained` loads every stage folder it
finds, so no stage of an earlier bundle may stay behind. A folder that holds anything a
rebuild would delete (such a stage, a file of the user's) is refused without ``overwrite``.
`segmo.json`'s "stages" lists the stage folders written, so that a bundle missing one of
them (a partial copy or download) is refused rather than loaded without it; a bundle of an
earlier segmo, without the list, loads the stages it holds.
"""

from __future__ import annotations

import dataclasses
import json
import math
import numbers
import os
from dataclasses import dataclass
from pathlib import Path
from typing import get_args

import torch

from segmo.errors import SegmoError
from segmo.files import foreign_entries, replacing_folder, write_atomic
from segmo.generation.sampling import SamplingOptions
from segmo.models.hub import (
    FORMAT,
    check_format,
    check_repo_id,
    push_folder,
    resolve,
    segmo_version,
)
from segmo.models.pretrained import (
    CONFIG_FILE,
    WEIGHTS_FILE,
    load_pretrained,
    read_config,
    read_json,
)
from segmo.motion.skeleton import SKELETONS
from segmo.pipeline.model_card import CARD_FILE, model_card
from segmo.segmentation import SegmenterName

BUNDLE_FILE = "segmo.json"
BUNDLE_FORMAT = FORMAT
STAGES = {"tokenizer": "rvq", "mask": "mask", "residual": "residual", "length": "length"}
# The text-segmenter backends a bundle may name (`segmo.text.llm.get_text_segmenter`).
TEXT_SEGMENTERS = ("rule", "openai", "transformers")
KIT_GUIDANCE_SCALE = 2.0  # spec §8: KIT's base-token guidance scale; HumanML3D's is the default


@dataclass
class SegMoConfig:
    """What `segmo.json` records besides the stage directories."""

    text_encoder: str
    skeleton: str = "t2m"
    fps: float = 20.0
    text_segmenter: str = "rule"
    # The defaults of `SamplingOptions` (KIT bundles: KIT_GUIDANCE_SCALE); `SegMo.sampling`.
    guidance_scale: float = SamplingOptions.guidance_scale
    residual_guidance_scale: float = SamplingOptions.residual_guidance_scale
    steps: int = SamplingOptions.steps
    residual_guided_layers: int | None = SamplingOptions.residual_guided_layers
    # Guidance of the base tokens and sink-ctrl's parameters (`SamplingOptions`).
    guidance: str = SamplingOptions.guidance
    ctrl_lambda: float = SamplingOptions.ctrl_lambda
    ctrl_k_base: float = SamplingOptions.ctrl_k_base
    ctrl_alpha: float = SamplingOptions.ctrl_alpha
    sink_ratio: float = SamplingOptions.sink_ratio
    unconditional: str = SamplingOptions.unconditional
    word_text: str = SamplingOptions.word_text
    segment_timing: str = SamplingOptions.segment_timing
    remasking: str = SamplingOptions.remasking
    segment_guidance: float = SamplingOptions.segment_guidance
    choice_temperature: float = SamplingOptions.choice_temperature
    motion_segmenter: str = "uniform"  # spans of `embed_pairs` by default
    format: int = BUNDLE_FORMAT



SAMPLING_FIELDS: tuple[str, ...] = (
    "guidance_scale", "residual_guidance_scale", "steps", "residual_guided_layers", "guidance",
    "ctrl_lambda", "ctrl_k_base", "ctrl_alpha", "sink_ratio", "unconditional", "word_text",
    "segment_timing", "remasking", "segment_guidance", "choice_temperature")


def sampling_fields(config: SegMoConfig) -> dict:
    """The sampling defaults a bundle records (`SegMo.sampling`)."""
    return {name: getattr(config, name) for name in SAMPLING_FIELDS}


def load_stage(directory: str | os.PathLike, kind: str) -> torch.nn.Module:
    """The model of a stage directory (or hub id), which must hold a `kind` model."""
    directory = resolve(directory)
    found = read_config(directory)["kind"]  # FileNotFoundError names the directory
    if found != kind:
        raise SegmoError(f"{directory}: holds a {found!r} model, expected a {kind!r} model")
    return load_pretrained(directory)


def check_tokenizer(stages: dict[str, torch.nn.Module | None], tokenizer: str | os.PathLike) -> None:
    """Refuse a tokenizer (`stages["tokenizer"]`, loaded from `tokenizer`) other than the
    one the mask and residual stages were trained with, where they record its digest: one
    of the same config but other codebooks decodes their tokens into garbage motions."""
    from segmo.data.motion_tokens import tokenizer_digest  # hashes every weight: only when needed

    digest = None
    for name in ("mask", "residual"):
        meta = getattr(stages[name], "meta", None) or {}
        if meta.get("tokenizer_digest") is None:
            continue  # exported before the digest was recorded
        digest = digest or tokenizer_digest(stages["tokenizer"])
        if meta["tokenizer_digest"] != digest:
            raise SegmoError(f"SegMo.from_stages: the {name} stage was trained with the tokenizer "
                             f"{meta.get('tokenizer', '?')} (digest {meta['tokenizer_digest']}), "
                             f"not {tokenizer} (digest {digest}); pass the tokenizer it was "
                             "trained with")


def read_bundle(directory: str | os.PathLike, revision: str | None = None
                ) -> tuple[SegMoConfig, dict[str, torch.nn.Module | None]]:
    """`segmo.json` and the stages of a bundle (a folder or a hub id); one SegmoError
    naming the file when either is not what a bundle holds."""
    directory = resolve(directory, revision)
    path = directory / BUNDLE_FILE
    if not path.is_file():
        hint = (" (it is a single model directory; assemble a bundle with `segmo bundle`)"
                if (directory / "config.json").is_file() else "")
        raise FileNotFoundError(f"{path}: not a SegMo bundle (no {BUNDLE_FILE}){hint}")
    payload = read_json(path)
    check_format(payload, path)
    if "text_encoder" not in payload:
        raise SegmoError(f"{path}: missing key 'text_encoder' (the text encoder's name)")
    known = {f.name for f in dataclasses.fields(SegMoConfig)}
    config = SegMoConfig(**{k: v for k, v in payload.items() if k in known})
    if not isinstance(config.text_encoder, str):
        raise SegmoError(f"{path}: 'text_encoder' must name the text encoder, got "
                         f"{config.text_encoder!r}")
    if not isinstance(config.skeleton, str) or config.skeleton not in SKELETONS:
        raise SegmoError(f"{path}: 'skeleton' must be one of {', '.join(SKELETONS)}, got "
                         f"{config.skeleton!r:.80}")
    fps = config.fps  # the frame rate of the motions, which the GIFs and BVH files play at
    if isinstance(fps, bool) or not isinstance(fps, numbers.Real) or not 1 <= fps <= 1000:
        raise SegmoError(f"{path}: 'fps' must be a frame rate from 1 to 1000, got {fps!r}")
    if config.text_segmenter not in TEXT_SEGMENTERS:
        raise SegmoError(f"{path}: 'text_segmenter' must be one of {', '.join(TEXT_SEGMENTERS)}, "
                         f"got {config.text_segmenter!r}")
    if config.motion_segmenter not in get_args(SegmenterName):
        raise SegmoError(f"{path}: 'motion_segmenter' must be one of "
                         f"{', '.join(get_args(SegmenterName))}, got {config.motion_segmenter!r}")
    for name in ("guidance_scale", "residual_guidance_scale"):
        value = getattr(config, name)
        if isinstance(value, bool) or not isinstance(value, numbers.Real) \
                or not math.isfinite(value):
            raise SegmoError(f"{path}: {name!r} must be a finite number, got {value!r}")
    try:  # the sampling defaults are checked as a generation would use them
        SamplingOptions(**sampling_fields(config))
    except SegmoError as error:
        raise SegmoError(f"{path}: {str(error).removeprefix('SegMo: ')}") from None
    recorded = payload.get("stages", [])  # not recorded by earlier bundles
    if not isinstance(recorded, list) or not all(isinstance(n, str) and n in STAGES
                                                 for n in recorded):
        raise SegmoError(f"{path}: 'stages' must be a list of stage names "
                         f"({', '.join(STAGES)}), got {recorded!r:.80}")
    for name in recorded:  # a partial copy or download does not load without a stage
        if not (directory / name).exists() and not (directory / name).is_symlink():
            raise SegmoError(f"{directory / name}: missing, but {BUNDLE_FILE} lists the {name} "
                             "stage (an incomplete copy or download?)")
    for name in STAGES:  # an optional stage that is there but broken is not left out
        path = directory / name
        if (path.exists() or path.is_symlink()) and not path.is_dir():
            raise SegmoError(f"{path}: the bundle's {name} stage is not a model directory "
                             "(a file, or a broken symbolic link)")
    stages = {name: load_stage(directory / name, kind) if (directory / name).is_dir()
              else None for name, kind in STAGES.items()}
    for name in ("tokenizer", "mask"):
        if stages[name] is None:
            raise FileNotFoundError(f"{directory / name}: the bundle has no {name} stage")
    return config, stages


def write_bundle(directory: str | os.PathLike, config: SegMoConfig,
                 stages: dict[str, torch.nn.Module | None], metrics: dict | None = None,
                 push_to_hub: bool = False, repo_id: str | None = None,
                 private: bool = False, overwrite: bool = False) -> Path:
    """Write every stage given, `segmo.json` and the model card (with `metrics`, a
    `segmo evaluate` metrics.json, when given) to `directory`, replacing it whole; with
    `push_to_hub`, upload the folder to the hub repository `repo_id`. Returns `directory`.

    Without `overwrite`, a non-empty `directory` must be a bundle holding nothing but what
    this one writes (rewriting the same bundle is fine)."""
    if push_to_hub and not repo_id:
        raise SegmoError("save_pretrained: push_to_hub needs repo_id ('owner/name')")
    if push_to_hub:
        check_repo_id(repo_id)
    SamplingOptions(**sampling_fields(config))  # no bundle that could not be loaded back
    directory = Path(directory)
    given = [name for name, module in stages.items() if module is not None]
    if not overwrite:
        check_replaceable(directory, given)
    with replacing_folder(directory) as tmp:
        for name in given:
            stages[name].save_pretrained(tmp / name)
        # A new optional key: an earlier segmo reads the bundle as before (no format bump).
        payload = {**dataclasses.asdict(config), "format": BUNDLE_FORMAT,
                   "segmo_version": segmo_version(), "stages": given}
        write_atomic(tmp / BUNDLE_FILE, json.dumps(payload, indent=2) + "\n")
        write_atomic(tmp / CARD_FILE, model_card(config, stages, metrics))
    if push_to_hub:
        push_folder(directory, repo_id, private=private)
    return directory


def check_replaceable(directory: Path, stages: list[str]) -> None:
    """Refuse a `directory` whose replacement by a bundle of `stages` would delete files:
    one that is not a bundle, or a bundle with other stages or files of the user's."""
    if directory.exists() and not directory.is_dir():
        raise SegmoError(f"save_pretrained: {directory} exists and is not a folder")
    if not directory.is_dir() or not any(directory.iterdir()):
        return
    if not (directory / BUNDLE_FILE).is_file():
        raise SegmoError(f"save_pretrained: {directory} is not empty and holds no {BUNDLE_FILE}; "
                         "pass overwrite=True (--overwrite) to replace it")
    written = [BUNDLE_FILE, CARD_FILE, *(f"{name}/{file}" for name in stages
                                         for file in (CONFIG_FILE, WEIGHTS_FILE))]
    extra = foreign_entries(directory, written)
    if extra:
        raise SegmoError(f"save_pretrained: {directory} holds another bundle and "
                         f"{', '.join(extra)}, which this bundle would delete; pass "
                         "overwrite=True (--overwrite) or choose another folder")
