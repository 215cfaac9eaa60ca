"""Benchmark a training step of the mask stage: on cached motion tokens, with on-the-fly
encoding (the path before the cache), and the MoMask reference's step, in one run.

    OMP_NUM_THREADS=1 python tools/bench_train.py --threads 1
    python tools/bench_train.py --threads 2 --rounds 8

Sizes: the model and batch of configs/mask/synthetic.yaml (dim 256, depth 4, 4 heads, FFN
512, batch 32, in-sample alignment over uniform segments) and the tokenizer of
configs/rvq/synthetic.yaml (width 128, 256 codes, 6 quantizers), randomly initialised: a
step's cost does not depend on the weights. Data: a random HumanML3D-layout folder
(`--motions` motions of 40..196 frames, two captions each, rule text segments, a text-
feature cache of random vectors) in a temporary folder, or `--data DIR` with a built cache
(`--text-features NAME`).

A step is what `segmo fit` runs per batch: the next batch from the DataLoader (samples
read, cropped and collated; no workers), the forward pass and losses, backward, AdamW.
- cached: `MaskTask.step` on a batch carrying cached tokens (motion_tokens=cached);
- on_the_fly: the same with the batch encoded by the frozen tokenizer (the path before);
- grouped: cached, with batches of similar length (`data.group_by_length`): a batch pads
  to its own longest clip instead of nearly the longest of the corpus;
- with --bf16, cached_bf16 and grouped_bf16: the same under bf16-mixed autocast (what
  `--trainer.precision bf16-mixed` trains), fast only where the CPU has native bf16;
- with --compile, grouped_compiled: grouped, on a copy of the model (same weights) whose
  trunk blocks run under `torch.compile` (inductor, dynamic shapes); it compiles during
  the warm-up (about a minute of one core), which the figure leaves out;
- momask: the MoMask reference's mask-transformer step at the same sizes: the frozen
  VQ-VAE encodes the motion batch, then its post-norm `nn.TransformerEncoder`
  (`bench_generate.momask_models`, sequence-first, one condition token) predicts the
  masked tokens, cross-entropy, backward, AdamW. MoMask also runs CLIP on every caption
  every step; here it gets the cached text vectors instead (`clip_replaced_by_cache`), so
  its figure is a lower bound of its real step time. It has no segments and no alignment;
- with --momask-grouped, momask_grouped: the same MoMask model and step on the cheap path's
  batches (cached tokens, grouped by length), so that grouped against it is the cost of
  this project's model per token (its text prefix of segments, its alignment loss) apart
  from the data path.
The variants are interleaved (A B C A B C ...) and each figure is the median of per-step
times; `throughput` gives steps per second over all timed steps (1 / mean step time) and
the speed-ups by it. The two differ for the grouped step, whose batches are as long as
their length group: its median is the step of the median group, its mean what an epoch
takes (on the built-in corpus, where one clip in seven is 40 frames long, the mean is
the lower). Also printed: the share of a cached step spent on the data, on the alignment
loss's motion side (spans), forward and backward; and how many tokens of an on-the-fly
batch differ from the cached tokens of the same crops (the zero padding of a batch
reaches the last tokens of its shorter motions through the convolutions). The last line
is JSON.
"""

from __future__ import annotations

import argparse
import copy
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_generate import momask_models  # noqa: E402

from segmo import cpu  # noqa: E402
from segmo.data.datamodule import MotionDataModule  # noqa: E402
from segmo.data.motion_tokens import MotionTokenCache, update_motion_tokens  # noqa: E402
from segmo.models.mask_transformer import cosine_schedule  # noqa: E402
from segmo.models.tokenizer import RVQVAE, RVQConfig  # noqa: E402
from segmo.segmentation import segment_batch  # noqa: E402
from segmo.tasks.common import text_condition, token_lengths  # noqa: E402
from segmo.tasks.mask import MaskTask  # noqa: E402
from segmo.text.encoders import TextEncoder, TextEncoding  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
CAPTIONS = ["a person walks forward, then waves.", "someone jumps twice and then sits down.",
            "a man turns left after walking.", "the figure claps three times.",
            "a person runs, then stops, then bows.", "a woman kicks with her right foot."]


class RandomEncoder(TextEncoder):
    """Random fixed vectors per text: the cache's format without a text model."""

    def __init__(self, name: str, dim: int) -> None:
        super().__init__(name, torch.nn.Identity(), None, dim, 32, "random")

    def encode(self, texts, batch_size=64):
        g = torch.Generator().manual_seed(len(texts))
        sentence = torch.randn(len(texts), self.dim, generator=g)
        return TextEncoding(sentence, sentence[:, None], torch.ones(len(texts), 1, dtype=torch.bool))


def random_corpus(root: Path, motions: int, text_dim: int) -> None:
    from segmo.text.cache import update_cache
    from segmo.text.extract import segment_folder
    from segmo.text.rules import RuleSegmenter

    rng = np.random.default_rng(0)
    for folder in ("new_joint_vecs", "texts"):
        (root / folder).mkdir(parents=True)
    ids = [f"{i:06d}" for i in range(motions)]
    for k, mid in enumerate(ids):
        frames = int(rng.integers(40, 197))
        np.save(root / "new_joint_vecs" / f"{mid}.npy",
                rng.standard_normal((frames, 263)).astype(np.float32))
        lines = [CAPTIONS[(k + j) % len(CAPTIONS)] for j in range(2)]
        (root / "texts" / f"{mid}.txt").write_text(
            "".join(f"{c}#{' '.join(w + '/OTHER' for w in c.split())}#0.0#0.0\n" for c in lines))
    np.save(root / "Mean.npy", np.zeros(263, dtype=np.float32))
    np.save(root / "Std.npy", np.ones(263, dtype=np.float32))
    for split in ("train", "val", "test"):
        (root / f"{split}.txt").write_text("\n".join(ids) + "\n")
    segment_folder(root, RuleSegmenter(), "rule", progress=False)
    update_cache(root, RandomEncoder("random", text_dim), segments=["rule"], progress=False)


def init_args(stage: str) -> dict:
    return yaml.safe_load((REPO / "configs" / stage / "synthetic.yaml").read_text())["model"]["init_args"]


def fill_codebooks(rvq: RVQVAE, root: Path) -> None:
    """Codebooks of encoder outputs (as the quantizer initialises them from a first batch),
    so that codes spread over the codebook as a trained tokenizer's do; zero codebooks
    would give every token code 0."""
    from segmo.data.humanml3d import MotionDataset

    ds = MotionDataset(root, "train", max_motions=64)
    with torch.no_grad():
        latents = torch.cat([rvq.eval().latents(ds.crop(i, 0)[None])[0] for i in range(len(ds))])
        g = torch.Generator().manual_seed(0)
        residual = latents
        for layer in range(rvq.num_quantizers):
            pick = torch.randint(0, len(residual), (rvq.codebook_size,), generator=g)
            rvq.quantizer.codebooks[layer] = residual[pick]
            residual = residual - rvq.quantizer.codebooks[layer][
                rvq.quantizer.nearest(layer, residual)]
        rvq.quantizer.initialised.fill_(True)


class MoMaskStep(torch.nn.Module):
    """MoMask's mask-transformer training step around `momask_models`: token embedding,
    condition projection, learned positions, the post-norm trunk, the output head."""

    def __init__(self, dim: int, depth: int, heads: int, ff_dim: int, codes: int,
                 text_dim: int, max_tokens: int = 50) -> None:
        super().__init__()
        self.trunk, self.head = momask_models(dim, depth, heads, ff_dim, codes)
        self.trunk.train(), self.head.train()
        self.codes = codes
        self.embed = torch.nn.Embedding(codes + 2, dim)  # + [MASK], [PAD]
        self.cond = torch.nn.Linear(text_dim, dim)
        self.position = torch.nn.Parameter(torch.zeros(max_tokens + 1, 1, dim))

    def forward(self, base: torch.Tensor, valid: torch.Tensor, sentence: torch.Tensor) -> torch.Tensor:
        b, n = base.shape
        lengths = valid.sum(1)
        count = torch.round(cosine_schedule(torch.rand(b)) * lengths).clamp(min=1)
        ranks = torch.rand(b, n).masked_fill(~valid, 2.0).argsort(1).argsort(1)
        target = ranks < count[:, None]
        inputs = torch.where(target, self.codes, base).masked_fill(~valid, self.codes + 1)
        x = torch.cat([self.cond(sentence)[None], self.embed(inputs).transpose(0, 1)])  # (1 + n, b, dim)
        x = x + self.position[: n + 1]
        padding = torch.cat([torch.zeros(b, 1, dtype=torch.bool), ~valid], 1)
        logits = self.head(self.trunk(x, src_key_padding_mask=padding)[1:]).transpose(0, 1)
        return torch.nn.functional.cross_entropy(logits[target], base[target])


def step_figures(times: dict[str, list[dict]]) -> dict:
    """Steps per second, ms per step and the speed-ups against "on_the_fly" (the path before
    the cache) and "momask" from each variant's per-step times (`{"total": seconds, ...}`):
    by the median step, and under "throughput" by all steps (1 / mean step time)."""
    def figures(statistic) -> dict:
        step = {name: statistic([t["total"] for t in steps]) for name, steps in times.items()}
        others = [name for name in times if name not in ("on_the_fly", "momask")]
        return {"steps_per_s": {name: round(1 / step[name], 2) for name in times},
                "ms_per_step": {name: round(1000 * step[name], 1) for name in times},
                "speedup_vs_on_the_fly": {name: round(step["on_the_fly"] / step[name], 2)
                                          for name in others},
                "speedup_vs_momask": {name: round(step["momask"] / step[name], 2)
                                      for name in others}}

    by_median = figures(statistics.median)
    return {**by_median,
            "speedup_cached_vs_on_the_fly": by_median["speedup_vs_on_the_fly"]["cached"],
            "speedup_cached_vs_momask": by_median["speedup_vs_momask"]["cached"],
            "throughput": figures(statistics.fmean)}


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--rounds", type=int, default=6, help="A B C rounds")
    parser.add_argument("--steps", type=int, default=4, help="steps of each variant per round")
    parser.add_argument("--motions", type=int, default=256)
    parser.add_argument("--data", type=Path, help="a dataset folder with a text-feature cache")
    parser.add_argument("--text-features", default="random")
    parser.add_argument("--bf16", action="store_true",
                        help="also time the cached step in bf16-mixed (torch.autocast), as "
                             "`--trainer.precision bf16-mixed` trains")
    parser.add_argument("--compile", action="store_true",
                        help="also time the grouped step with the trunk blocks under "
                             "torch.compile (compiles during the warm-up)")
    parser.add_argument("--momask-grouped", action="store_true",
                        help="also time the MoMask reference's model on the grouped, cached "
                             "batches")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    mask_args, rvq_args = init_args("mask"), init_args("rvq")
    with tempfile.TemporaryDirectory() as tmp:
        root = args.data
        if root is None:
            root = Path(tmp) / "data"
            random_corpus(root, args.motions, mask_args["text_dim"])
        rvq = RVQVAE(RVQConfig(feature_dim=263, **{k: rvq_args[k] for k in (
            "width", "code_dim", "depth", "dilation_growth", "codebook_size", "num_quantizers")}))
        fill_codebooks(rvq, root)
        rvq.save_pretrained(Path(tmp) / "rvq")
        task = MaskTask(**{**mask_args, "tokenizer": str(Path(tmp) / "rvq"), "max_segments": 5})
        task.train()
        optimizer = task.configure_optimizers()["optimizer"]
        modules = {}
        for mode in ("cached", "on_the_fly", "grouped"):
            dm = MotionDataModule(str(root), batch_size=32, text_segments="rule",
                                  text_features=args.text_features, max_segments=5,
                                  group_by_length=mode == "grouped")
            dm.setup("fit")
            if mode != "on_the_fly":
                build = update_motion_tokens(root, task.tokenizer, "random", [dm.dataset("train")],
                                             progress=False)
                dm.dataset("train").motion_tokens = MotionTokenCache(build.folder)
            modules[mode] = dm
        batches = {mode: iter(()) for mode in modules}

        def next_batch(mode: str) -> dict:
            try:
                return next(batches[mode])
            except StopIteration:
                batches[mode] = iter(modules[mode].train_dataloader())
                return next(batches[mode])

        tasks = {"eager": (task, optimizer)}
        if args.compile:
            compiled = copy.deepcopy(task)
            for i, block in enumerate(compiled.model.trunk.blocks):
                compiled.model.trunk.blocks[i] = torch.compile(block, dynamic=True)
            tasks["compiled"] = (compiled, compiled.configure_optimizers()["optimizer"])

        def segmo_step(mode: str) -> dict:
            t0 = time.perf_counter()
            batch = next_batch(mode.removesuffix("_bf16").removesuffix("_compiled"))
            t1 = time.perf_counter()
            model, model_optimizer = tasks["compiled" if mode.endswith("_compiled") else "eager"]
            # bf16-mixed: what `--trainer.precision bf16-mixed` runs (torch.autocast on the CPU).
            with torch.autocast("cpu", dtype=torch.bfloat16, enabled=mode.endswith("_bf16")):
                terms = model.step(batch)
            t2 = time.perf_counter()
            model_optimizer.zero_grad(set_to_none=True)
            terms["loss"].backward()
            model_optimizer.step()
            t3 = time.perf_counter()
            return {"total": t3 - t0, "data": t1 - t0, "forward": t2 - t1, "backward": t3 - t2}

        momask = MoMaskStep(mask_args["dim"], mask_args["depth"], mask_args["heads"],
                            mask_args["ff_dim"], rvq.codebook_size, mask_args["text_dim"])
        momask_optimizer = torch.optim.AdamW(momask.parameters(), lr=2e-4)

        def momask_step(mode: str) -> dict:
            t0 = time.perf_counter()
            if mode == "momask_grouped":  # the cheap path's batches: tokens from the cache
                batch = next_batch("grouped")
                base = batch["tokens"][..., 0]
            else:
                batch = next_batch("on_the_fly")
                with torch.no_grad():
                    base = task.tokenizer.encode(batch["motion"])[..., 0]
            n = base.shape[1]
            valid = torch.arange(n) < token_lengths(batch["lengths"])[:, None]
            loss = momask(base, valid, batch["sentence"])  # CLIP replaced by the cached vector
            momask_optimizer.zero_grad(set_to_none=True)
            loss.backward()
            momask_optimizer.step()
            return {"total": time.perf_counter() - t0}

        runs = {"cached": segmo_step, "on_the_fly": segmo_step, "grouped": segmo_step,
                "momask": momask_step}
        if args.bf16:
            runs |= {"cached_bf16": segmo_step, "grouped_bf16": segmo_step}
        if args.compile:
            runs |= {"grouped_compiled": segmo_step}
        if args.momask_grouped:
            runs |= {"momask_grouped": momask_step}
        times: dict[str, list[dict]] = {name: [] for name in runs}
        for name, run in runs.items():  # warm-up
            for _ in range(2):
                run(name)
        for _ in range(args.rounds):
            for name, run in runs.items():
                times[name] += [run(name) for _ in range(args.steps)]

        # The alignment loss's motion side on a cached batch: uniform spans from lengths.
        batch = next_batch("cached")
        _, segments_mask = text_condition(batch)[1:], batch["segment_mask"]
        lengths = token_lengths(batch["lengths"])
        t0 = time.perf_counter()
        for _ in range(20):
            segment_batch(None, segments_mask.sum(1), lengths, "uniform", max_segments=5)
        spans_ms = (time.perf_counter() - t0) / 20 * 1000
        # On-the-fly (batched, zero-padded) tokens against the cached tokens of the same crops.
        differ_base = differ_any = total = 0
        for _ in range(4):
            batch = next_batch("cached")
            fly = task.tokenizer.encode(batch["motion"])
            valid = torch.arange(fly.shape[1]) < token_lengths(batch["lengths"])[:, None]
            differ_base += int(((fly[..., 0] != batch["tokens"][..., 0]) & valid).sum())
            differ_any += int(((fly != batch["tokens"]).any(-1) & valid).sum())
            total += int(valid.sum())

    def median(name: str, key: str = "total") -> float:
        return statistics.median(t[key] for t in times[name])

    result = {
        **step_figures(times),
        "cached_step_ms": {k: round(1000 * median("cached", k), 1)
                           for k in ("data", "forward", "backward")},
        "on_the_fly_step_ms": {k: round(1000 * median("on_the_fly", k), 1)
                               for k in ("data", "forward", "backward")},
        "alignment_spans_ms": round(spans_ms, 2),
        "on_the_fly_tokens_differing_from_cache": {"base": round(differ_base / total, 4),
                                                   "any_layer": round(differ_any / total, 4)},
        "clip_replaced_by_cache": True,
        "sizes": {"dim": mask_args["dim"], "depth": mask_args["depth"], "batch": 32,
                  "tokenizer_width": rvq_args["width"], "codes": rvq.codebook_size},
        "threads": args.threads, "rounds": args.rounds, "steps_per_round": args.steps,
        "cpu": cpu.info().describe(),
        "loadavg_after": Path("/proc/loadavg").read_text().split()[:3]
        if Path("/proc/loadavg").exists() else None,
    }
    print(f"cached {result['ms_per_step']['cached']} ms, on the fly "
          f"{result['ms_per_step']['on_the_fly']} ms, MoMask reference "
          f"{result['ms_per_step']['momask']} ms, grouped {result['ms_per_step']['grouped']} ms "
          f"per step (medians; by throughput grouped is "
          f"{result['throughput']['speedup_vs_on_the_fly']['grouped']}x the on-the-fly step and "
          f"{result['throughput']['speedup_vs_momask']['grouped']}x MoMask's; {args.threads} "
          f"threads; {result['cpu']})")
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    main()
