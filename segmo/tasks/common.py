"""Pieces shared by the token-level tasks (mask, residual, length)."""

from __future__ import annotations

from pathlib import Path

import torch
from torch import Tensor

from segmo.errors import SegmoError
from segmo.models.pretrained import read_config
from segmo.models.tokenizer import FRAMES_PER_TOKEN, RVQVAE


def step_schedule(warmup_steps: int, milestones: list[int], gamma: float):
    """Learning-rate factor of an optimiser step: linear warm-up, then ×gamma per milestone."""

    def factor(step: int) -> float:
        warm = min(1.0, (step + 1) / warmup_steps) if warmup_steps > 0 else 1.0
        return warm * gamma ** sum(step >= m for m in milestones)

    return factor


def adamw_with_schedule(parameters, lr: float, weight_decay: float, warmup_steps: int,
                        milestones: list[int], gamma: float, betas=(0.9, 0.99)) -> dict:
    """AdamW with a per-step warm-up + step-decay schedule, in Lightning's format."""
    optimizer = torch.optim.AdamW(parameters, lr=lr, betas=tuple(betas), weight_decay=weight_decay)
    scheduler = torch.optim.lr_scheduler.LambdaLR(
        optimizer, step_schedule(warmup_steps, list(milestones), gamma)
    )
    return {"optimizer": optimizer, "lr_scheduler": {"scheduler": scheduler, "interval": "step"}}


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


def check_text_features(datamodule, text_dim: int, text_encoder: str | None, task: str) -> str | None:
    """Fail early, naming both settings, when the data's cached text features do not fit.

    Returns the encoder name the model is trained with (recorded in the exported model so
    that inference encodes prompts with the same encoder).
    """
    if datamodule is None:
        return text_encoder
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


def token_lengths(lengths: Tensor) -> Tensor:
    """Frame lengths (b,) → token lengths (b,)."""
    return torch.div(lengths, FRAMES_PER_TOKEN, rounding_mode="floor")


def token_mask(lengths: Tensor, n: int) -> Tensor:
    """Frame lengths (b,) → (b, n) bool, True on valid tokens."""
    return torch.arange(n, device=lengths.device) < token_lengths(lengths)[:, None]
