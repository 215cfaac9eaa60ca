"""Pieces shared by the token-level tasks (mask, residual, length), and `TransformerTask`,
the base of the mask and residual stages."""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path
from typing import Any, Literal

import torch
from torch import Tensor

from segmo.data.humanml3d import MotionDataset
from segmo.data.motion_tokens import MotionTokenCache, update_motion_tokens
from segmo.errors import SegmoError
from segmo.models.pretrained import read_config
from segmo.models.tokenizer import FRAMES_PER_TOKEN, RVQVAE
from segmo.models.transformer import TransformerConfig
from segmo.tasks.base import Task

_DEFAULT = TransformerConfig()  # the model's defaults are the task's
log = logging.getLogger(__name__)


class TransformerTask(Task):
    """What the mask and residual stages share: a frozen tokenizer (an exported directory)
    whose codes the model predicts, a text-conditioned transformer built from the
    `TransformerConfig` arguments below, the text-feature checks at `setup`, and the
    optimiser of `Task`.

    Subclasses take their own arguments and pass the rest on (``**kwargs``); jsonargparse
    follows them, so `segmo fit --help` and every YAML list all arguments flat, as before.
    ``max_segments`` (A) and ``text_tokens`` (word-level conditioning: "words" adds the
    caption's per-word features as prefix keys, `TextPrefix`) come from
    ``data.init_args.max_segments`` and ``data.init_args.text_tokens`` under ``segmo fit``
    (`segmo.training.cli`).

    ``word_attention`` (with words): "prefix", the words as further keys of every block's
    self-attention, or "cross", a gated cross-attention sub-layer over them
    (`TransformerConfig`). ``word_norm`` (with words): "unit" scales each word feature to
    unit length before the projection, "none" keeps the encoder's scale.
    ``memory_slots``: MLA-Gen's learned memory slots, attended by every block (0 = none).
    ``local_uncond_prob``: the share of condition-dropped samples that keep their segments
    (and words) and drop the sentence only, so that guidance can keep the local condition
    in its unconditional branch (`SamplingOptions.unconditional`, MLA-Gen).

    ``motion_tokens``: "cached" (default) encodes every crop the data can draw once, at
    `setup`, into ``DATA/motion_tokens/<key>/`` (`segmo.data.motion_tokens`; built or
    extended by rank 0 under DDP while the others wait) and trains on those tokens;
    "on_the_fly" encodes each batch with the tokenizer at every step, as MoMask does.
    """

    def __init__(
        self,
        tokenizer: str,
        cond_drop_prob: float,
        motion_tokens: Literal["cached", "on_the_fly"] = "cached",
        text_dim: int = _DEFAULT.text_dim,
        text_encoder: str | None = None,
        dim: int = _DEFAULT.dim,
        depth: int = _DEFAULT.depth,
        heads: int = _DEFAULT.heads,
        ff_dim: int = _DEFAULT.ff_dim,
        dropout: float = _DEFAULT.dropout,
        norm_first: bool = _DEFAULT.norm_first,
        max_segments: int = _DEFAULT.max_segments,
        max_tokens: int = _DEFAULT.max_tokens,
        text_tokens: Literal["none", "words"] = "none",
        max_words: int = _DEFAULT.max_words,
        word_attention: Literal["prefix", "cross"] = "prefix",
        word_norm: Literal["none", "unit"] = "none",
        memory_slots: int = _DEFAULT.memory_slots,
        local_uncond_prob: float = 0.0,
        lr: float = 2e-4,
        weight_decay: float = 1e-5,
        warmup_steps: int = 2000,
        milestones: list[int] = [50_000],  # noqa: B006 - jsonargparse needs a plain default
        gamma: float = 0.1,
    ) -> None:
        super().__init__()
        self.save_hyperparameters()
        check_shares(cond_drop_prob=cond_drop_prob, local_uncond_prob=local_uncond_prob)
        self.tokenizer = load_tokenizer(tokenizer)
        # Checkpoints record it absolute: `segmo export` rebuilds the task from any folder.
        self.hparams.tokenizer = str(Path(tokenizer).resolve())

    def keep_local(self, drop: Tensor) -> Tensor | None:
        """(b,) bool: the dropped samples that keep their local condition
        (`local_uncond_prob`), None when the share is 0."""
        if not self.hparams.local_uncond_prob:
            return None
        return drop & (torch.rand(drop.shape, device=drop.device) < self.hparams.local_uncond_prob)

    def transformer_config(self) -> dict:
        """The `TransformerConfig` fields: the task's arguments, the tokenizer's codebook size."""
        names = [f.name for f in dataclasses.fields(TransformerConfig) if f.name != "codebook_size"]
        return {"codebook_size": self.tokenizer.codebook_size, **{k: self.hparams[k] for k in names}}

    def setup(self, stage: str) -> None:
        check_text_features(self)
        check_max_tokens(self.datamodule, self.hparams.max_tokens)
        if self.hparams.motion_tokens == "cached" and self.datamodule is not None:
            attach_motion_tokens(self)

    def check_before_training(self, datamodule: Any) -> None:
        super().check_before_training(datamodule)
        check_max_tokens(datamodule, self.hparams.max_tokens)

    @torch.no_grad()
    def batch_tokens(self, batch: dict) -> Tensor:
        """(b, n, q) long tokens of a batch: its cached ``tokens``, else the tokenizer's
        encoding of its motions."""
        if "tokens" in batch:
            return batch["tokens"]
        self.tokenizer.eval()
        return self.tokenizer.encode(batch["motion"])


def check_shares(**shares: float) -> None:
    """SegmoError naming the first model option given as a share outside [0, 1] (a
    probability: 1.5 would drop every condition without a word)."""
    for name, share in shares.items():
        if not 0.0 <= share <= 1.0:
            raise SegmoError(f"model.init_args.{name}={share}: a share in [0, 1]")


def check_max_tokens(datamodule: Any, max_tokens: int) -> None:
    """The longest motion `datamodule` has set up fits a model of ``max_tokens`` tokens, or
    one `SegmoError` (it failed at the first batch holding one, with a ValueError)."""
    datasets = [ds for ds in getattr(datamodule, "datasets", {}).values()
                if isinstance(ds, MotionDataset) and len(ds)]
    if not datasets:
        return
    frames = max(ds.crop_length(i) for ds in datasets for i in range(len(ds)))
    if frames // FRAMES_PER_TOKEN > max_tokens:
        raise SegmoError(f"model.init_args.max_tokens={max_tokens}: the data's longest motion "
                         f"is {frames // FRAMES_PER_TOKEN} tokens ({frames} frames); give at "
                         "least that")


def attach_motion_tokens(task: TransformerTask) -> None:
    """Build (rank 0) or extend the motion-token cache of the task's tokenizer for the
    DataModule's datasets and attach it to them. Rank 0 writes; every rank waits for it
    (the broadcast is the barrier) and gets its error, if any, so that none hangs."""
    datamodule = task.datamodule
    datasets = [ds for ds in getattr(datamodule, "datasets", {}).values()
                if isinstance(ds, MotionDataset)]
    if not datasets:
        return
    root = datasets[0].root
    folder, error = None, None
    if task.global_rank == 0:
        try:
            summary = update_motion_tokens(root, task.tokenizer, task.hparams.tokenizer, datasets)
            print(f"motion tokens: {summary}", flush=True)  # the progress line of a fit's setup
            folder = str(summary.folder)
        except (SegmoError, OSError) as err:
            error = (f"model.init_args.motion_tokens=cached: {err} (or train with "
                     "--model.init_args.motion_tokens=on_the_fly)")
    strategy = task.trainer.strategy
    folder, error = strategy.broadcast((folder, error), src=0)
    if error is not None:
        raise SegmoError(error)
    cache = MotionTokenCache(folder)
    for ds in datasets:
        ds.motion_tokens = cache


def load_tokenizer(path: str) -> RVQVAE:
    """The frozen, exported RVQ-VAE that turns motions into tokens (spec §1, stage 1)."""
    if not (Path(path) / "config.json").is_file():
        raise SegmoError(
            f"model.init_args.tokenizer={path!r}: not an exported tokenizer directory (no "
            "config.json); train one with "
            "`segmo fit --config configs/rvq/...` and `segmo export CKPT --out DIR`"
        )
    try:
        kind = read_config(path)["kind"]
        if kind != "rvq":
            raise SegmoError(f"holds a {kind!r} model, not an 'rvq' tokenizer")
        tokenizer = RVQVAE.from_pretrained(path)
    except SegmoError as error:  # names the file (and line) at fault
        raise SegmoError(f"model.init_args.tokenizer={path!r}: {error}") from None
    except (OSError, ValueError, KeyError, TypeError, RuntimeError) as error:
        # A damaged directory: invalid config.json, missing or truncated weights.
        raise SegmoError(f"model.init_args.tokenizer={path!r}: cannot load the tokenizer: "
                         f"{type(error).__name__}: {error}") from None
    tokenizer.requires_grad_(False)
    return tokenizer.eval()


def check_text_features(task: Task) -> None:
    """Fail early, naming both settings, when the data's cached text features do not fit
    the task's `text_dim` and `text_encoder`; then set `text_encoder` to the encoder the
    model is trained with (recorded in the exported model so that inference encodes prompts
    with the same encoder)."""
    datamodule, h = task.datamodule, task.hparams
    if datamodule is not None:
        h.text_encoder = _text_encoder(datamodule, h.text_dim, h.text_encoder, type(task).__name__)


def _text_encoder(datamodule, text_dim: int, text_encoder: str | None, task: str) -> str:
    name = getattr(datamodule, "hparams", {}).get("text_features")
    if name is None:
        raise SegmoError(
            f"{task}: the data has no text features; set data.init_args.text_features "
            "(e.g. minilm) and build the cache with `segmo encode-texts`"
        )
    if text_encoder is not None and text_encoder != name:
        raise SegmoError(
            f"{task}: model.init_args.text_encoder={text_encoder!r} but "
            f"data.init_args.text_features={name!r}"
        )
    cache = getattr(datamodule, "text_cache", None)
    if cache is not None and cache.dim != text_dim:
        raise SegmoError(
            f"{task}: model.init_args.text_dim={text_dim} but the cached text features "
            f"({name}) are {cache.dim}-d"
        )
    return name


def text_condition(batch: dict) -> tuple[Tensor, Tensor, Tensor]:
    """sentence (b, text_dim), segments (b, a, text_dim), segment_mask (b, a) bool of a batch."""
    for key in ("sentence", "segment_features", "segment_mask"):
        if key not in batch:
            raise KeyError(f"batch has no {key!r}: the DataModule needs text_features set")
    return batch["sentence"], batch["segment_features"], batch["segment_mask"].bool()


def word_condition(batch: dict, model: Any) -> dict[str, Tensor]:
    """The ``words``/``word_mask`` keyword arguments of `model` for a batch: the batch's
    per-word features where the model conditions on words, nothing otherwise."""
    if model.config.text_tokens == "none":
        return {}
    if "word_features" not in batch:
        raise KeyError("batch has no 'word_features': the transformer conditions on words "
                       "(text_tokens='words'), set data.init_args.text_tokens=words")
    return {"words": batch["word_features"], "word_mask": batch["word_mask"].bool()}


def token_lengths(lengths: Tensor) -> Tensor:
    """Frame lengths (b,) → token lengths (b,)."""
    return torch.div(lengths, FRAMES_PER_TOKEN, rounding_mode="floor")


def token_mask(lengths: Tensor, n: int) -> Tensor:
    """Frame lengths (b,) → (b, n) bool, True on valid tokens."""
    return torch.arange(n, device=lengths.device) < token_lengths(lengths)[:, None]
