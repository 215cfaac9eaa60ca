"""Results across training seeds (segmo.evaluation.seeds)."""

import math

import numpy as np
import pytest
from scipy import stats

from segmo.evaluation.seeds import differ, figures, interval, seed_table, summarise


def _run(top1: float, fid: float) -> dict:
    return {"generation": {"generated": {"top1": {"mean": top1, "interval": 0.01},
                                         "fid": {"mean": fid, "interval": 0.1}}},
            "action_order": {"generated": {"sequence_accuracy": top1 / 2}}, "notes": {"x": "text"}}


def test_figures_flattens_means_and_numbers_and_ignores_text():
    flat = figures(_run(0.7, 2.0))
    assert flat == {"generation/generated/top1": 0.7, "generation/generated/fid": 2.0,
                    "action_order/generated/sequence_accuracy": 0.35}


def test_interval_is_the_student_t_half_width():
    values = [0.70, 0.72, 0.75]
    mean, half = interval(values)
    sd = np.std(values, ddof=1)
    assert mean == pytest.approx(np.mean(values))
    assert half == pytest.approx(stats.t.ppf(0.975, 2) * sd / math.sqrt(3))
    assert half > 1.96 * sd / math.sqrt(3)  # wider than the normal approximation with 3 seeds
    assert math.isnan(interval([0.7])[1])
    with pytest.raises(ValueError):
        interval([])


def test_summarise_keeps_the_figures_every_run_has():
    runs = [_run(0.70, 2.0), _run(0.72, 3.0), {"generation": {"generated": {"top1": {"mean": 0.74}}}}]
    summary = summarise(runs)
    assert set(summary) == {"generation/generated/top1"}
    assert summary["generation/generated/top1"]["mean"] == pytest.approx(0.72)
    assert summary["generation/generated/top1"]["seeds"] == 3


def test_differ_only_when_the_intervals_are_apart():
    assert differ({"mean": 1.0, "interval": 0.1}, {"mean": 1.5, "interval": 0.1})
    assert not differ({"mean": 1.0, "interval": 0.3}, {"mean": 1.5, "interval": 0.3})
    assert not differ({"mean": 1.0, "interval": math.nan}, {"mean": 9.0, "interval": 0.1})


def test_seed_table_rows_and_cells():
    columns = ["generation/generated/top1", "generation/generated/missing"]
    table = seed_table([("in_sample", [_run(0.70, 2.0), _run(0.72, 2.2)], columns),
                        ("none", [_run(0.71, 1.9)], columns)], ["Top-1", "X"])
    lines = table.splitlines()
    assert lines[0] == "| | seeds | Top-1 | X |"
    assert lines[2].startswith("| in_sample | 2 | 0.710±0.")
    assert lines[2].endswith("| – |")
    assert lines[3] == "| none | 1 | 0.710 | – |"
    with pytest.raises(ValueError, match="row 'a' has 1 figures for 2 titles"):
        seed_table([("a", [_run(0.7, 2.0)], ["x"])], ["a", "b"])
