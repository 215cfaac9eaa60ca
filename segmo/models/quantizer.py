"""Residual vector quantizer with EMA codebooks (spec §3).

Each of the `num_quantizers` layers quantizes what the previous layers left over, so the
sum of the chosen codes approximates the encoder output ever more closely. Codebooks are
not learnt by gradient descent but as exponential moving averages of the vectors assigned
to them, and codes nobody uses are re-seeded from encoder outputs.

Every piece of state (codebooks, EMA statistics, the per-layer "initialised" flags) is a
registered buffer: the reference code kept it in plain attributes, so resuming from a
checkpoint re-initialised the codebooks from scratch.

Under DDP (`torch.distributed` initialised) the statistics are all-reduced, and the random
choices (dropout depth, codebook initialisation, dead-code replacement) are made on rank 0
and broadcast, so that every rank keeps bit-identical codebooks.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn


def _distributed() -> bool:
    return torch.distributed.is_available() and torch.distributed.is_initialized()


def _all_reduce_sum(tensor: Tensor) -> Tensor:
    if _distributed():
        torch.distributed.all_reduce(tensor)
    return tensor


def _broadcast_from_rank0(tensor: Tensor) -> Tensor:
    if _distributed():
        torch.distributed.broadcast(tensor, src=0)
    return tensor


@dataclass
class QuantizerOutput:
    """What `ResidualQuantizer.forward` returns.

    quantized: (b, n, c) sum of the kept layers' codes, with straight-through gradients
        to the input.
    indices: (b, n, q) long; −1 for layers dropped by quantizer dropout.
    commitment_loss: () MSE between each kept layer's input and its detached codes,
        averaged over kept layers.
    perplexity: (q,) exp(entropy) of each layer's code histogram over the valid vectors
        of the batch (of all ranks in training); NaN for dropped layers.
    code_usage: (q,) fraction of each layer's codes used in the batch; NaN if dropped.
    """

    quantized: Tensor
    indices: Tensor
    commitment_loss: Tensor
    perplexity: Tensor
    code_usage: Tensor


class ResidualQuantizer(nn.Module):
    """`num_quantizers` EMA codebooks of `codebook_size` codes of dimension `code_dim`.

    Args:
        ema_decay: decay of the codebook moving averages.
        dead_code_threshold: a code whose EMA count falls below this is re-seeded with a
            random encoder output of the current batch.
        quantizer_dropout: probability that a training batch keeps only layers 0..k,
            with k uniform in [0, num_quantizers).
    """

    def __init__(
        self,
        num_quantizers: int,
        codebook_size: int,
        code_dim: int,
        ema_decay: float = 0.99,
        dead_code_threshold: float = 1.0,
        quantizer_dropout: float = 0.2,
        eps: float = 1e-5,
    ) -> None:
        super().__init__()
        if num_quantizers < 1 or codebook_size < 1 or code_dim < 1:
            raise ValueError(
                f"ResidualQuantizer: num_quantizers={num_quantizers}, codebook_size={codebook_size}"
                f" and code_dim={code_dim} must all be positive"
            )
        if not 0.0 <= quantizer_dropout <= 1.0:
            raise ValueError(f"ResidualQuantizer: quantizer_dropout={quantizer_dropout} not in [0, 1]")
        self.num_quantizers = num_quantizers
        self.codebook_size = codebook_size
        self.code_dim = code_dim
        self.ema_decay = ema_decay
        self.dead_code_threshold = dead_code_threshold
        self.quantizer_dropout = quantizer_dropout
        self.eps = eps
        q, k, c = num_quantizers, codebook_size, code_dim
        # fp32 whatever the module's dtype: EMA updates of 0.01 * x lose too much in half.
        self.register_buffer("codebooks", torch.zeros(q, k, c))
        self.register_buffer("ema_counts", torch.zeros(q, k))
        self.register_buffer("ema_sums", torch.zeros(q, k, c))
        # Per layer, because quantizer dropout may keep a deep layer out of the first batch.
        self.register_buffer("initialised", torch.zeros(q, dtype=torch.bool))

    def _apply(self, fn, recurse=True):
        # Keep the codebook state in fp32 when the module is cast with .half()/.to(dtype).
        super()._apply(fn, recurse)
        for name in ("codebooks", "ema_counts", "ema_sums"):
            buffer = self._buffers[name]
            if buffer.is_floating_point() and buffer.dtype != torch.float32:
                self._buffers[name] = buffer.float()
        return self

    # -- lookups ---------------------------------------------------------------------------

    def nearest(self, layer: int, x: Tensor) -> Tensor:
        """Index of the nearest code of `layer` for each row of x (m, c) -> (m,) long."""
        codebook = self.codebooks[layer]
        x = x.float()
        distances = (
            x.pow(2).sum(1, keepdim=True) - 2 * x @ codebook.t() + codebook.pow(2).sum(1)[None]
        )
        return distances.argmin(dim=1)

    def codes(self, indices: Tensor) -> Tensor:
        """Sum of the codes of indices (b, n, q') -> (b, n, c) fp32, q' ≤ q; −1 adds zero."""
        if indices.shape[-1] > self.num_quantizers:
            raise ValueError(
                f"ResidualQuantizer.codes: indices have {indices.shape[-1]} layers, "
                f"the quantizer only {self.num_quantizers}"
            )
        if indices.min() < -1 or indices.max() >= self.codebook_size:
            raise ValueError(
                f"ResidualQuantizer.codes: indices must lie in [-1, {self.codebook_size}), "
                f"got [{int(indices.min())}, {int(indices.max())}]"
            )
        out = indices.new_zeros(*indices.shape[:-1], self.code_dim, dtype=torch.float32)
        for layer in range(indices.shape[-1]):
            index = indices[..., layer]
            kept = (index >= 0).unsqueeze(-1)
            out = out + self.codebooks[layer][index.clamp(min=0)] * kept
        return out

    # -- training-time state updates -------------------------------------------------------

    def _random_rows(self, x: Tensor, count: int, generator: torch.Generator | None) -> Tensor:
        """`count` rows of x (m, c) drawn with replacement, chosen on rank 0."""
        picks = torch.randint(len(x), (count,), generator=generator, device="cpu")
        return x[picks.to(x.device)]

    @torch.no_grad()
    def _initialise(self, layer: int, x: Tensor, generator: torch.Generator | None) -> None:
        codebook = self._random_rows(x, self.codebook_size, generator)
        self.codebooks[layer] = _broadcast_from_rank0(codebook.contiguous())
        self.ema_sums[layer] = self.codebooks[layer]
        self.ema_counts[layer] = 1.0
        self.initialised[layer] = True

    @torch.no_grad()
    def _update(self, layer: int, x: Tensor, index: Tensor, generator: torch.Generator | None) -> Tensor:
        """EMA update of one layer from x (m, c) fp32 and its codes (m,); returns counts (k,)."""
        one_hot = F.one_hot(index, self.codebook_size).to(x.dtype)  # (m, k)
        counts = _all_reduce_sum(one_hot.sum(0))
        sums = _all_reduce_sum(one_hot.t() @ x)  # (k, c)
        decay = self.ema_decay
        self.ema_counts[layer].mul_(decay).add_(counts, alpha=1 - decay)
        self.ema_sums[layer].mul_(decay).add_(sums, alpha=1 - decay)
        # Laplace smoothing keeps rarely used codes from dividing by ~0.
        total = self.ema_counts[layer].sum()
        smoothed = (self.ema_counts[layer] + self.eps) / (total + self.codebook_size * self.eps) * total
        self.codebooks[layer] = self.ema_sums[layer] / smoothed[:, None]

        dead = self.ema_counts[layer] < self.dead_code_threshold  # identical on every rank
        if dead.any():
            replacement = _broadcast_from_rank0(self._random_rows(x, int(dead.sum()), generator))
            self.codebooks[layer][dead] = replacement
            # Counts at the threshold keep the code alive for as long as anything uses it.
            self.ema_counts[layer][dead] = self.dead_code_threshold
            self.ema_sums[layer][dead] = replacement * self.dead_code_threshold
        return counts

    def _dropout_depth(self, generator: torch.Generator | None, device: torch.device) -> int:
        """Number of layers to keep for this batch, the same on every rank."""
        draw = torch.rand((), generator=generator, device="cpu")
        depth = torch.randint(1, self.num_quantizers + 1, (), generator=generator, device="cpu")
        keep = torch.where(draw < self.quantizer_dropout, depth, self.num_quantizers)
        if _distributed():
            # gloo only moves CPU tensors, nccl only CUDA ones: use the codebook's device.
            keep = _broadcast_from_rank0(keep.to(device))
        return int(keep)

    # -- forward ---------------------------------------------------------------------------

    def forward(
        self,
        x: Tensor,
        mask: Tensor | None = None,
        generator: torch.Generator | None = None,
    ) -> QuantizerOutput:
        """Quantize x (b, n, c).

        mask (b, n) bool, True = valid: only valid vectors feed the codebook statistics
        and the commitment loss. In training mode the codebooks are updated (and
        initialised on first use), and quantizer dropout applies. `generator` (CPU) drives
        the random choices; on rank 0 only under DDP.
        """
        b, n, c = x.shape
        if c != self.code_dim:
            raise ValueError(f"ResidualQuantizer: input has {c} channels, code_dim is {self.code_dim}")
        if mask is None:
            mask = torch.ones(b, n, dtype=torch.bool, device=x.device)
        q = self.num_quantizers
        keep = q
        if self.training and self.quantizer_dropout > 0:
            keep = self._dropout_depth(generator, self.codebooks.device)

        with torch.autocast(device_type=x.device.type, enabled=False):
            x32 = x.float()
            residual = x32.reshape(b * n, c)
            valid = mask.reshape(b * n)
            indices = torch.full((b * n, q), -1, dtype=torch.long, device=x.device)
            codes_sum = torch.zeros_like(residual)
            losses = []
            perplexity = torch.full((q,), float("nan"), device=x.device)
            usage = torch.full((q,), float("nan"), device=x.device)
            for layer in range(keep):
                if self.training and not bool(self.initialised[layer]):
                    self._initialise(layer, residual.detach()[valid], generator)
                index = self.nearest(layer, residual.detach())
                # Gathered (a copy) before the EMA step, so the codes are the ones chosen.
                codes = self.codebooks[layer][index]
                if self.training:
                    counts = self._update(layer, residual.detach()[valid], index[valid], generator)
                else:
                    # Local statistics only: evaluation may run on one rank alone.
                    counts = torch.bincount(index[valid], minlength=self.codebook_size).float()
                losses.append(F.mse_loss(residual[valid], codes[valid]))
                probs = counts / counts.sum().clamp(min=1)
                perplexity[layer] = torch.exp(-(probs * torch.log(probs + 1e-10)).sum())
                usage[layer] = (counts > 0).float().mean()
                indices[:, layer] = index
                codes_sum = codes_sum + codes
                # The next layer quantizes what is left; codes are constants (EMA-learnt).
                residual = residual - codes
            # One straight-through estimator for the whole stack: the decoder's gradient
            # reaches the encoder output once, not once per layer.
            quantized = x32 + (codes_sum.reshape(b, n, c) - x32).detach()
        return QuantizerOutput(
            quantized=quantized.to(x.dtype),
            indices=indices.reshape(b, n, q),
            commitment_loss=torch.stack(losses).mean(),
            perplexity=perplexity,
            code_usage=usage,
        )
