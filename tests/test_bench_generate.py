"""tools/bench_generate.py's same-machine MoMask reference: the passes it times."""

from __future__ import annotations

import importlib.util
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _load_tool():
    spec = importlib.util.spec_from_file_location("bench_generate", REPO / "tools" / "bench_generate.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_momask_floor_runs_two_passes_per_step_and_layer():
    """MoMask runs the conditional and unconditional passes separately: 2 per decoding step
    and 2 per residual layer, over 1 + n tokens (mask) and 2 + n tokens (residual)."""
    tool = _load_tool()
    trunk, head = tool.momask_models(dim=16, depth=1, heads=2, ff_dim=32, codes=8)
    calls = []
    trunk.register_forward_hook(lambda module, args, output: calls.append(args[0].shape))
    tool.momask_floor(trunk, head, b=3, n=5, steps=4, num_quantizers=3)
    assert [tuple(s) for s in calls] == [(6, 3, 16)] * 8 + [(7, 3, 16)] * 4
