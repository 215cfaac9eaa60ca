"""tools/training_curves.py: plateau verdicts and the table from CSV-logger files."""

import json
from pathlib import Path

import pytest
from conftest import load_tool

from segmo.cli import run
from segmo.errors import SegmoError


def test_plateau_verdicts():
    curves = load_tool("training_curves")
    assert curves.plateau([5, 4, 3, 2, 1, 0.5], 3, 0.01, True) == "improving"
    assert curves.plateau([5, 2, 1, 1.0, 1.001, 1.0], 3, 0.01, True) == "plateau"
    assert curves.plateau([5, 2, 1, 1.5, 1.6, 1.7], 3, 0.01, True) == "worse"
    assert curves.plateau([0.1, 0.5, 0.8, 0.81, 0.8, 0.805], 3, 0.02, False) == "plateau"
    assert curves.plateau([1, 2], 3, 0.01, True) == "too few points"


def test_smooth_is_a_trailing_mean():
    curves = load_tool("training_curves")
    assert curves.smooth([1.0, 3.0, 5.0, 7.0], 2) == [1.0, 2.0, 4.0, 6.0]
    assert curves.smooth([1.0, 3.0], 1) == [1.0, 3.0]


def test_table_and_png_from_metrics_csv(tmp_path: Path, capsys):
    curves = load_tool("training_curves")
    run = tmp_path / "runs" / "mask" / "a" / "version_0"
    run.mkdir(parents=True)
    rows = ["epoch,step,train/loss,val/loss"] + [f"0,{s},1.0," for s in range(0, 50, 10)]
    rows += [f"0,{s},,{v}" for s, v in ((9, 3.0), (19, 2.0), (29, 1.5), (39, 1.49), (49, 1.495), (59, 1.49))]
    (run / "metrics.csv").write_text("\n".join(rows) + "\n")
    result = curves.main(["--runs", str(tmp_path / "runs"), "--metric", "val/loss", "--out", str(tmp_path / "png")])
    assert (tmp_path / "png" / "val_loss.png").is_file()
    (row,) = result["runs"]
    assert row["points"] == 6 and row["best"] == 1.49 and row["last_step"] == 59 and row["plateau"] == "plateau"
    assert "| mask/a/version_0 | val/loss | 6 | 3 | 1.49 | 1.49 (59) | plateau |" in capsys.readouterr().out


def test_bad_input_is_one_line_and_keeps_the_pictures_already_there(tmp_path: Path, capsys):
    curves = load_tool("training_curves")
    folder = tmp_path / "runs" / "a" / "version_0"
    folder.mkdir(parents=True)
    good = "epoch,step,val/loss\n0,9,3.0\n0,19,nan\n0,29,2.0\n"
    (folder / "metrics.csv").write_text(good)
    argv = ["--runs", str(tmp_path / "runs"), "--out", str(tmp_path / "png")]
    curves.main(argv + ["--metric", "val/loss"])
    out = capsys.readouterr().out
    assert json.loads(out.splitlines()[-1])["runs"][0]["points"] == 2  # the NaN left out
    picture = (tmp_path / "png" / "val_loss.png").read_bytes()
    # a metric no run logged, beside one they did: refused before any PNG is written
    with pytest.raises(SystemExit) as stop:  # as a command: one line, exit status 2
        run("training_curves.py", curves.main, argv + ["--metric", "val/loss", "--metric", "val/lsos"])
    assert stop.value.code == 2 and capsys.readouterr().err.strip() == (
        f"training_curves.py: --metric val/lsos: no run under {tmp_path / 'runs'} logged it (a "
        "finite value) (see `training_curves.py --help`)")
    assert not (tmp_path / "png" / "val_lsos.png").exists()
    (folder / "metrics.csv").write_text(good + "0,oops,1.0\n")
    with pytest.raises(SegmoError) as error:
        curves.main(argv + ["--metric", "val/loss"])
    assert str(error.value) == (f"{folder / 'metrics.csv'}:5: expected numbers in 'step' and "
                                "'val/loss', got 'oops' and '1.0'")
    assert (tmp_path / "png" / "val_loss.png").read_bytes() == picture
    with pytest.raises(SegmoError, match="argument --window: expected a whole number >= 1"):
        curves.main(argv + ["--metric", "val/loss", "--window", "0"])


def test_iou_and_perplexity_are_higher_is_better_and_runs_are_told_apart_by_stage(tmp_path: Path):
    curves = load_tool("training_curves")
    rising = [0.1, 0.2, 0.3, 0.4, 0.5, 0.6]
    for stage in ("mask", "rvq"):  # the same run name under two stages, as `segmo fit --name demo` makes
        folder = tmp_path / "runs" / stage / "demo" / "version_0"
        folder.mkdir(parents=True)
        rows = ["epoch,step,val/timing_iou,val/perplexity_q0,val/within2"]
        rows += [f"0,{10 * i + 9},{v},{100 * v},{v}" for i, v in enumerate(rising)]
        (folder / "metrics.csv").write_text("\n".join(rows) + "\n")
    result = curves.main(["--runs", str(tmp_path / "runs"), "--metric", "val/timing_iou", "--metric",
                          "val/perplexity_q0", "--metric", "val/within2", "--out", str(tmp_path / "png")])
    assert {(r["metric"], r["plateau"], r["best"] == r["last"]) for r in result["runs"]} == {
        ("val/timing_iou", "improving", True), ("val/perplexity_q0", "improving", True),
        ("val/within2", "improving", True)}
    assert sorted({r["run"] for r in result["runs"]}) == ["mask/demo/version_0", "rvq/demo/version_0"]
