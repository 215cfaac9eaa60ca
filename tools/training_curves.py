"""Training curves of `segmo fit` runs, to see whether a recipe reached its plateau.

Reads the CSV logger's ``metrics.csv`` of each run (``RUNS/<stage>/<name>/version_<k>/``,
the newest version of each run folder) and draws, per metric, one line per run over the
training step; a run is labelled by its folder relative to ``--runs``
(``mask/demo/version_0``). A run's validation metric has reached its plateau when its last
``--window`` validation points improve on the best before them by less than
``--tolerance`` (relative) either way ("improving" or "worse" otherwise). Higher is better
for a metric whose name holds one of HIGHER_IS_BETTER (accuracy, top-k, R@k, IoU, code
usage and perplexity, within-k), lower for every other (losses, errors, distances). Writes
one PNG per metric and prints a Markdown table (run, metric, first, best, last, plateau)
and a final JSON line.
NaN and inf values (a diverged run) are left out of the curves. A bad file or argument is
one line on stderr (exit status 2), before any PNG is written; PNGs are written atomically.

    python tools/training_curves.py --runs runs --metric val/loss --out curves/
    python tools/training_curves.py --runs runs/mask --metric val/loss --metric val/segment_top1 \\
        --out curves/ --window 3
    python tools/training_curves.py --runs runs/mask --metric train/loss --smooth 20 --window 20 --out curves/
"""

from __future__ import annotations

import csv
import io
import math
import sys
from pathlib import Path

from segmo.cli import run
from segmo.errors import ArgumentParser, SegmoError, non_negative_float, positive_int
from segmo.files import json_text, write_atomic

# Words of the metric names the tasks log (`self.log` in segmo/tasks) for which higher is
# better: accuracy, frame_accuracy, top1, segment_top1*, R@k, timing_iou, code_usage_q*,
# perplexity_q* (the codebook's, not a language model's) and the length's within2.
HIGHER_IS_BETTER = ("acc", "top", "r@", "iou", "usage", "perplexity", "within")


def read_metric(path: Path, metric: str) -> list[tuple[int, float]]:
    """(step, value) of every row of a metrics.csv that holds `metric`; NaN and inf values (a
    diverged run) are left out. SegmoError naming the file and line for a file that is not
    the CSV logger's."""
    try:
        with path.open(newline="", encoding="utf-8") as f:
            reader = csv.DictReader(f)
            rows = list(reader)
            columns = reader.fieldnames or ()
    except (OSError, UnicodeDecodeError, csv.Error) as error:
        raise SegmoError(f"{path}: cannot read as a CSV file ({error})") from None
    if metric in columns and "step" not in columns:
        raise SegmoError(f"{path}: no 'step' column; expected the CSV logger's metrics.csv")
    out = []
    for line, row in enumerate(rows, start=2):  # line 1 is the header
        value = row.get(metric, "")
        if value in ("", None):
            continue
        try:
            step, number = int(float(row["step"])), float(value)
        except (TypeError, ValueError, OverflowError):
            raise SegmoError(f"{path}:{line}: expected numbers in 'step' and {metric!r}, got "
                             f"{row['step']!r} and {value!r}") from None
        if math.isfinite(number):
            out.append((step, number))
    return out


def smooth(values: list[float], points: int) -> list[float]:
    """Trailing moving average over `points` values (1: unchanged), for noisy train metrics."""
    if points <= 1:
        return list(values)
    return [sum(values[max(0, i - points + 1):i + 1]) / (i + 1 - max(0, i - points + 1))
            for i in range(len(values))]


def plateau(values: list[float], window: int, tolerance: float, lower_is_better: bool) -> str:
    """How the last `window` points compare with the best before them: "improving" (by more
    than `tolerance`, relative), "worse" (by more than it: over-fitting), else "plateau";
    "too few points" below 2 × window points."""
    if len(values) < 2 * window:
        return "too few points"
    before, last = values[:-window], values[-window:]
    best_before = min(before) if lower_is_better else max(before)
    best_last = min(last) if lower_is_better else max(last)
    gain = (best_before - best_last) if lower_is_better else (best_last - best_before)
    scale = tolerance * max(abs(best_before), 1e-12)
    return "improving" if gain > scale else "worse" if gain < -scale else "plateau"


def runs_under(root: Path) -> list[Path]:
    """Every run's newest metrics.csv under `root` (one per run folder)."""
    newest: dict[Path, Path] = {}
    for path in sorted(root.rglob("version_*/metrics.csv")):
        run = path.parent.parent
        if run not in newest or path.stat().st_mtime > newest[run].stat().st_mtime:
            newest[run] = path
    return [newest[r] for r in sorted(newest)]


def main(argv: list[str] | None = None) -> dict:
    """Read the runs, write the PNGs, print the table and the JSON line; the JSON's object
    is returned. SegmoError for bad arguments or files: nothing is written then."""
    p = ArgumentParser(prog="training_curves.py", description=__doc__.split("\n\n")[0])
    p.add_argument("--runs", type=Path, required=True, help="folder holding the runs (searched recursively)")
    p.add_argument("--metric", action="append", required=True, help="e.g. val/loss (repeatable)")
    p.add_argument("--out", type=Path, required=True, help="folder for the PNGs")
    p.add_argument("--window", type=positive_int, default=3, help="validation points that define the plateau")
    p.add_argument("--tolerance", type=non_negative_float, default=0.01,
                   help="relative gain below which it is a plateau")
    p.add_argument("--smooth", type=positive_int, default=1,
                   help="moving average over this many logged points (train metrics are noisy)")
    args = p.parse_args(argv)
    if not args.runs.is_dir():
        p.error(f"--runs {args.runs}: no such folder")
    if args.out.exists() and not args.out.is_dir():
        p.error(f"--out {args.out}: is a file; give a folder for the PNGs")
    files = runs_under(args.runs)
    if not files:
        p.error(f"--runs {args.runs}: no version_*/metrics.csv below it")
    # Every file is read before anything is written: a bad file or a metric no run logged
    # leaves the PNGs of an earlier call as they were.
    points = {metric: {path: read_metric(path, metric) for path in files} for metric in args.metric}
    missing = [metric for metric, by_run in points.items() if not any(by_run.values())]
    if missing:
        p.error(f"--metric {missing[0]}: no run under {args.runs} logged it (a finite value)")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for metric, by_run in points.items():
        lower = not any(word in metric.lower() for word in HIGHER_IS_BETTER)
        fig, ax = plt.subplots(figsize=(6, 3.5))
        for path, logged in by_run.items():
            if not logged:
                continue
            name = path.parent.relative_to(args.runs).as_posix()
            steps, raw = zip(*logged, strict=True)
            values = smooth(list(raw), args.smooth)
            ax.plot(steps, values, marker="o", markersize=2, label=name)
            best = min(values) if lower else max(values)
            rows.append({"run": name, "metric": metric, "points": len(values), "first": values[0],
                         "best": best, "last": values[-1], "last_step": steps[-1],
                         "plateau": plateau(list(values), args.window, args.tolerance, lower)})
        ax.set_xlabel("step")
        ax.set_ylabel(metric)
        ax.legend(fontsize=7)
        fig.tight_layout()
        picture = io.BytesIO()
        fig.savefig(picture, format="png", dpi=110)
        plt.close(fig)
        write_atomic(args.out / (metric.replace("/", "_") + ".png"), picture.getvalue())
    print("| run | metric | points | first | best | last (step) | plateau |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for r in rows:
        print(f"| {r['run']} | {r['metric']} | {r['points']} | {r['first']:.4g} | {r['best']:.4g} | "
              f"{r['last']:.4g} ({r['last_step']}) | {r['plateau']} |")
    result = {"runs": rows, "window": args.window, "tolerance": args.tolerance, "smooth": args.smooth}
    print(json_text(result))
    return result


if __name__ == "__main__":
    run("training_curves.py", main, sys.argv[1:])
