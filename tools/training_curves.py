"""Training curves of `segmo fit` runs, to see whether a recipe reached its plateau.

Reads the CSV logger's ``metrics.csv`` of each run (``RUNS/<stage>/<name>/version_<k>/``)
and draws, per metric, one line per run over the training step; a run's validation
metric has reached its plateau when its last ``--window`` validation points improve on
the best before them by less than ``--tolerance`` (relative) either way ("improving" or
"worse" otherwise). Writes one PNG per metric and
prints a Markdown table (run, metric, first, best, last, plateau) and a final JSON line.

    python tools/training_curves.py --runs runs --metric val/loss --out curves/
    python tools/training_curves.py --runs runs/mask --metric val/loss --metric val/segment_top1 \\
        --out curves/ --window 3
    python tools/training_curves.py --runs runs/mask --metric train/loss --smooth 20 --window 20 --out curves/
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path


def read_metric(path: Path, metric: str) -> list[tuple[int, float]]:
    """(step, value) of every row of a metrics.csv that holds `metric`."""
    with path.open(newline="") as f:
        rows = list(csv.DictReader(f))
    out = []
    for row in rows:
        value = row.get(metric, "")
        if value not in ("", None):
            out.append((int(float(row["step"])), float(value)))
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
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--runs", type=Path, required=True, help="folder holding the runs (searched recursively)")
    p.add_argument("--metric", action="append", required=True, help="e.g. val/loss (repeatable)")
    p.add_argument("--out", type=Path, required=True, help="folder for the PNGs")
    p.add_argument("--window", type=int, default=3, help="validation points that define the plateau")
    p.add_argument("--tolerance", type=float, default=0.01, help="relative gain below which it is a plateau")
    p.add_argument("--smooth", type=int, default=1,
                   help="moving average over this many logged points (train metrics are noisy)")
    args = p.parse_args(argv)
    if not args.runs.is_dir():
        p.error(f"--runs {args.runs}: no such folder")
    if args.window < 1:
        p.error(f"--window {args.window}: must be at least 1")
    files = runs_under(args.runs)
    if not files:
        p.error(f"--runs {args.runs}: no version_*/metrics.csv below it")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for metric in args.metric:
        lower = not any(word in metric for word in ("top", "acc", "usage", "r@"))
        fig, ax = plt.subplots(figsize=(6, 3.5))
        for path in files:
            points = read_metric(path, metric)
            if not points:
                continue
            name = path.parent.parent.name
            steps, raw = zip(*points, strict=True)
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
        fig.savefig(args.out / (metric.replace("/", "_") + ".png"), dpi=110)
        plt.close(fig)
    if not rows:
        p.error(f"none of the runs logged {args.metric}")
    print("| run | metric | points | first | best | last (step) | plateau |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for r in rows:
        print(f"| {r['run']} | {r['metric']} | {r['points']} | {r['first']:.4g} | {r['best']:.4g} | "
              f"{r['last']:.4g} ({r['last_step']}) | {r['plateau']} |")
    result = {"runs": rows, "window": args.window, "tolerance": args.tolerance, "smooth": args.smooth}
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    sys.exit(main() and 0)
