"""tools/bench_train.py: the step figures it reports, by the median step and by throughput."""

from __future__ import annotations

from conftest import load_tool


def test_step_figures_by_median_and_by_throughput():
    # Grouped batches are as long as their length group: mostly short steps and a few long
    # ones. The median is the short step, the throughput (1 / mean) what an epoch takes.
    steps = {"cached": [0.6] * 4, "on_the_fly": [0.8] * 4, "grouped": [0.2, 0.2, 0.2, 1.0],
             "momask": [0.7] * 4}
    times = {name: [{"total": t, "data": 0.0} for t in ts] for name, ts in steps.items()}
    figures = load_tool("bench_train").step_figures(times)
    assert figures["ms_per_step"] == {"cached": 600.0, "on_the_fly": 800.0, "grouped": 200.0,
                                      "momask": 700.0}
    assert figures["speedup_vs_on_the_fly"] == {"cached": 1.33, "grouped": 4.0}
    assert figures["speedup_vs_momask"] == {"cached": 1.17, "grouped": 3.5}
    assert figures["speedup_cached_vs_on_the_fly"] == 1.33
    throughput = figures["throughput"]
    assert throughput["ms_per_step"]["grouped"] == 400.0
    assert throughput["steps_per_s"]["grouped"] == 2.5
    assert throughput["speedup_vs_on_the_fly"] == {"cached": 1.33, "grouped": 2.0}
    assert throughput["speedup_vs_momask"] == {"cached": 1.17, "grouped": 1.75}
