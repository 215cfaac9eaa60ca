"""The paper's Table 3 ablation: one mask transformer per alignment / segmentation variant,
the same tokenizer, residual transformer and length estimator, evaluated the same way.

    python tools/ablation_grid.py --data data/synth --tokenizer models/rvq \\
        --evaluator models/evaluator --out runs/ablation [--steps 2000] \\
        [--variants in_sample,none,batch,global,token,cpd,kmeans] \\
        [--residual models/residual --length models/length] [--seeds 0,1,2] \\
        [--parallel 2] [--dry-run]

For each variant: `segmo fit --config configs/mask/<dataset>.yaml` with
`--model.init_args.alignment X --model.init_args.segmenter Y` (and `--trainer.max_steps N`
when --steps is given), `segmo export` of its last checkpoint, `segmo bundle` with the
shared stages, `segmo evaluate`. The residual transformer and length estimator are
trained once when not given. Every step whose output exists is skipped, so an interrupted
grid resumes. Writes OUT/table3.md (Real row + one row per variant, the paper's format).
--dry-run prints the commands without running anything. Paths may be relative to where the
tool is called from (the commands run in the repository, so they are made absolute). A
command that fails stops the grid with one line naming it (exit 2); its own output is above.

With --seeds, each variant's mask transformer is trained once per seed
(`--seed_everything S`, runs named `mask_<variant>_s<S>`), and OUT/seeds.md holds each
variant's mean ± 95 % interval over its seeds (`segmo.evaluation.seeds`), overall and by
number of caption segments where `segmo evaluate` reports them. --parallel N runs N
variant/seed jobs side by side, each at one thread (on two cores, two one-thread runs
finish sooner than one after the other at two threads: the small model's matmuls do not
use two threads well).
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from segmo.cli import run
from segmo.errors import ArgumentParser, SegmoError, positive_int
from segmo.evaluation.report import compare_table, number
from segmo.files import write_atomic

# variant → (alignment method, motion segmenter, row name in the paper's Table 3)
VARIANTS: dict[str, tuple[str, str, str]] = {
    "in_sample": ("in_sample", "uniform", "SegMo"),
    "none": ("none", "uniform", "SegMo (No Align)"),
    "batch": ("batch", "uniform", "SegMo (Batch-Level Align)"),
    "global": ("global", "uniform", "SegMo (Global Align)"),
    "token": ("token", "uniform", "SegMo (Token Align)"),
    "cpd": ("in_sample", "cpd", "SegMo (CPD-based Seg)"),
    "kmeans": ("in_sample", "kmeans", "SegMo (clustering-based Seg)"),
    # Segmentation source (Fig. 4): the built-in corpus' ground-truth text segments
    # (tools/truth_segments.py, then `segmo encode-texts --segments truth`) instead of the rules.
    "truth": ("in_sample", "uniform", "SegMo (ground-truth text segments)"),
}
# Variants trained and evaluated on another text-segment source than the config's.
TEXT_SEGMENTS = {"truth": "truth"}
REPO = Path(__file__).resolve().parents[1]
SEGMO = [sys.executable, "-m", "segmo"]
# The figures of OUT/seeds.md: (metrics.json path, column title).
SEED_COLUMNS: tuple[tuple[str, str], ...] = (
    ("generation/generated/top1", "Top-1"), ("generation/generated/fid", "FID"),
    ("generation/generated/matching", "MM-Dist"), ("generation/generated/diversity", "Diversity"),
    ("action_order/generated/sequence_accuracy", "action order (sequence)"),
)


def say(line: str) -> None:
    """One whole line on stdout (jobs side by side must not interleave within a line)."""
    sys.stdout.write(line + "\n")
    sys.stdout.flush()


class Grid:
    """Runs (or prints) the commands; `ckpt` finds the last checkpoint of a run."""

    def __init__(self, args: argparse.Namespace) -> None:
        self.args = args
        self.out = Path(args.out)
        self.runs = self.out / "runs"
        # Side by side, each job gets one thread (see the module docstring).
        self.env = {**os.environ, "OMP_NUM_THREADS": "1"} if args.parallel > 1 else None

    def run(self, command: list[str], done: Path | None = None) -> None:
        line = shlex.join(command)
        if done is not None and done.exists():
            say(f"# done, skipped: {line}")
            return
        say(line)
        if self.args.dry_run:
            return
        start = time.perf_counter()
        try:
            subprocess.run(command, check=True, cwd=REPO, env=self.env)
        except subprocess.CalledProcessError as error:
            raise SegmoError(f"exit status {error.returncode}, see its output above: {line}") from None
        say(f"# {time.perf_counter() - start:.0f} s: {line[:120]}")

    def ckpt(self, run_name: str) -> str:
        if self.args.dry_run:
            return f"{self.runs}/<stage>/{run_name}/version_<k>/checkpoints/last.ckpt"
        found = sorted(self.runs.glob(f"*/{run_name}/version_*/checkpoints/last.ckpt"),
                       key=lambda p: p.stat().st_mtime)
        if not found:
            raise SegmoError(f"{self.runs}/*/{run_name}: no last.ckpt; did `segmo fit` fail?")
        return str(found[-1])

    def fit_and_export(self, stage: str, run_name: str, overrides: list[str]) -> Path:
        """Train one stage from configs/<stage>/<dataset>.yaml and export it; → model dir."""
        target = self.out / "models" / run_name
        if (target / "config.json").is_file():
            say(f"# done, skipped: training of {target}")
            return target
        steps = [] if self.args.steps is None else ["--trainer.max_steps", str(self.args.steps)]
        self.run([*SEGMO, "fit", "--config", f"configs/{stage}/{self.args.dataset}.yaml",
                  "--data.root", self.args.data, *overrides, *steps,
                  "--runs_dir", str(self.runs), "--run_name", run_name])
        self.run([*SEGMO, "export", self.ckpt(run_name), "--out", str(target)])
        return target


def main(argv: list[str] | None = None) -> None:
    """Parse the arguments, run (or print) the grid and write its tables."""
    p = ArgumentParser(prog="ablation_grid.py", description=__doc__.split("\n\n")[0],
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", required=True, help="dataset root with text segments and features")
    p.add_argument("--tokenizer", required=True, help="exported RVQ-VAE directory")
    p.add_argument("--evaluator", required=True, help="T2M evaluator directory")
    p.add_argument("--out", required=True)
    p.add_argument("--steps", type=positive_int, default=None, help="trainer.max_steps (default: the config's)")
    p.add_argument("--variants", default=",".join(VARIANTS), help=f"subset of {','.join(VARIANTS)}")
    p.add_argument("--residual", help="exported residual transformer (default: train one)")
    p.add_argument("--length", help="exported length estimator (default: train one)")
    p.add_argument("--dataset", default="synthetic", help="config name: configs/<stage>/<dataset>.yaml")
    p.add_argument("--action-classifier", help="passed to segmo evaluate")
    p.add_argument("--eval-args", default="", help="extra `segmo evaluate` flags, e.g. '--repeats 5'")
    p.add_argument("--seeds", help="training seeds of the mask transformer, e.g. 0,1,2 "
                   "(default: the config's seed, one run per variant)")
    p.add_argument("--parallel", type=positive_int, default=1, help="jobs side by side, one thread each")
    p.add_argument("--dry-run", action="store_true", help="print the commands only")
    args = p.parse_args(argv)
    variants = [v.strip() for v in args.variants.split(",") if v.strip()]
    unknown = set(variants) - set(VARIANTS)
    if unknown:
        p.error(f"--variants: unknown {sorted(unknown)}; choose from {list(VARIANTS)}")
    if not variants or len(set(variants)) < len(variants):
        p.error(f"--variants {args.variants!r}: expected different variants separated by commas")
    try:
        seeds = [None] if args.seeds is None else [int(x) for x in args.seeds.split(",") if x.strip()]
    except ValueError:
        p.error(f"--seeds {args.seeds!r}: expected whole numbers separated by commas, e.g. 0,1,2")
    if not seeds:
        p.error("--seeds: no seed given")
    if len(set(seeds)) < len(seeds) or any(s is not None and s < 0 for s in seeds):
        p.error(f"--seeds {args.seeds!r}: expected different whole numbers >= 0")
    try:
        shlex.split(args.eval_args)  # before hours of training, not after
    except ValueError as error:
        p.error(f"--eval-args {args.eval_args!r}: {error}")
    # The commands run in the repository (the configs' paths are relative to it): the
    # user's paths, relative to where the tool was called, are made absolute.
    for flag in ("data", "tokenizer", "evaluator", "out", "residual", "length", "action_classifier"):
        if getattr(args, flag) is not None:
            setattr(args, flag, str(Path(getattr(args, flag)).resolve()))
    if not args.dry_run:
        for flag in ("data", "tokenizer", "evaluator"):
            if not Path(getattr(args, flag)).is_dir():
                p.error(f"--{flag} {getattr(args, flag)}: no such directory")
        for variant in variants:
            source = TEXT_SEGMENTS.get(variant)
            if source and not (Path(args.data) / "text_segments" / source).is_dir():
                p.error(f"--variants {variant}: {args.data}/text_segments/{source} is missing; run "
                        f"tools/truth_segments.py --data {args.data}, then segmo encode-texts "
                        f"--data {args.data} --encoder minilm --segments {source}")

    grid = Grid(args)
    tokenizer = ["--model.init_args.tokenizer", args.tokenizer]
    residual = args.residual or str(grid.fit_and_export("residual", "residual", tokenizer))
    length = args.length or str(grid.fit_and_export("length", "length", []))
    extra = ["--action-classifier", args.action_classifier] if args.action_classifier else []

    def job(variant: str, seed: int | None) -> tuple[str, int | None, Path]:
        alignment, segmenter, title = VARIANTS[variant]
        name = variant if seed is None else f"{variant}_s{seed}"
        seeded = [] if seed is None else ["--seed_everything", str(seed)]
        source = TEXT_SEGMENTS.get(variant)
        mask = grid.fit_and_export("mask", f"mask_{name}", [
            *tokenizer, "--model.init_args.alignment", alignment,
            "--model.init_args.segmenter", segmenter, *seeded,
            *(["--data.text_segments", source] if source else [])])
        bundle = grid.out / "bundles" / name
        grid.run([*SEGMO, "bundle", "--tokenizer", args.tokenizer, "--mask", str(mask),
                  "--residual", residual, "--length", length, "--out", str(bundle)],
                 done=bundle / "segmo.json")
        evaluation = grid.out / "eval" / name
        grid.run([*SEGMO, "evaluate", "--model", str(bundle), "--data", args.data,
                  "--evaluator", args.evaluator, "--name", title, "--out", str(evaluation),
                  *(["--text-segments", source] if source else []),
                  *extra, *shlex.split(args.eval_args)], done=evaluation / "metrics.json")
        return variant, seed, evaluation / "metrics.json"

    jobs = [(v, s) for v in variants for s in seeds]
    with ThreadPoolExecutor(max_workers=args.parallel) as pool:
        done = list(pool.map(lambda vs: job(*vs), jobs))
    if args.dry_run:
        return
    first = {v: path for v, s, path in done if s == seeds[0]}
    table = compare_table([(VARIANTS[v][2], json.loads(first[v].read_text())) for v in variants])
    write_atomic(grid.out / "table3.md", table + "\n")
    print(table)
    grid_rows = {v: json.loads(first[v].read_text()) for v in variants if v in TRAIN_SEGMENTERS}
    if len(grid_rows) > 1:
        write_atomic(grid.out / "isc_grid.md", isc_grid(grid_rows) + "\n")
        print(isc_grid(grid_rows))
    if seeds != [None]:
        runs = {v: [json.loads(path.read_text()) for vv, _, path in done if vv == v] for v in variants}
        write_atomic(grid.out / "seeds.md", seeds_report(runs) + "\n")
        print(seeds_report(runs))


# The variants that differ only in the motion segmenter of the alignment loss (Fig. 4's rows).
TRAIN_SEGMENTERS = ("in_sample", "cpd", "kmeans")


def isc_grid(evaluations: dict[str, dict]) -> str:
    """The paper's Fig. 4 as a table (OUT/isc_grid.md): a row per training segmenter (the
    in_sample, cpd and kmeans variants), a column per evaluation segmenter; cells "ISC (CV)"
    from each evaluation's `isc` section."""
    columns = sorted({name for m in evaluations.values() for name in m.get("isc", {})})
    lines = ["| trained with \\ evaluated with | " + " | ".join(columns) + " |",
             "| --- |" + " --- |" * len(columns)]
    for variant, metrics in evaluations.items():
        isc = metrics.get("isc", {})
        cells = [f"{number(isc[c]['mean']):.3f} (CV {number(isc[c]['cv']):.2f})" if c in isc else "–"
                 for c in columns]
        lines.append(f"| {VARIANTS[variant][1]} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def seeds_report(runs: dict[str, list[dict]]) -> str:
    """OUT/seeds.md: real, reconstruction and each variant's generated row over its seeds,
    overall and per number of caption segments (`segmo evaluate`'s `by_num_segments`)."""
    from segmo.evaluation.seeds import seed_table

    titles = [t for _, t in SEED_COLUMNS]
    first = next(iter(runs.values()))

    def paths(row: str, bucket: str | None) -> list[str]:
        out = []
        for path, _ in SEED_COLUMNS:
            section, _, metric = path.split("/")
            where = f"{section}/by_num_segments/{bucket}" if bucket else section
            out.append(f"{where}/{row}/{metric}")
        return out

    def table(bucket: str | None) -> str:
        rows = [("real motions", first[:1], paths("real", bucket)),
                ("tokenizer reconstruction", first[:1], paths("reconstruction", bucket))]
        rows += [(VARIANTS[v][2], r, paths("generated", bucket)) for v, r in runs.items()]
        return seed_table(rows, titles)

    parts = ["Mean ± 95 % interval over training seeds (Student t); the real and reconstruction "
             "rows do not depend on the mask transformer's seed.", "", "All captions:", "", table(None)]
    for bucket in first[0].get("generation", {}).get("by_num_segments", {}):
        parts += ["", f"Captions with {bucket} text segment(s):", "", table(bucket)]
    return "\n".join(parts)

if __name__ == "__main__":
    run("ablation_grid.py", main, sys.argv[1:])
