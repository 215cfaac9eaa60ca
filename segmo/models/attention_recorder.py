"""Recording the attention of the transformers' motion queries (MLA-Gen's and SALAD's
analyses; `segmo.evaluation.attention` computes the diagnostics from it).

    with record_attention({"mask": mask_model, "residual": residual_model}) as recording:
        indices = generate_tokens(mask_model, residual_model, ...)
    recording.maps[0].weights        # (rows, heads, queries, keys) float32, post-softmax

While the context is open, every pass of a trunk over motion tokens
(`Trunk.forward_motion`) records, for each block, the attention weights from its motion
queries to every key: the text prefix first (sentence, segment 1..A; later kinds such as
words or memory slots where a model has them), then the motion positions. Only the rows
that carry a condition are kept (the unconditional rows of a guidance batch have their
whole prefix masked out, and are dropped). The prefix's own encoding is not recorded: it
attends to the text alone.

The weights are computed beside the model's own attention call, from the same queries and
keys, in fp32 with the same mask, and the model's call runs unchanged: recording cannot
change an output, works on every attention path (SDPA and the CPU matmul path of
`segmo.models.cpu_inference`), and costs nothing when no recording is open (nothing is
wrapped then). While a recording is open, masked decoding runs every step's pass even where
it could reuse the previous one (`is_recorded`), so that the recording has one pass per
decoding step. Recordings and attention controls nest: one opened inside another puts
back the other's wrappers when it closes.
"""

from __future__ import annotations

import math
import weakref
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field

import torch
from torch import nn

from segmo.models.text_prefix import prefix_labels
from segmo.models.transformer import SelfAttention, Trunk

# The trunks inside an open recording, and how many recordings and controls are open on
# each (they nest: an edit inside a recording).
_RECORDED: weakref.WeakKeyDictionary[nn.Module, int] = weakref.WeakKeyDictionary()


def is_recorded(model: nn.Module) -> bool:
    """Whether a recording (or an attention control, `segmo.models.attention_control`) is
    open on a trunk of `model`."""
    return any(isinstance(m, Trunk) and m in _RECORDED for m in model.modules())


def observe(trunk: Trunk, on: bool) -> None:
    """One more context observing `trunk` (on) or one fewer: while any does, decoding runs
    every pass."""
    count = _RECORDED.get(trunk, 0) + (1 if on else -1)
    if count > 0:
        _RECORDED[trunk] = count
    else:
        _RECORDED.pop(trunk, None)


@dataclass
class AttentionMap:
    """One block of one pass: what its motion queries attended to.

    stage:   the model's name in the recording ("mask", "residual", ...).
    step:    the pass' index among that stage's passes of the recording (for the mask
             transformer the decoding step, for the residual one the layer; a generation
             of several batches continues counting).
    block:   block index (0 = first).
    rows:    (r,) long, the batch rows kept (those with a condition).
    queries: (r, m) long, the motion position of each query.
    weights: (r, heads, m, keys) float32, post-softmax; keys = prefix slots, then motion
             positions 0..n−1.
    key_valid: (r, keys) bool, the keys that could be attended to.
    key_labels: one label per key: "sentence", "segment k" (k from 1), "word w" (w from 0,
             the start token) where the model has word keys, "memory s" where it has
             memory slots, then "motion i".
    """

    stage: str
    step: int
    block: int
    rows: torch.Tensor
    queries: torch.Tensor
    weights: torch.Tensor
    key_valid: torch.Tensor
    key_labels: list[str]

    @property
    def prefix_length(self) -> int:
        """The keys before the motion positions: text slots, then memory slots."""
        return sum(not label.startswith("motion ") for label in self.key_labels)

    @property
    def text_length(self) -> int:
        """The text slots (sentence, segments, words), the first keys."""
        return sum(not label.startswith(("motion ", "memory ")) for label in self.key_labels)


@dataclass
class AttentionRecording:
    """The maps of a recording, in the order the passes ran."""

    maps: list[AttentionMap] = field(default_factory=list)

    def of(self, stage: str) -> list[AttentionMap]:
        return [m for m in self.maps if m.stage == stage]

    def steps(self, stage: str) -> int:
        return 1 + max((m.step for m in self.of(stage)), default=-1)


def _weights(q: torch.Tensor, k: torch.Tensor, key_valid: torch.Tensor) -> torch.Tensor:
    """Post-softmax weights in fp32 (outside the generation's bf16 autocast, if any)."""
    with torch.autocast(q.device.type, enabled=False):
        scores = torch.matmul(q.float(), k.float().transpose(-1, -2)) / math.sqrt(q.shape[-1])
        scores = scores.masked_fill(~key_valid[:, None, None, :], -math.inf)
        return torch.softmax(scores, dim=-1)


class _Pass:
    """The state of the trunk pass being recorded."""

    def __init__(self) -> None:
        self.active = False
        self.stage = ""
        self.step = 0
        self.rows: torch.Tensor | None = None
        self.positions: torch.Tensor | None = None
        self.labels: list[str] = []
        self.last_block = 0


@contextmanager
def record_attention(models: dict[str, nn.Module]) -> Iterator[AttentionRecording]:
    """Record the motion queries' attention of every trunk inside `models` (name → model)
    while the context is open; yields the `AttentionRecording` it fills."""
    recording = AttentionRecording()
    restore: list[tuple[object, str, object]] = []
    state = _Pass()
    counters: dict[str, int] = {}

    def wrap_trunk(stage: str, trunk: Trunk) -> None:
        original = trunk.forward_motion
        blocks = list(trunk.blocks)

        def forward_motion(tokens, token_mask, prefix, positions=None):
            mask = prefix.blocks[0].mask
            state.active, state.stage = True, stage
            state.step = counters.get(stage, 0)
            counters[stage] = state.step + 1
            state.rows = torch.nonzero(prefix.conditional_rows()).flatten()
            state.positions = positions
            state.labels = [*(prefix.labels or prefix_labels(mask.shape[1] - 1)),
                            *(f"motion {i}" for i in range(tokens.shape[1]))]
            state.last_block = len(blocks) - 1
            try:
                return original(tokens, token_mask, prefix, positions)
            finally:
                state.active = False

        # Another context's wrapper (a control or recording open around this one) is put
        # back after.
        had = "forward_motion" in trunk.__dict__
        restore.append((trunk, "forward_motion", original if had else None))
        trunk.forward_motion = forward_motion
        observe(trunk, True)
        for index, block in enumerate(blocks):
            wrap_attention(index, block.attention)

    def wrap_attention(index: int, module: SelfAttention) -> None:
        original = module.attend

        def attend(q, k, v, key_valid, dropout=0.0):
            if state.active and state.rows is not None and len(state.rows):
                rows = state.rows
                if state.positions is not None and index == state.last_block:
                    queries = state.positions[rows]
                else:
                    queries = torch.arange(q.shape[2], device=q.device).expand(len(rows), -1)
                recording.maps.append(AttentionMap(
                    stage=state.stage, step=state.step, block=index, rows=rows.cpu(),
                    queries=queries.cpu(), weights=_weights(q[rows], k[rows], key_valid[rows]).cpu(),
                    key_valid=key_valid[rows].cpu(), key_labels=state.labels))
            return original(q, k, v, key_valid, dropout)

        had = "attend" in module.__dict__
        restore.append((module, "attend", original if had else None))
        module.attend = attend

    for stage, model in models.items():
        for module in model.modules():
            if isinstance(module, Trunk):
                wrap_trunk(stage, module)
    try:
        yield recording
    finally:
        for obj, name, previous in reversed(restore):
            if name == "forward_motion":
                observe(obj, False)
            if previous is None:
                obj.__dict__.pop(name, None)  # the class' method again
            else:
                setattr(obj, name, previous)
