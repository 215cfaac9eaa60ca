"""segmo.cpu: what the CPU can do, and generation on CPUs without the fast paths.

The CPUs without AVX-512 are simulated by replacing `segmo.cpu.info` with their answer and
by making the private oneDNN ops refuse bf16 as they do there, so these tests check the
fallback on any host; the comparisons with the fast paths run where the host has them.
"""

from __future__ import annotations

import pytest
import torch

from segmo import cpu
from segmo.generation import SamplingOptions, generate_tokens
from segmo.generation.generate import resolve_precision
from segmo.models import cpu_inference
from segmo.models.cpu_inference import PackedLinear, use_cpu_kernels
from segmo.models.mask_transformer import MaskTransformer, MaskTransformerConfig
from segmo.models.residual_transformer import ResidualTransformer, ResidualTransformerConfig

AVX2_ONLY = cpu.CPUInfo(model="AMD EPYC 7B13 (simulated)", isa="AVX2", onednn_linear=True,
                        onednn_bf16=False, native_bf16=())
AVX512_EMULATED_BF16 = cpu.CPUInfo(model="Cascade Lake (simulated)", isa="AVX512",
                                   onednn_linear=True, onednn_bf16=True, native_bf16=())
NATIVE_BF16 = cpu.CPUInfo(model="Sapphire Rapids (simulated)", isa="AVX512", onednn_linear=True,
                          onednn_bf16=True, native_bf16=("AVX512_BF16", "AMX"))
NO_ONEDNN = cpu.CPUInfo(model="no oneDNN (simulated)", isa="DEFAULT", onednn_linear=False,
                        onednn_bf16=False, native_bf16=())
NEEDS_ONEDNN_BF16 = pytest.mark.skipif(
    not cpu.onednn_bf16(),
    reason="this CPU has no oneDNN bf16 path (needs AVX512BW/VL/DQ or AVX-NE-CONVERT)")
TINY = dict(codebook_size=16, text_dim=8, max_segments=3, max_tokens=12, dim=32, depth=2,
            heads=2, ff_dim=64, dropout=0.1)


def simulate(monkeypatch, answer: cpu.CPUInfo) -> None:
    """Make segmo see `answer`, and make oneDNN refuse what that CPU's oneDNN refuses."""
    monkeypatch.setattr(cpu, "info", lambda: answer)
    real_pack = cpu_inference._ONEDNN_PACK

    def pack(weight, rows):
        if weight.dtype == torch.bfloat16 and not answer.onednn_bf16:
            raise RuntimeError("mkldnn_reorder_linear_weight: bf16 path needs the cpu support "
                               "avx_ne_convert or avx512bw, avx512vl and avx512dq")
        if not answer.onednn_linear:
            raise RuntimeError("simulated: no oneDNN on this CPU")
        return real_pack(weight, rows)

    monkeypatch.setattr(cpu_inference, "_ONEDNN_PACK", pack)


@pytest.fixture(scope="module")
def models():
    torch.manual_seed(0)
    mask = use_cpu_kernels(MaskTransformer(MaskTransformerConfig(**TINY)).eval())
    residual = use_cpu_kernels(
        ResidualTransformer(ResidualTransformerConfig(**TINY, num_quantizers=3)).eval())
    with torch.no_grad():  # sharper logits than the initialisation, as in test_generation
        mask.classifier.weight.mul_(50)
        residual.code_embeddings.mul_(50)
    return mask, residual


def text(b: int, seed: int = 1):
    g = torch.Generator().manual_seed(seed)
    return (torch.randn(b, 8, generator=g), torch.randn(b, 3, 8, generator=g),
            torch.ones(b, 3, dtype=torch.bool))


def generate(models, precision: str, seed: int = 0) -> torch.Tensor:
    mask, residual = models
    return generate_tokens(mask, residual, *text(4), torch.tensor([48, 40, 24, 8]),
                           options=SamplingOptions(steps=5),
                           precision=precision, generator=torch.Generator().manual_seed(seed))


def packed_layers(models) -> set[str]:
    """The modes ("fp32", "bf16") some `Linear` of the models holds pre-packed weights for."""
    return {mode for model in models for m in model.modules()
            if isinstance(m, PackedLinear) for mode in m._packed}


def clear_packed(models) -> None:
    for model in models:
        for m in model.modules():
            if isinstance(m, PackedLinear):
                m._packed.clear()


def test_this_cpu_answers_consistently():
    answer = cpu.info()
    assert cpu.info() is answer  # probed once
    assert answer.model and answer.isa == torch.backends.cpu.get_cpu_capability()
    assert not answer.native_bf16 or answer.onednn_bf16  # native bf16 is used through oneDNN
    assert cpu.native_bf16() == bool(answer.native_bf16)
    line = cpu.describe()
    assert "\n" not in line and answer.model in line and f"torch kernels {answer.isa}" in line
    assert cpu.auto_precision()[0] == ("bf16" if cpu.native_bf16() else "fp32")


@pytest.mark.skipif(getattr(torch.ops.mkldnn, "_reorder_linear_weight", None) is None,
                    reason="this torch has no oneDNN linear ops")
def test_onednn_bf16_is_the_check_oneDNN_makes():
    """The answer is the very check that made bf16 generation crash on AVX2-only CPUs."""
    weight = torch.randn(8, 4).bfloat16()
    if cpu.onednn_bf16():
        torch.ops.mkldnn._reorder_linear_weight(weight, 16)
    else:
        with pytest.raises(RuntimeError, match="bf16 path needs"):
            torch.ops.mkldnn._reorder_linear_weight(weight, 16)


@pytest.mark.parametrize("answer,expected,why", [
    (AVX2_ONLY, "fp32", "no bf16 path in oneDNN"),
    (NO_ONEDNN, "fp32", "no bf16 path in oneDNN"),
    (AVX512_EMULATED_BF16, "fp32", "only emulates bf16"),
    (NATIVE_BF16, "bf16", "native bf16 on this CPU (AVX512_BF16, AMX)"),
])
def test_auto_precision_is_bf16_only_where_native(monkeypatch, answer, expected, why):
    monkeypatch.setattr(cpu, "info", lambda: answer)
    precision, reason = resolve_precision("auto", "cpu")
    assert precision == expected and why in reason
    assert resolve_precision("auto", "cuda")[0] == "fp32"
    assert resolve_precision("fp32", "cpu") == ("fp32", "asked for")
    bf16, reason = resolve_precision("bf16", "cpu")
    assert bf16 == "bf16" and ("reference kernels" in reason) == (not answer.onednn_bf16)
    with pytest.raises(ValueError, match="'auto', 'fp32' or 'bf16'"):
        resolve_precision("fp16", "cpu")


def test_fp32_without_onednn_gives_the_same_tokens(models, monkeypatch):
    """fp32 through F.linear (a CPU without oneDNN's linear) matches the pre-packed oneDNN
    path to ~1e-6 and draws the same tokens; an AVX2-only CPU keeps the oneDNN path."""
    clear_packed(models)
    fast = torch.stack([generate(models, "fp32", seed) for seed in range(4)])
    assert packed_layers(models) == ({"fp32"} if cpu.onednn_linear() else set())
    mask, _ = models
    ids = torch.randint(0, 16, (4, 10), generator=torch.Generator().manual_seed(0))
    token_mask = torch.ones(4, 10, dtype=torch.bool)
    with torch.inference_mode():
        fast_logits = mask(ids, token_mask, *text(4)).logits
    with monkeypatch.context() as patch:
        simulate(patch, AVX2_ONLY)
        assert torch.equal(torch.stack([generate(models, "fp32", s) for s in range(4)]), fast)
    with monkeypatch.context() as patch:
        simulate(patch, NO_ONEDNN)
        clear_packed(models)
        fallback = torch.stack([generate(models, "fp32", seed) for seed in range(4)])
        assert packed_layers(models) == set()  # F.linear all the way
        with torch.inference_mode():
            fallback_logits = mask(ids, token_mask, *text(4)).logits
    torch.testing.assert_close(fallback_logits, fast_logits, rtol=1e-5, atol=1e-5)
    assert torch.equal(fallback, fast)


def test_bf16_on_an_avx2_only_cpu_runs_the_fallback(models, monkeypatch):
    """What crashed before: bf16 generation where oneDNN refuses bf16. It now runs in
    F.linear under autocast (with a warning that it is slow there), reproducibly."""
    simulate(monkeypatch, AVX2_ONLY)
    clear_packed(models)
    with pytest.warns(UserWarning, match="reference kernels"):
        out = generate(models, "bf16")
    assert "bf16" not in packed_layers(models)
    assert out.shape == (4, 12, 3) and bool((out[0] >= 0).all())
    with pytest.warns(UserWarning):
        assert torch.equal(generate(models, "bf16"), out)
    # "auto" is fp32 there: the same tokens as an explicit fp32 request, and no warning.
    assert torch.equal(generate(models, "auto"), generate(models, "fp32"))


@NEEDS_ONEDNN_BF16
def test_bf16_fallback_agrees_with_onednn_bf16(models, monkeypatch):
    """The fallback rounds each linear layer's output to bf16 before its GELU, oneDNN after
    the fused GELU: tokens agree about as well as bf16 agrees with fp32 (measured 94 % of
    the base tokens, logits within ~0.5 % of their range, on this tiny model)."""
    clear_packed(models)
    fast = torch.stack([generate(models, "bf16", seed) for seed in range(8)])
    assert "bf16" in packed_layers(models)
    fp32 = torch.stack([generate(models, "fp32", seed) for seed in range(8)])
    simulate(monkeypatch, AVX2_ONLY)
    with pytest.warns(UserWarning):
        fallback = torch.stack([generate(models, "bf16", seed) for seed in range(8)])
    agreement = (fallback[..., 0] == fast[..., 0]).float().mean().item()
    bf16_vs_fp32 = (fp32[..., 0] == fast[..., 0]).float().mean().item()
    assert agreement > 0.85 and bf16_vs_fp32 > 0.85, (agreement, bf16_vs_fp32)


@pytest.mark.parametrize("answer", [AVX2_ONLY, NO_ONEDNN], ids=["avx2-only", "no-onednn"])
def test_linear_without_a_fast_path_is_f_linear(monkeypatch, answer):
    """`Linear` on a CPU that lacks a oneDNN path: F.linear (+ GELU), under autocast in bf16,
    never the private op that would refuse it."""
    simulate(monkeypatch, answer)
    torch.manual_seed(0)
    layer = PackedLinear(16, 24, activation="gelu").eval()
    x = torch.randn(3, 5, 16)
    expected = torch.nn.functional.gelu(torch.nn.functional.linear(x, layer.weight, layer.bias))
    with torch.inference_mode():
        torch.testing.assert_close(layer(x), expected, rtol=1e-5, atol=1e-5)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            y = layer(x)
            autocast = torch.nn.functional.gelu(
                torch.nn.functional.linear(x, layer.weight, layer.bias))
    assert y.dtype == torch.bfloat16 and torch.equal(y, autocast)
    assert set(layer._packed) == ({"fp32"} if answer.onednn_linear else set())


def test_cpu_kernels_keep_the_model_and_its_tokens(tmp_path):
    """`use_cpu_kernels` swaps kernels, not the model: the same parameters and state-dict
    keys, the same fp32 tokens as the plain model, a second call changes nothing, and the
    swapped model saves and loads as the plain one."""
    torch.manual_seed(0)
    plain = (MaskTransformer(MaskTransformerConfig(**TINY)).eval(),
             ResidualTransformer(ResidualTransformerConfig(**TINY, num_quantizers=3)).eval())
    with torch.no_grad():
        plain[0].classifier.weight.mul_(50)
        plain[1].code_embeddings.mul_(50)
    import copy

    swapped = tuple(use_cpu_kernels(copy.deepcopy(m)) for m in plain)
    for a, b in zip(plain, swapped, strict=True):
        assert list(a.state_dict()) == list(b.state_dict())
        assert all(torch.equal(x, y) for x, y in zip(a.state_dict().values(),
                                                      b.state_dict().values(), strict=True))
        parameters = [id(p) for p in b.parameters()]
        use_cpu_kernels(b)
        assert [id(p) for p in b.parameters()] == parameters
    assert any(isinstance(m, PackedLinear) for m in swapped[0].modules())
    assert torch.equal(generate(plain, "fp32"), generate(swapped, "fp32"))
    swapped[0].save_pretrained(tmp_path / "mask")
    loaded = MaskTransformer.from_pretrained(tmp_path / "mask")
    assert not any(isinstance(m, PackedLinear) for m in loaded.modules())
    assert all(torch.equal(x, y) for x, y in zip(loaded.state_dict().values(),
                                                  plain[0].state_dict().values(), strict=True))
