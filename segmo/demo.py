"""`segmo demo`: the whole flow on the built-in corpus, end to end, on a CPU.

build corpus → extract text segments (rule) → cache text features (MiniLM) → train the
tokenizer, the mask transformer (with segment alignment), the residual transformer and
the length estimator with the `configs/*/synthetic.yaml` recipes → export and bundle →
generate motions for a few prompts → render GIFs and a grounding map.

The demo keeps to a wall-clock budget (``--budget 20m`` by default): each training stage
gets a share of what is left when it starts (Lightning's ``max_time``), so that the demo
ends in about the budget on a slow host and trains longer on a fast one, up to the
synthetic recipes' own step counts. ``--budget quick`` is the test suite's smoke run
(two steps a stage). Each step prints the equivalent stand-alone command and is skipped
when its output already exists, so an interrupted demo resumes where it stopped. Outputs:

    OUT/corpus/          the built-in corpus (HumanML3D layout)
    OUT/runs/<stage>/    training runs (logs, checkpoints, resolved configs)
    OUT/models/<stage>/  exported stage models
    OUT/model/           the SegMo bundle (`segmo.SegMo.from_pretrained`)
    OUT/samples/         generated motions: .npy, .gif, .bvh
    OUT/grounding.png    a grounding similarity map (paper Fig. 5)
"""

from __future__ import annotations

import argparse
import json
import logging
import re
import time
from dataclasses import dataclass
from importlib.resources import files
from pathlib import Path

import torch

from segmo.data.layout import read_ground_truth, read_motion, read_split
from segmo.errors import ArgumentParser, SegmoError, non_negative_int
from segmo.export import export
from segmo.files import output_folder
from segmo.pipeline import SegMo
from segmo.pipeline.grounding import plot_similarity_map
from segmo.synth import build_corpus
from segmo.synth.sequence import VERSION
from segmo.text.cache import update_cache
from segmo.text.extract import segment_folder
from segmo.text.rules import RuleSegmenter

# The top-level configs/ folder, shipped inside the package (pyproject.toml maps it to
# segmo._configs), so that an installed segmo runs the demo as well as a source checkout.
CONFIGS = files("segmo._configs")

# Decoding steps and guided residual layers of the demo's bundle, from the steps × quality
# curve on corpus v3 (README, "Generation speed on a CPU"), and its base-token guidance
# scale, from the scale curve of two training seeds (README, "MLA-Gen's guidance and
# priors"): on the built-in corpus 2 beats MoMask's 4 on every metric.
CORPUS_STEPS = 4
CORPUS_GUIDED_LAYERS = 2
CORPUS_GUIDANCE_SCALE = 2.0

PROMPTS = [
    "a person walks forward, then waves with the right hand.",
    "someone jumps twice and then sits down.",
    "a man turns left after walking, then runs.",
    "a person kicks with the left foot while standing.",
]


@dataclass(frozen=True)
class Budget:
    """Corpus size and how long each stage trains: `seconds` of wall clock for the whole
    demo (None: exactly `*_steps` steps a stage), the stages' steps as a cap."""

    num_motions: int
    rvq_steps: int
    mask_steps: int
    residual_steps: int
    length_epochs: int
    seconds: float | None = None


# Each training stage's share of the time left when it starts (of the stages still to come).
SHARES = {"rvq": 0.30, "mask": 0.45, "residual": 0.20, "length": 0.05}
# Seconds kept back for generating, rendering and grounding at the end, and for each
# stage's start-up and export (measured: 25-40 s and 5-15 s on 2 cores).
RESERVE_END, RESERVE_STAGE = 45.0, 15.0
QUICK = Budget(num_motions=24, rvq_steps=2, mask_steps=2, residual_steps=2, length_epochs=1)


def timed_budget(seconds: float) -> Budget:
    """The demo on a wall-clock budget: the synthetic recipes' step counts as caps."""
    return Budget(num_motions=1000, rvq_steps=6000, mask_steps=6000, residual_steps=4000,
                  length_epochs=30, seconds=seconds)


def parse_budget(text: str) -> Budget:
    """`--budget`: "quick", or a duration such as 20m, 90s, 1h30m, 1200 (seconds)."""
    if text == "quick":
        return QUICK
    match = re.fullmatch(r"\s*(?:(\d+(?:\.\d+)?)h)?\s*(?:(\d+(?:\.\d+)?)m)?\s*(?:(\d+(?:\.\d+)?)s?)?\s*",
                         text)
    if not text.strip() or not match or not any(match.groups()):
        raise argparse.ArgumentTypeError(f"expected 'quick' or a duration like 20m, 90s or 1h30m, "
                                         f"got {text!r}")
    hours, minutes, seconds = (float(g) if g else 0.0 for g in match.groups())
    total = 3600 * hours + 60 * minutes + seconds
    if total < 120:
        raise argparse.ArgumentTypeError(f"a budget of {text!r} is under the 2 minutes the fixed "
                                         "steps (corpus, text features, rendering) take")
    return timed_budget(total)


def _step(title: str, command: str) -> float:
    print(f"\n==> {title}\n    $ {command}", flush=True)
    return time.perf_counter()


def _done(start: float, timings: dict[str, float], key: str) -> None:
    timings[key] = time.perf_counter() - start
    print(f"    done in {timings[key]:.0f} s", flush=True)


def _train(stage: str, root: Path, out: Path, overrides: list[str],
           max_seconds: float | None = None) -> Path:
    """`segmo fit` one synthetic config, then `segmo export` its last weights. With
    `max_seconds`, training stops when that time is up (or at the step cap)."""
    # Lightning takes seconds to import: kept out of `segmo demo --help`.
    from segmo.training.cli import main as fit

    # Lightning's banners and model tables would drown the demo's own progress lines.
    logging.getLogger("lightning.pytorch").setLevel(logging.WARNING)

    model_dir = out / "models" / stage
    if (model_dir / "config.json").is_file():
        print(f"    {model_dir} exists, skipped")
        return model_dir
    if max_seconds is not None:
        seconds = max(int(max_seconds), 10)
        overrides = [*overrides, f"--trainer.max_time=00:{seconds // 3600:02d}:"
                                 f"{seconds % 3600 // 60:02d}:{seconds % 60:02d}"]
        print(f"    training for at most {seconds} s", flush=True)
    cli = fit(["fit", "--config", str(CONFIGS / stage / "synthetic.yaml"),
               f"--data.root={root}", f"--runs_dir={out / 'runs'}", "--run_name=demo",
               "--trainer.enable_model_summary=false", *overrides])
    # Stopped by the clock, the run may end between checkpoints: save the final weights.
    final = Path(cli.trainer.default_root_dir) / "final.ckpt"
    cli.trainer.save_checkpoint(final)
    print(f"    trained {cli.trainer.global_step} steps", flush=True)
    export(final, model_dir)
    return model_dir


def _check_same_corpus(root: Path, num_motions: int, seed: int) -> None:
    """Refuse to resume a demo whose corpus was built with another seed, size or version:
    its trained stages are skipped on resuming, so the new settings would be ignored (or
    the corpus rebuilt under models trained on the old one)."""
    try:
        built = json.loads((root / "corpus.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return  # none yet (or unreadable: build_corpus says so)
    wanted = {"version": VERSION, "seed": seed, "num_motions": num_motions}
    if isinstance(built, dict) and any(built.get(k) != v for k, v in wanted.items()):
        raise SegmoError(
            f"{root.parent}: holds an earlier demo on corpus version {built.get('version')}, "
            f"seed {built.get('seed')}, {built.get('num_motions')} motions; this one asks for "
            f"version {VERSION}, seed {seed}, {num_motions} motions. A demo resumes only its "
            "own run: give another --out, or delete that folder")


def run(out: Path, budget: Budget, seed: int = 0) -> dict[str, float]:
    out.mkdir(parents=True, exist_ok=True)
    root = out / "corpus"
    timings: dict[str, float] = {}
    start = time.perf_counter()

    def steps(n: int) -> list[str]:
        # Validate once, on the last step, so that last.ckpt holds the final weights.
        return [f"--trainer.max_steps={n}", "--trainer.max_epochs=-1",
                "--trainer.check_val_every_n_epoch=null", f"--trainer.val_check_interval={n}"]

    def seconds_for(stage: str) -> float | None:
        """This stage's share of the time left (None: no time budget)."""
        if budget.seconds is None:
            return None
        later = list(SHARES)[list(SHARES).index(stage):]
        left = (budget.seconds - (time.perf_counter() - start) - RESERVE_END
                - RESERVE_STAGE * len(later))
        return max(left, 0.0) * SHARES[stage] / sum(SHARES[s] for s in later)

    t = _step("1/8 build the built-in corpus",
              f"segmo synth --out {root} --num-motions {budget.num_motions} --seed {seed}")
    _check_same_corpus(root, budget.num_motions, seed)
    build_corpus(root, budget.num_motions, seed)  # returns at once when the corpus is whole
    _done(t, timings, "corpus")

    t = _step("2/8 extract text segments", f"segmo segment-texts --data {root} --backend rule")
    segment_folder(root, RuleSegmenter(), "rule")
    _done(t, timings, "segment_texts")

    t = _step("3/8 cache text features",
              f"segmo encode-texts --data {root} --encoder minilm --segments rule")
    update_cache(root, "minilm", segments=["rule"])
    _done(t, timings, "encode_texts")

    t = _step("4/8 train the RVQ-VAE tokenizer",
              f"segmo fit --config configs/rvq/synthetic.yaml --data.root {root}")
    tokenizer = _train("rvq", root, out, steps(budget.rvq_steps), seconds_for("rvq"))
    _done(t, timings, "rvq")

    tok = [f"--model.init_args.tokenizer={tokenizer}"]
    t = _step("5/8 train the mask transformer with segment alignment",
              f"segmo fit --config configs/mask/synthetic.yaml --data.root {root} "
              f"--model.init_args.tokenizer {tokenizer}")
    mask = _train("mask", root, out, [*tok, *steps(budget.mask_steps)], seconds_for("mask"))
    _done(t, timings, "mask")

    t = _step("6/8 train the residual transformer",
              f"segmo fit --config configs/residual/synthetic.yaml --data.root {root} "
              f"--model.init_args.tokenizer {tokenizer}")
    residual = _train("residual", root, out, [*tok, *steps(budget.residual_steps)],
                      seconds_for("residual"))
    _done(t, timings, "residual")

    t = _step("7/8 train the length estimator",
              f"segmo fit --config configs/length/synthetic.yaml --data.root {root}")
    length = _train("length", root, out, [f"--trainer.max_epochs={budget.length_epochs}"],
                    seconds_for("length"))
    _done(t, timings, "length")

    t = _step("8/8 bundle, generate, render and ground",
              f"segmo bundle --tokenizer {tokenizer} --mask {mask} --residual {residual} "
              f"--length {length} --out {out / 'model'}")
    _generate_and_render(out, root, tokenizer, mask, residual, length, seed)
    _done(t, timings, "generate")
    return timings


def _generate_and_render(out: Path, root: Path, tokenizer: Path, mask: Path, residual: Path,
                         length: Path, seed: int) -> None:
    # matplotlib on use, and its file backend chosen before pyplot is imported.
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    model = SegMo.from_stages(tokenizer=str(tokenizer), mask=str(mask), residual=str(residual),
                              length=str(length))
    # The sampling defaults measured on the built-in corpus (README, "Generation speed"):
    # the fewest passes whose metrics stay within the 95 % interval of 10 guided steps,
    # and the guidance scale of the scale curve.
    model.config.steps, model.config.residual_guided_layers = CORPUS_STEPS, CORPUS_GUIDED_LAYERS
    model.config.guidance_scale = CORPUS_GUIDANCE_SCALE
    model.save_pretrained(out / "model")
    result = model.generate(PROMPTS, generator=torch.Generator().manual_seed(seed))
    samples = out / "samples"
    result.save(samples)
    print(f"    generated {len(PROMPTS)} motions -> {samples}")

    # Ground a multi-segment test caption in its real motion.
    for motion_id in read_split(root, "test"):
        caption = read_ground_truth(root, motion_id)["captions"][0]
        if len(caption["segments"]) >= 2:
            break
    features = read_motion(root, motion_id)
    # The default search, one span per segment in caption order: the paper's 5-token window
    # is far shorter than the corpus's segments, so no window could overlap a true span well.
    grounding = model.ground(caption["text"], features,
                             segments=[s["text"] for s in caption["segments"]])
    truth = [(s["start"], s["end"]) for s in caption["segments"]]
    ax = plot_similarity_map(grounding, title=caption["text"],
                             truth=truth if len(truth) == len(grounding.segments) else None)
    ax.figure.savefig(out / "grounding.png", dpi=100, bbox_inches="tight")
    plt.close(ax.figure)
    for text, span, truth_segment in zip(grounding.segments, grounding.best_spans_frames,
                                         caption["segments"]):
        print(f"    ground {text!r}: frames {span}, truth {truth_segment['start']}-{truth_segment['end']}")


def main(argv: list[str] | None = None) -> None:
    parser = ArgumentParser(prog="segmo demo", description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=output_folder, default="runs/demo", help="output folder")
    parser.add_argument("--budget", type=parse_budget, default="20m",
                        help="wall-clock time for the whole demo, e.g. 20m (default), 45m, 1h; "
                             "quick: a smoke run for the tests")
    parser.add_argument("--seed", type=non_negative_int, default=0)
    args = parser.parse_args(argv)
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        parser.error(f"--out {out}: exists and is not a folder")
    start = time.perf_counter()
    timings = run(out, args.budget, args.seed)
    total = time.perf_counter() - start
    print("\nTimings: " + ", ".join(f"{k} {v:.0f} s" for k, v in timings.items())
          + f"; total {total / 60:.1f} min")
    print(f"Outputs in {out}: model/ (load with segmo.SegMo.from_pretrained), samples/ "
          "(npy, gif, bvh), grounding.png, runs/ (logs), corpus/")


if __name__ == "__main__":
    main()
