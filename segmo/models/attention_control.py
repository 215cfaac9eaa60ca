"""Changing what the transformers' motion queries attend to while they generate: the
mechanism of SALAD's zero-shot edits (after Prompt-to-Prompt), which
`segmo.generation.attention_edit` builds on.

    control = AttentionControl({"mask": mask_model, "residual": residual_model})
    with control.storing():
        generate_tokens(...)                 # the source: every pass' weights kept
    with control.editing(edit):
        generate_tokens(...)                 # weights = edit(site, weights, stored) per block

While a control is open, every block's attention over motion queries is computed as the
CPU path's two matmuls (`segmo.models.cpu_inference.attention_weights`, then the weights
times the values), so that a weight can be changed between the two, and with the same
arithmetic as that path: a control whose edit changes nothing gives the tokens of a plain
CPU generation bit for bit. Masked decoding then runs one pass per decoding step
(`segmo.models.attention_recorder.is_recorded`), so that `Site.step` is the step.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import torch
from torch import nn

from segmo.models.attention_recorder import observe
from segmo.models.cpu_inference import attention_weights
from segmo.models.text_prefix import prefix_labels
from segmo.models.transformer import Trunk


@dataclass
class Site:
    """Where a block's attention is computed.

    stage: the model's name in the control ("mask", "residual"); step: the pass' index
    among that stage's passes (the decoding step for the mask transformer, the layer − 1
    for the residual one); block: 0 = first; labels: one per key ("sentence", "segment k",
    "word w", then "motion i"); queries: (rows, m) long motion positions of the queries, None
    = every position in order; conditional: how many leading rows carry a condition (the
    guidance batch's conditional rows; the unconditional ones follow).
    """

    stage: str
    step: int
    block: int
    labels: list[str]
    queries: torch.Tensor | None
    conditional: int


@dataclass
class Stored:
    """A stored block of the source: its conditional rows' weights (c, heads, m, keys)
    fp32, their query positions (c, m) (None = all) and valid keys (c, keys)."""

    weights: torch.Tensor
    queries: torch.Tensor | None
    key_valid: torch.Tensor
    labels: list[str]


# edit(site, weights (rows, heads, m, keys) fp32, the source's Stored at that site or None)
Edit = Callable[[Site, torch.Tensor, "Stored | None"], torch.Tensor]


class AttentionControl:
    """Stores or edits the attention of every trunk inside `models` (name → model) while
    one of its contexts is open; nothing is wrapped otherwise."""

    def __init__(self, models: dict[str, nn.Module]) -> None:
        self.models = models
        self.stored: dict[tuple[str, int, int], Stored] = {}

    @contextmanager
    def storing(self) -> Iterator[AttentionControl]:
        """Keep every block's weights (conditional rows) in `self.stored`, replacing
        what an earlier storing kept."""
        self.stored = {}
        with self._wrapped(store=True, edit=None):
            yield self

    @contextmanager
    def editing(self, edit: Edit) -> Iterator[AttentionControl]:
        """Replace every block's weights by `edit(site, weights, stored)`."""
        with self._wrapped(store=False, edit=edit):
            yield self

    @contextmanager
    def _wrapped(self, store: bool, edit: Edit | None) -> Iterator[None]:
        restore: list[tuple[object, str, object]] = []
        counters: dict[str, int] = {}
        state: dict = {"site": None}

        def wrap_trunk(stage: str, trunk: Trunk) -> None:
            original = trunk.forward_motion
            last = len(trunk.blocks) - 1

            def forward_motion(tokens, token_mask, prefix, positions=None):
                mask = prefix.blocks[0].mask
                step = counters.get(stage, 0)
                counters[stage] = step + 1
                labels = [*(prefix.labels or prefix_labels(mask.shape[1] - 1)),
                          *(f"motion {i}" for i in range(tokens.shape[1]))]
                state.update(stage=stage, step=step, labels=labels, positions=positions,
                             conditional=int(prefix.conditional_rows().sum()), last=last)
                try:
                    return original(tokens, token_mask, prefix, positions)
                finally:
                    state["stage"] = None

            # Another context's wrapper (a recording open around an edit) is put back after.
            had = "forward_motion" in trunk.__dict__
            restore.append((trunk, "forward_motion", original if had else None))
            trunk.forward_motion = forward_motion
            observe(trunk, True)
            for index, block in enumerate(trunk.blocks):
                wrap_attention(index, block.attention)

        def wrap_attention(index: int, module: nn.Module) -> None:
            original = module.attend

            def attend(q, k, v, key_valid, dropout=0.0):
                if state.get("stage") is None:
                    return original(q, k, v, key_valid, dropout)
                weights = attention_weights(q, k, key_valid)
                queries = state["positions"] if index == state["last"] else None
                site = Site(state["stage"], state["step"], index, state["labels"], queries,
                            state["conditional"])
                c = site.conditional
                if store:
                    self.stored[(site.stage, site.step, index)] = Stored(
                        weights[:c].clone(), None if queries is None else queries[:c].clone(),
                        key_valid[:c].clone(), site.labels)
                if edit is not None:
                    weights = edit(site, weights, self.stored.get((site.stage, site.step, index)))
                return torch.matmul(weights.to(v.dtype), v)

            had = "attend" in module.__dict__
            restore.append((module, "attend", original if had else None))
            module.attend = attend

        for stage, model in self.models.items():
            if model is None:
                continue
            for module in model.modules():
                if isinstance(module, Trunk):
                    wrap_trunk(stage, module)
        try:
            yield
        finally:
            for obj, name, previous in reversed(restore):
                if name == "forward_motion":
                    observe(obj, False)
                if previous is None:
                    obj.__dict__.pop(name, None)  # the class' method again
                else:
                    setattr(obj, name, previous)
