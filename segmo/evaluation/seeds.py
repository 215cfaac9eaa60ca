"""Results across training seeds: mean ± 95 % interval of each metric over several runs.

A `segmo evaluate` result holds the interval over evaluation repeats of one trained model;
whether a training choice (alignment or not) changes quality needs the spread over
training seeds too. `summarise` takes the metrics.json dicts of one variant's seeds and
gives, for every figure they all hold, the mean over seeds and the half-width of the
95 % Student-t interval (n - 1 degrees of freedom: with three seeds the half-width is
2.48 standard deviations of the mean's estimate, not 1.96). `differ` says whether two
such intervals are apart; overlapping intervals are reported as "no difference".
`paired` gives the interval of the per-seed differences of two variants trained with the
same seeds (`tools/compare_seeds.py` prints both for chosen figures).

    in_sample = [json.loads(p.read_text()) for p in in_sample_paths]
    columns = ["generation/generated/top1", "generation/generated/fid"]
    print(seed_table([("in_sample", in_sample, columns), ("none", none, columns)], ["Top-1", "FID"]))
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

from scipy import stats


def figures(metrics: Mapping[str, Any], prefix: str = "") -> dict[str, float]:
    """Flatten a metrics dict to {"a/b/c": value}: a {"mean", "interval"} dict is one figure
    (its mean: the evaluation repeats' average; a null mean, how metrics.json writes NaN, is
    NaN), other numbers are taken as they are (a bare null is left out, like config's). Any
    other dict is walked into, so an ISC entry {"mean", "cv", "pairs"} gives three figures
    (isc/uniform/mean, isc/uniform/cv, isc/uniform/pairs)."""
    out: dict[str, float] = {}
    for key, value in metrics.items():
        path = f"{prefix}{key}"
        if isinstance(value, Mapping):
            mean = value.get("mean", "absent")
            if set(value) <= {"mean", "interval"} and (mean is None or isinstance(mean, (int, float))):
                out[path] = math.nan if mean is None else float(mean)
            else:
                out |= figures(value, path + "/")
        elif isinstance(value, (int, float)) and not isinstance(value, bool):
            out[path] = float(value)
    return out


def interval(values: Sequence[float]) -> tuple[float, float]:
    """(mean, half-width of the 95 % t interval) of per-seed values; one seed → width nan."""
    n = len(values)
    if n == 0:
        raise ValueError("interval: no values")
    mean = sum(values) / n
    if n == 1:
        return mean, math.nan
    sd = math.sqrt(sum((v - mean) ** 2 for v in values) / (n - 1))
    return mean, float(stats.t.ppf(0.975, n - 1) * sd / math.sqrt(n))


def summarise(runs: Sequence[Mapping[str, Any]]) -> dict[str, dict[str, float]]:
    """{figure: {"mean", "interval", "seeds"}} over the runs, for the figures every run has."""
    if not runs:
        raise ValueError("summarise: no runs")
    flat = [figures(r) for r in runs]
    common = set(flat[0]).intersection(*flat[1:])
    out = {}
    for key in sorted(common):
        values = [f[key] for f in flat]
        if not all(math.isfinite(v) for v in values):
            continue
        mean, half = interval(values)
        out[key] = {"mean": mean, "interval": half, "seeds": float(len(values))}
    return out


def paired(base: Sequence[Mapping[str, Any]], new: Sequence[Mapping[str, Any]]
           ) -> dict[str, dict[str, float]]:
    """{figure: {"mean", "interval", "seeds"}} of the per-seed differences new − base, run i
    of one against run i of the other (the same training seed), for the figures every run
    has. Pairing removes what a seed does to both (its data order, its initialisation), so
    the interval is narrower than the two arms' intervals side by side whenever the seeds
    move both arms alike; it is still "no difference" while it holds zero."""
    if len(base) != len(new) or not base:
        raise ValueError(f"paired: {len(base)} runs against {len(new)}; give the same seeds "
                         "in the same order")
    flat_base, flat_new = [figures(r) for r in base], [figures(r) for r in new]
    common = set(flat_base[0]).intersection(*flat_base[1:], *flat_new)
    out = {}
    for key in sorted(common):
        differences = [n[key] - b[key] for b, n in zip(flat_base, flat_new)]
        if not all(math.isfinite(d) for d in differences):
            continue
        mean, half = interval(differences)
        out[key] = {"mean": mean, "interval": half, "seeds": float(len(differences))}
    return out


def excludes_zero(entry: Mapping[str, float]) -> bool:
    """Whether a {"mean", "interval"} summary's 95 % interval leaves out 0 (a paired
    difference beyond the seeds' spread)."""
    return not math.isnan(entry["interval"]) and abs(entry["mean"]) > entry["interval"]


def differ(a: Mapping[str, float], b: Mapping[str, float]) -> bool:
    """Whether two {"mean", "interval"} summaries' 95 % intervals do not overlap."""
    if math.isnan(a["interval"]) or math.isnan(b["interval"]):
        return False
    return abs(a["mean"] - b["mean"]) > a["interval"] + b["interval"]


def _cell(entry: Mapping[str, float] | None, digits: int) -> str:
    if entry is None:
        return "–"
    if math.isnan(entry["interval"]):
        return f"{entry['mean']:.{digits}f}"
    return f"{entry['mean']:.{digits}f}±{entry['interval']:.{digits}f}"


def seed_table(rows: Sequence[tuple[str, Sequence[Mapping[str, Any]], Sequence[str]]],
               titles: Sequence[str], digits: int = 3) -> str:
    """Markdown: one line per (name, runs, figure paths) with its number of seeds, cells
    "mean±interval" over the runs; the paths of each row line up with `titles`."""
    lines = ["| | seeds | " + " | ".join(titles) + " |", "| --- | --- |" + " --- |" * len(titles)]
    for name, runs, columns in rows:
        if len(columns) != len(titles):
            raise ValueError(f"seed_table: row {name!r} has {len(columns)} figures for {len(titles)} titles")
        summary = summarise(runs)
        lines.append(f"| {name} | {len(runs)} | " + " | ".join(
            _cell(summary.get(c), digits) for c in columns) + " |")
    return "\n".join(lines)
