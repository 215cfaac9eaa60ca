"""Results across training seeds (segmo.evaluation.seeds)."""

import json
import math
from pathlib import Path

import numpy as np
import pytest
from conftest import load_tool
from scipy import stats

from segmo.evaluation.seeds import (
    differ,
    excludes_zero,
    figures,
    interval,
    paired,
    seed_table,
    summarise,
)


def _run(top1: float, fid: float) -> dict:
    return {"generation": {"generated": {"top1": {"mean": top1, "interval": 0.01},
                                         "fid": {"mean": fid, "interval": 0.1}}},
            "action_order": {"generated": {"sequence_accuracy": top1 / 2}}, "notes": {"x": "text"}}


def test_figures_flattens_means_and_numbers_and_ignores_text():
    flat = figures(_run(0.7, 2.0))
    assert flat == {"generation/generated/top1": 0.7, "generation/generated/fid": 2.0,
                    "action_order/generated/sequence_accuracy": 0.35}


def test_figures_keep_every_number_of_an_isc_entry():
    """An ISC entry {"mean", "cv", "pairs"} is three figures: collapsing it to its mean lost
    the CV (the paper's Fig. 4 figure) and the pair count."""
    run = {"isc": {"uniform": {"mean": 0.8, "cv": 0.25, "pairs": 12.0}},
           "generation": {"generated": {"multimodality": {"mean": 1.5}}}}
    assert figures(run) == {"isc/uniform/mean": 0.8, "isc/uniform/cv": 0.25, "isc/uniform/pairs": 12.0,
                            "generation/generated/multimodality": 1.5}


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


def test_paired_differences_are_narrower_when_seeds_move_both_arms():
    # Each seed lifts both arms alike; the new arm is 0.02 above on every seed.
    base = [_run(0.70, 2.0), _run(0.75, 2.4), _run(0.80, 1.6)]
    new = [_run(0.72, 2.1), _run(0.77, 2.2), _run(0.82, 1.9)]
    top1 = "generation/generated/top1"
    difference = paired(base, new)[top1]
    assert difference["mean"] == pytest.approx(0.02) and difference["interval"] == pytest.approx(0, abs=1e-12)
    assert excludes_zero(difference)
    assert not differ(summarise(base)[top1], summarise(new)[top1])  # side by side: overlap
    fid = paired(base, new)["generation/generated/fid"]
    assert fid["mean"] == pytest.approx(0.2 / 3) and not excludes_zero(fid)
    with pytest.raises(ValueError, match="3 runs against 2"):
        paired(base, new[:2])


def test_compare_seeds_tool(tmp_path, capsys):
    tool = load_tool("compare_seeds")
    files = {}
    for arm, values in (("base", (0.50, 0.60, 0.55)), ("new", (0.60, 0.66, 0.66))):
        for seed, value in enumerate(values):
            path = tmp_path / f"{arm}_s{seed}.txt"
            # what tools/order_by_template.py prints: lines of text, the JSON object last
            path.write_text("  3+ actions: ...\n" + json.dumps(
                {"by_num_actions": {"3+": {"sequence_accuracy": value, "motions": 89}}}) + "\n")
            files.setdefault(arm, []).append(str(path))
    argv = ["--base", *files["base"], "--new", *files["new"], "--names", "recipe,timing"]
    assert tool.main(argv + ["--figure", "by_num_actions/3+/sequence_accuracy"]) == 0
    row = capsys.readouterr().out.splitlines()[-1]
    assert row.startswith("| by_num_actions/3+/sequence_accuracy | 0.550 ± ")
    assert "| 0.090 ± 0.0" in row and row.endswith("| beyond the seeds' spread |")
    assert tool.main(argv) == 0  # no --figure: the figures every file holds
    assert capsys.readouterr().out.split() == ["by_num_actions/3+/motions", "by_num_actions/3+/sequence_accuracy"]
    assert tool.main(argv + ["--figure", "top1"]) == 2
    assert capsys.readouterr().err.strip() == (
        f"compare_seeds: --figure 'top1': not in {files['base'][0]} (nor 5 more); "
        "run without --figure to list the figures")
    Path(files["new"][1]).write_text("no result here\n")
    assert tool.main(argv + ["--figure", "by_num_actions/3+/motions"]) == 2
    assert capsys.readouterr().err.strip() == (
        f"compare_seeds: {files['new'][1]}: neither the file nor its last line is a JSON object")
    # one seed a side: a difference, but no interval to judge it by
    assert tool.main(["--base", files["base"][0], "--new", files["new"][0],
                      "--figure", "by_num_actions/3+/sequence_accuracy"]) == 0
    row = capsys.readouterr().out.splitlines()[-1]
    assert row == ("| by_num_actions/3+/sequence_accuracy | 0.500 | 0.600 | 0.100 "
                   "| one seed: no verdict |")
    with pytest.raises(SystemExit):
        tool.main(["--base", *files["base"], "--new", *files["new"][:2]])
    assert "--base has 3 files and --new 2" in capsys.readouterr().err
