"""tools/bench_generate.py: the MoMask passes it times, its MAC count, the precision it picks."""

from __future__ import annotations

import pytest
from conftest import load_tool

from segmo.generation import SamplingOptions


def _load_tool():
    return load_tool("bench_generate")


def test_momask_floor_runs_two_passes_per_step_and_layer():
    """MoMask runs the conditional and unconditional passes separately: 2 per decoding step
    and 2 per residual layer, over 1 + n tokens (mask) and 2 + n tokens (residual)."""
    tool = _load_tool()
    trunk, head = tool.momask_models(dim=16, depth=1, heads=2, ff_dim=32, codes=8)
    calls = []
    trunk.register_forward_hook(lambda module, args, output: calls.append(args[0].shape))
    tool.momask_floor(trunk, head, b=3, n=5, steps=4, num_quantizers=3)
    assert [tuple(s) for s in calls] == [(6, 3, 16)] * 8 + [(7, 3, 16)] * 4


def test_generation_macs_counts_what_the_floor_passes_compute(monkeypatch):
    """The arithmetic bound's MAC count equals what PyTorch's FLOP counter sees in the floor
    passes (linear layers sent through `F.linear`, attention through matmuls)."""
    import torch
    from torch.utils.flop_counter import FlopCounterMode

    from segmo.models import cpu_inference
    from segmo.models.mask_transformer import MaskTransformer, MaskTransformerConfig
    from segmo.models.residual_transformer import ResidualTransformer, ResidualTransformerConfig

    tool = _load_tool()
    # The CPU kernels with oneDNN off: linear layers run F.linear, attention two matmuls,
    # all of which the counter sees.
    monkeypatch.setattr(cpu_inference, "_ONEDNN_LINEAR", None)
    shared = dict(codebook_size=16, text_dim=8, max_segments=3, max_tokens=12, dim=32,
                  depth=2, heads=2, ff_dim=64)
    mask = cpu_inference.use_cpu_kernels(MaskTransformer(MaskTransformerConfig(**shared)).eval())
    residual = cpu_inference.use_cpu_kernels(
        ResidualTransformer(ResidualTransformerConfig(**shared, num_quantizers=3)).eval())
    b, n, steps = 2, 10, 4
    text = tool.text_inputs(mask, b, seed=0)
    sampled = []  # the positions generation itself asks for, pass by pass
    original = MaskTransformer.forward_condition

    def recording(self, indices, token_mask, condition, positions=None, sink_rows=None):
        sampled.append(n if positions is None else positions.shape[1])
        return original(self, indices, token_mask, condition, positions, sink_rows)

    monkeypatch.setattr(MaskTransformer, "forward_condition", recording)
    tool.generate_tokens(mask, residual, *text, torch.full((b,), 4 * n),
                         options=SamplingOptions(steps=steps))
    assert tool.sampled_counts(n, steps) == sampled == [10, 9, 6, 1]
    with FlopCounterMode(display=False) as counter:
        tool.floor_passes(mask, residual, text, n, steps, "fp32")
    with FlopCounterMode(display=False) as prefix_counter, torch.inference_mode():
        tool.guidance_condition(mask, *text)  # the prefix encodings, not counted as passes
        tool.guidance_condition(residual, *text)
    assert 0 < prefix_counter.get_total_flops() < counter.get_total_flops()
    counted = counter.get_total_flops() - prefix_counter.get_total_flops()
    assert counted == 2 * tool.generation_macs(mask, residual, b, n, steps)


@pytest.mark.parametrize("simulated", [False, True], ids=["this-cpu", "avx2-only"])
def test_bench_says_which_precision_it_chose_and_why(monkeypatch, capsys, simulated):
    """`--precision auto` (the default) runs what `segmo generate` runs; the first line and
    the JSON say which precision, why, and on which CPU."""
    import json

    import torch

    from segmo import cpu

    if simulated:
        answer = cpu.CPUInfo(model="AMD EPYC 7B13 (simulated)", isa="AVX2", onednn_linear=True,
                             onednn_bf16=False, native_bf16=())
        monkeypatch.setattr(cpu, "info", lambda: answer)
    tool = _load_tool()
    threads = torch.get_num_threads()
    try:
        tool.main(["--random-config", "tiny", "--repeats", "1", "--threads", "1",
                   "--default-allocator"])
    finally:
        torch.set_num_threads(threads)
    lines = capsys.readouterr().out.strip().splitlines()
    expected, why = cpu.auto_precision()
    assert lines[0] == f"precision {expected} (auto: {why}); CPU: {cpu.describe()}"
    result = json.loads(lines[-1])
    assert (result["precision"], result["precision_asked"]) == (expected, "auto")
    assert result["precision_reason"] == why and result["cpu"] == cpu.describe()
    if simulated:
        assert expected == "fp32" and "no bf16 path in oneDNN" in why


def test_paired_ratios_cancel_drift_that_hits_both_alike():
    """A variant 10 % slower than the baseline in every round reads 1.10 with an interval
    around it, however much the host drifts between rounds."""
    tool = _load_tool()
    drift = [1.0, 3.0, 0.5, 2.0, 1.5]
    times = {"cfg": [d for d in drift], "slow": [1.1 * d for d in drift],
             "noisy": [d * f for d, f in zip(drift, [0.9, 1.1, 1.0, 0.95, 1.05])]}
    ratios = tool.paired_ratios(times)
    assert ratios["slow"]["median_ratio"] == pytest.approx(1.1)
    low, high = ratios["slow"]["ratio_interval_95"]
    assert low == pytest.approx(1.1, abs=1e-3) and high == pytest.approx(1.1, abs=1e-3)
    low, high = ratios["noisy"]["ratio_interval_95"]
    assert low < 1.0 < high and ratios["noisy"]["rounds"] == 5


def test_versus_times_each_mechanism_against_plain_cfg(capsys):
    """`--versus` runs plain CFG and each named mechanism in turns and reports one paired
    ratio per mechanism; an unknown name is refused naming the choices."""
    import json

    tool = _load_tool()
    # The word variants generate with word features (a words model refuses to run without).
    tool.main(["--random-config", "tiny", "--versus", "sink_ctrl,memory16,words,words_cross", "--repeats", "2",
               "--threads", "1"])
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert set(result["versus_cfg"]) == {"sink_ctrl", "memory16", "words", "words_cross"}
    assert set(result["cpu_ms_per_motion"]) == {"cfg", "sink_ctrl", "memory16", "words", "words_cross"}
    assert all(r["rounds"] == 2 and r["median_ratio"] > 0 for r in result["versus_cfg"].values())
    with pytest.raises(SystemExit):
        tool.main(["--random-config", "tiny", "--versus", "sink_ctl"])
    assert "sink_ctrl" in capsys.readouterr().err
