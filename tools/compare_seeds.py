"""Two variants trained with the same seeds: each one's mean ± 95 % interval over its seeds
and the paired difference, for chosen figures of their result files.

    python tools/compare_seeds.py --base runs/recipe_s0.json runs/recipe_s1.json runs/recipe_s2.json \\
        --new runs/timing_s0.json runs/timing_s1.json runs/timing_s2.json \\
        --figure by_num_actions/3+/sequence_accuracy [--figure ...] [--names recipe,timing]

A result file is a `segmo evaluate` metrics.json or what `tools/order_by_template.py`
printed (its last line is the JSON object; the lines before it are passed over). A figure is
a path into that object (`segmo.evaluation.seeds.figures`: a {"mean", "interval"} entry is
its mean), e.g. `generation/generated/top1` or `isc/uniform/cv`; without --figure the tool
lists the figures every file holds. The files of --base and --new are paired in the order given: list the seeds in
the same order. Prints a Markdown table: each arm's mean ± interval (Student t over the
seeds), the paired difference new − base with its interval, and "beyond the seeds' spread"
where that interval leaves out zero, else "no difference"; with one seed a side there is no
interval, and the verdict says so ("one seed: no verdict").
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from segmo.evaluation.seeds import excludes_zero, figures, paired, summarise


class CompareError(Exception):
    """Bad input: one line for the user."""


def read_result(path: Path) -> dict[str, Any]:
    """A metrics.json, or a file whose last non-empty line is a JSON object."""
    try:
        text = path.read_text()
    except OSError as error:
        raise CompareError(f"{path}: cannot read ({error.strerror or error})") from None
    lines = [line for line in text.splitlines() if line.strip()]
    for candidate in (text, lines[-1] if lines else ""):
        try:
            value = json.loads(candidate)
        except json.JSONDecodeError:
            continue
        if isinstance(value, dict):
            return value
    raise CompareError(f"{path}: neither the file nor its last line is a JSON object")


def _cell(entry: dict[str, float] | None, digits: int) -> str:
    if entry is None:
        return "–"
    if entry["seeds"] < 2:
        return f"{entry['mean']:.{digits}f}"
    return f"{entry['mean']:.{digits}f} ± {entry['interval']:.{digits}f}"


def compare(base: list[dict], new: list[dict], names: tuple[str, str], chosen: list[str],
            digits: int = 3) -> str:
    """The Markdown table of `chosen` figures (see the module docstring)."""
    arms, differences = (summarise(base), summarise(new)), paired(base, new)
    lines = [f"| figure | {names[0]} | {names[1]} | {names[1]} − {names[0]} (paired) | verdict |",
             "| --- | --- | --- | --- | --- |"]
    for figure in chosen:
        difference = differences.get(figure)
        if difference is None:  # NaN or inf in some seed's file
            verdict = "not finite in every file"
        elif difference["seeds"] < 2:  # no interval, so neither "beyond" nor "no difference"
            verdict = "one seed: no verdict"
        else:
            verdict = "beyond the seeds' spread" if excludes_zero(difference) else "no difference"
        lines.append(f"| {figure} | {_cell(arms[0].get(figure), digits)} | "
                     f"{_cell(arms[1].get(figure), digits)} | {_cell(difference, digits)} | {verdict} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--base", nargs="+", type=Path, required=True, help="one file per seed")
    parser.add_argument("--new", nargs="+", type=Path, required=True,
                        help="one file per seed, in the order of --base")
    parser.add_argument("--figure", action="append", default=[], help="a figure's path; repeat")
    parser.add_argument("--names", default="base,new", help="the two arms' names, comma-separated")
    parser.add_argument("--digits", type=int, default=3)
    args = parser.parse_args(argv)
    if not 0 <= args.digits <= 12:
        parser.error(f"--digits {args.digits}: expected a whole number from 0 to 12")
    names = tuple(n.strip() for n in args.names.split(","))
    if len(names) != 2 or not all(names):
        parser.error(f"--names {args.names!r}: expected two names separated by a comma")
    if len(args.base) != len(args.new):
        parser.error(f"--base has {len(args.base)} files and --new {len(args.new)}: "
                     "give one file per seed, the same seeds for both")
    try:
        base = [read_result(p) for p in args.base]
        new = [read_result(p) for p in args.new]
    except CompareError as error:
        print(f"compare_seeds: {error}", file=sys.stderr)
        return 2
    flat = {p: figures(r) for p, r in zip([*args.base, *args.new], [*base, *new])}
    common = set.intersection(*(set(f) for f in flat.values()))
    if not args.figure:
        print("\n".join(sorted(common)))
        return 0
    for figure in args.figure:
        lacking = [str(p) for p, f in flat.items() if figure not in f]
        if lacking:
            print(f"compare_seeds: --figure {figure!r}: not in {lacking[0]}"
                  + (f" (nor {len(lacking) - 1} more)" if len(lacking) > 1 else "")
                  + "; run without --figure to list the figures", file=sys.stderr)
            return 2
    print(compare(base, new, names, args.figure, args.digits))
    return 0


if __name__ == "__main__":
    sys.exit(main())
