"""Faster CPU inference for the transformers: kernels swapped into a built model.

    model = use_cpu_kernels(MaskTransformer.from_pretrained("models/mask"))

`segmo.models.transformer` is written as plain PyTorch (`F.linear`, SDPA). For inference
on a CPU two of its pieces have faster equivalents, and `use_cpu_kernels` swaps them in
place (same parameters, same state-dict keys; `SegMo` does it for its transformers):

- Every `Linear` becomes a `PackedLinear`, which calls oneDNN directly where
  `segmo.cpu` found the path: fp32 CPU matmuls otherwise go to MKL, which runs AVX2
  kernels on AMD CPUs while oneDNN uses AVX-512 wherever the CPU has it (~2× faster on
  this project's AMD machines); under bf16 autocast oneDNN fuses bias and GELU (~8 % of a
  pass over autocast's `addmm` + GELU); and the weights are handed over once, pre-packed
  in oneDNN's blocked layout (bit-identical results, ~20 % faster matmuls in bf16, ~15 %
  in fp32; `tools/bench_generate.py`). Same arithmetic with fp32 accumulation: fp32
  results agree with `F.linear` to ~1e-6. These are private ops that refuse what a CPU
  cannot do (bf16 needs AVX512BW/VL/DQ or AVX-NE-CONVERT), so each path runs only where
  `segmo.cpu` found it, and a layer with gradients, off the CPU or without the path is
  exactly `Linear`.
- The residual transformer's tied output projection goes through oneDNN's unpacked fp32
  linear, for the same reason.
- Attention becomes two matmuls instead of SDPA's fused kernel: at this project's lengths
  (≤ ~60 keys) PyTorch's CPU flash kernel spends its time on per-block overhead, not
  arithmetic (a bf16 guidance batch of 64 rows, 6 heads, 49 queries, 55 keys takes
  4.0 ms per call against 1.4 ms here, ~10 ms per generated motion). The softmax runs in
  fp32 (bf16 softmax is 3× slower on CPU). With gradients, dropout, off the CPU or for
  long sequences it is SDPA.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from segmo import cpu
from segmo.models.residual_transformer import ResidualTransformer
from segmo.models.transformer import Linear, SelfAttention, attention

_MKLDNN = getattr(torch.ops, "mkldnn", None)
_ONEDNN_LINEAR = getattr(_MKLDNN, "_linear_pointwise", None)
_ONEDNN_PACK = getattr(_MKLDNN, "_reorder_linear_weight", None)
# Rows the packed layout is tuned for (a batch-32 guidance batch); any row count works.
_PACK_ROWS = 3136
_MATMUL_ATTENTION_MAX_KEYS = 256


def onednn_mode(x: torch.Tensor, weight: torch.Tensor) -> str | None:
    """"fp32" or "bf16" when a linear layer may call oneDNN directly on `x`, else None."""
    if (_ONEDNN_LINEAR is None or _ONEDNN_PACK is None or x.device.type != "cpu"
            or weight.dtype != torch.float32 or not torch.backends.mkldnn.is_available()):
        return None
    if torch.is_grad_enabled() and (x.requires_grad or weight.requires_grad):
        return None
    if not cpu.onednn_linear():
        return None
    if torch.is_autocast_enabled("cpu"):
        bf16 = torch.get_autocast_dtype("cpu") == torch.bfloat16 and cpu.onednn_bf16()
        return "bf16" if bf16 else None
    return "fp32" if x.dtype == torch.float32 else None


def linear(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None = None
           ) -> torch.Tensor:
    """`F.linear`, through oneDNN in fp32 CPU inference (for weights that change per call,
    such as the residual transformer's tied output projection, so not packed)."""
    if onednn_mode(x, weight) == "fp32":
        return _ONEDNN_LINEAR(x, weight, bias, "none", [], "")
    return F.linear(x, weight, bias)


class PackedLinear(Linear):
    """`Linear` computed by oneDNN with its weights converted and packed once per precision,
    and packed again whenever the parameters change (an in-place update, an optimizer step,
    `load_state_dict`: anything that moves autograd's version counter); `Linear` itself
    wherever `onednn_mode` says no. A write through ``param.data`` does not move that
    counter, so the old packing would stay: write through the parameter under
    ``torch.no_grad()`` instead, or clear ``_packed``."""

    def __init__(self, in_features: int, out_features: int, activation: str = "none") -> None:
        super().__init__(in_features, out_features, activation)
        self._packed: dict[str, tuple] = {}  # mode → (key, weight, bias); never saved

    @classmethod
    def from_linear(cls, layer: Linear) -> PackedLinear:
        """A PackedLinear computing with `layer`'s own parameters."""
        packed = cls(layer.in_features, layer.out_features, layer.activation)
        packed.weight, packed.bias = layer.weight, layer.bias
        return packed.train(layer.training)

    def __getstate__(self) -> dict:
        state = super().__getstate__()
        state["_packed"] = {}  # oneDNN's opaque tensors neither pickle nor deep-copy
        return state

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        mode = onednn_mode(x, self.weight)
        if mode is None:
            return super().forward(x)
        dtype = torch.bfloat16 if mode == "bf16" else torch.float32
        key = (self.weight.data_ptr(), self.weight._version, self.bias._version)
        cached = self._packed.get(mode)
        if cached is None or cached[0] != key:
            weight = _ONEDNN_PACK(self.weight.detach().to(dtype), _PACK_ROWS)
            cached = self._packed[mode] = (key, weight, self.bias.detach().to(dtype))
        _, weight, bias = cached
        algorithm = "none" if self.activation == "gelu" else ""  # "none": exact (erf) GELU
        return _ONEDNN_LINEAR(x.to(dtype), weight, bias, self.activation, [], algorithm)


def matmul_attention(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor,
                     key_valid: torch.Tensor, dropout: float = 0.0) -> torch.Tensor:
    """`segmo.models.transformer.attention` computed with two matmuls in CPU inference (the
    module docstring says why); the same shapes and masking."""
    grad = torch.is_grad_enabled() and (q.requires_grad or k.requires_grad or v.requires_grad)
    if (q.device.type != "cpu" or dropout > 0.0 or grad
            or k.shape[2] > _MATMUL_ATTENTION_MAX_KEYS):
        return attention(q, k, v, key_valid, dropout)
    return torch.matmul(attention_weights(q, k, key_valid).to(v.dtype), v)


def attention_weights(q: torch.Tensor, k: torch.Tensor, key_valid: torch.Tensor) -> torch.Tensor:
    """The post-softmax weights of `matmul_attention`, fp32 (b, heads, l, m): what its
    second matmul multiplies the values by (`segmo.models.attention_control` edits them)."""
    mask = key_valid[:, None, None, :]
    bias = torch.zeros(mask.shape, dtype=torch.float32, device=q.device).masked_fill(~mask, -math.inf)
    scores = torch.matmul(q, k.transpose(-1, -2)).float()  # a new fp32 tensor: edit in place
    scores.mul_(q.shape[-1] ** -0.5).add_(bias)  # (a broadcast masked_fill_ is 6× slower)
    return torch.softmax(scores, dim=-1)


def use_cpu_kernels(model: nn.Module) -> nn.Module:
    """Swap `PackedLinear` and `matmul_attention` into `model` in place; returns it.

    Parameters, buffers and state-dict keys stay as they are, so the model saves, loads and
    trains as before; calling it again changes nothing."""
    for parent in list(model.modules()):
        for name, child in list(parent.named_children()):
            if isinstance(child, Linear) and not isinstance(child, PackedLinear):
                setattr(parent, name, PackedLinear.from_linear(child))
        if isinstance(parent, SelfAttention):
            parent.attend = matmul_attention
        if isinstance(parent, ResidualTransformer):
            parent.project = linear
    return model
