"""The paper's Table 3 ablation: one mask transformer per alignment / segmentation variant,
the same tokenizer, residual transformer and length estimator, evaluated the same way.

    python tools/ablation_grid.py --data data/synth --tokenizer models/rvq \\
        --evaluator models/evaluator --out runs/ablation [--steps 2000] \\
        [--variants in_sample,none,batch,global,token,cpd,kmeans] \\
        [--residual models/residual --length models/length] [--dry-run]

For each variant: `segmo fit --config configs/mask/<dataset>.yaml` with
`--model.init_args.alignment X --model.init_args.segmenter Y` (and `--trainer.max_steps N`
when --steps is given), `segmo export` of its last checkpoint, `segmo bundle` with the
shared stages, `segmo evaluate`. The residual transformer and length estimator are
trained once when not given. Every step whose output exists is skipped, so an interrupted
grid resumes. Writes OUT/table3.md (Real row + one row per variant, the paper's format).
--dry-run prints the commands without running anything.
"""

from __future__ import annotations

import argparse
import json
import shlex
import subprocess
import sys
import time
from pathlib import Path

# variant → (alignment method, motion segmenter, row name in the paper's Table 3)
VARIANTS: dict[str, tuple[str, str, str]] = {
    "in_sample": ("in_sample", "uniform", "SegMo"),
    "none": ("none", "uniform", "SegMo (No Align)"),
    "batch": ("batch", "uniform", "SegMo (Batch-Level Align)"),
    "global": ("global", "uniform", "SegMo (Global Align)"),
    "token": ("token", "uniform", "SegMo (Token Align)"),
    "cpd": ("in_sample", "cpd", "SegMo (CPD-based Seg)"),
    "kmeans": ("in_sample", "kmeans", "SegMo (clustering-based Seg)"),
}
REPO = Path(__file__).resolve().parents[1]
SEGMO = [sys.executable, "-m", "segmo"]


class Grid:
    """Runs (or prints) the commands; `ckpt` finds the last checkpoint of a run."""

    def __init__(self, args: argparse.Namespace) -> None:
        self.args = args
        self.out = Path(args.out)
        self.runs = self.out / "runs"

    def run(self, command: list[str], done: Path | None = None) -> None:
        line = shlex.join(command)
        if done is not None and done.exists():
            print(f"# done, skipped: {line}", flush=True)
            return
        print(line, flush=True)
        if self.args.dry_run:
            return
        start = time.perf_counter()
        subprocess.run(command, check=True, cwd=REPO)
        print(f"# {time.perf_counter() - start:.0f} s", flush=True)

    def ckpt(self, run_name: str) -> str:
        if self.args.dry_run:
            return f"{self.runs}/<stage>/{run_name}/version_<k>/checkpoints/last.ckpt"
        found = sorted(self.runs.glob(f"*/{run_name}/version_*/checkpoints/last.ckpt"),
                       key=lambda p: p.stat().st_mtime)
        if not found:
            raise FileNotFoundError(f"{self.runs}/*/{run_name}: no last.ckpt; did `segmo fit` fail?")
        return str(found[-1])

    def fit_and_export(self, stage: str, run_name: str, overrides: list[str]) -> Path:
        """Train one stage from configs/<stage>/<dataset>.yaml and export it; → model dir."""
        target = self.out / "models" / run_name
        if (target / "config.json").is_file():
            print(f"# done, skipped: training of {target}", flush=True)
            return target
        steps = [] if self.args.steps is None else ["--trainer.max_steps", str(self.args.steps)]
        self.run([*SEGMO, "fit", "--config", f"configs/{stage}/{self.args.dataset}.yaml",
                  "--data.root", self.args.data, *overrides, *steps,
                  "--runs_dir", str(self.runs), "--run_name", run_name])
        self.run([*SEGMO, "export", self.ckpt(run_name), "--out", str(target)])
        return target


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", required=True, help="dataset root with text segments and features")
    p.add_argument("--tokenizer", required=True, help="exported RVQ-VAE directory")
    p.add_argument("--evaluator", required=True, help="T2M evaluator directory")
    p.add_argument("--out", required=True)
    p.add_argument("--steps", type=int, default=None, help="trainer.max_steps (default: the config's)")
    p.add_argument("--variants", default=",".join(VARIANTS), help=f"subset of {','.join(VARIANTS)}")
    p.add_argument("--residual", help="exported residual transformer (default: train one)")
    p.add_argument("--length", help="exported length estimator (default: train one)")
    p.add_argument("--dataset", default="synthetic", help="config name: configs/<stage>/<dataset>.yaml")
    p.add_argument("--action-classifier", help="passed to segmo evaluate")
    p.add_argument("--eval-args", default="", help="extra `segmo evaluate` flags, e.g. '--repeats 5'")
    p.add_argument("--dry-run", action="store_true", help="print the commands only")
    args = p.parse_args(argv)
    variants = [v for v in args.variants.split(",") if v]
    unknown = set(variants) - set(VARIANTS)
    if unknown:
        p.error(f"--variants: unknown {sorted(unknown)}; choose from {list(VARIANTS)}")
    if not args.dry_run:
        for flag in ("data", "tokenizer", "evaluator"):
            if not Path(getattr(args, flag)).exists():
                p.error(f"--{flag} {getattr(args, flag)}: no such directory")

    grid = Grid(args)
    tokenizer = ["--model.init_args.tokenizer", args.tokenizer]
    residual = args.residual or str(grid.fit_and_export("residual", "residual", tokenizer))
    length = args.length or str(grid.fit_and_export("length", "length", []))
    rows = []
    for variant in variants:
        alignment, segmenter, title = VARIANTS[variant]
        mask = grid.fit_and_export("mask", f"mask_{variant}", [
            *tokenizer, "--model.init_args.alignment", alignment,
            "--model.init_args.segmenter", segmenter])
        bundle = grid.out / "bundles" / variant
        grid.run([*SEGMO, "bundle", "--tokenizer", args.tokenizer, "--mask", str(mask),
                  "--residual", residual, "--length", length, "--out", str(bundle)],
                 done=bundle / "segmo.json")
        evaluation = grid.out / "eval" / variant
        extra = ["--action-classifier", args.action_classifier] if args.action_classifier else []
        grid.run([*SEGMO, "evaluate", "--model", str(bundle), "--data", args.data,
                  "--evaluator", args.evaluator, "--name", title, "--out", str(evaluation),
                  *extra, *shlex.split(args.eval_args)], done=evaluation / "metrics.json")
        rows.append((title, evaluation / "metrics.json"))
    if args.dry_run:
        return
    sys.path.insert(0, str(REPO))
    from segmo.evaluation.report import compare_table

    table = compare_table([(title, json.loads(path.read_text())) for title, path in rows])
    (grid.out / "table3.md").write_text(table + "\n")
    print(table)


if __name__ == "__main__":
    main()
