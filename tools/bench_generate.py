"""Benchmark text → tokens → features generation on this machine.

    python tools/bench_generate.py --random-config humanml3d --batch-size 32
    python tools/bench_generate.py --random-config humanml3d --batch-size 32 --precision bf16
    python tools/bench_generate.py --model DIR --batch-size 1 --repeats 5
    python tools/bench_generate.py --random-config humanml3d --compare-precision

`--model DIR`: DIR holds model directories (any sub-folder with a config.json) of kinds
"mask", "residual" and optionally "rvq". `--random-config humanml3d`: randomly initialised
paper-sized models (8 layers, width 384, 6 heads, FFN 1024, 512 codes, 6 quantizers,
49 tokens = 196 frames, text_dim 512, A = 5) and a random RVQ-VAE decoder when
`segmo.models.tokenizer` is importable (otherwise decoding is excluded from the timing).
`--random-config tiny`: a 1-layer width-32 model, for checking that the tool runs (under
emulation, say) rather than for its figures.

`--precision auto` (the default) is what `segmo generate` runs: bf16 on a CPU with native
bf16 (AVX512-BF16, AMX, AVX-NE-CONVERT), fp32 elsewhere (`segmo.cpu`). The first line says
the precision chosen and why, and the CPU (model, the ISA torch's kernels use, its oneDNN
paths); the JSON line repeats them. bf16 also runs where oneDNN has no bf16 path (no
AVX-512), in torch's reference kernels: several times slower than fp32.

Measured after one warm-up, over `--repeats` runs, median:
- ms_per_motion: generation (+ decoding when a tokenizer is present) / batch size;
- floor: the bare transformer passes of plain decoding (steps mask passes, each computed at
  the positions generation samples in it, + q−1 residual passes, each on the 2b guidance
  batch, same precision, no sampling), timed in the same run, interleaved with the
  generation runs so that machine load affects both alike; generation skips some of
  them exactly (a repeated step, identical unconditional rows; `masked_decode`), so its
  floor_ratio can fall below 1;
- floor_ratio = token-generation time / floor time; peak RSS of the process;
- matmul_gmacs_before_after: the machine's matmul speed just before and after the timed
  runs (`gemm_gmacs`); on a shared host it drifts, and every figure above drifts with it;
- gmac_per_motion: the multiply-accumulates of those passes (`generation_macs`), and
  matmul_bound_ms_per_motion = that / the measured matmul speed: the time the arithmetic
  alone takes at that speed, whatever the implementation;
- allocator_tuned: whether glibc malloc keeps freed memory (`keep_freed_memory`, as the
  `segmo generate` and `segmo evaluate` commands do); `--default-allocator` turns it off;
- with --momask-floor: momask_floor_ms_per_motion, the MoMask reference's bare passes
  (fp32, `momask_floor`, at its own 10 steps whatever --steps says) timed on this
  machine, interleaved with the runs above, and
  speedup_vs_momask_floor = that time / ms_per_motion, a ratio that does not depend on
  the host;
- *_cpu_*: process CPU time. On a shared machine, multi-threaded wall times swing wildly
  (OpenMP threads wait for descheduled peers); `--threads 1` CPU times stay stable.
The last printed line is JSON.

`--versus sink_ctrl,memory16,...` (with --random-config) measures what a mechanism costs
instead: plain CFG and each named variant (`VERSUS`) generate in turns in one process,
--repeats rounds, the order rotated every round; each variant's cost is the ratio of its
process CPU time to the baseline's in the same round (paired, so that the host's drift
cancels), reported as the median ratio with a 95 % interval (t over the rounds' log
ratios). A variant "costs at most 5 %" when the interval's upper end is at most 1.05.
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import os
import resource
import statistics
import sys
import time
from pathlib import Path

import torch

from segmo import cpu
from segmo.generation.allocator import keep_freed_memory
from segmo.generation.generate import (
    decode_tokens,
    generate_tokens,
    guidance_condition,
    inference,
    masked_count,
    resolve_precision,
)
from segmo.generation.sampling import SamplingOptions
from segmo.models.cpu_inference import PackedLinear, use_cpu_kernels
from segmo.models.mask_transformer import MaskTransformer, MaskTransformerConfig
from segmo.models.pretrained import load_pretrained, read_config
from segmo.models.residual_transformer import ResidualTransformer, ResidualTransformerConfig

# The MoMask reference decodes base tokens in 10 steps (its default), whatever --steps says.
MOMASK_STEPS = 10
PAPER = dict(codebook_size=512, text_dim=512, max_segments=5, dim=384, depth=8, heads=6,
             ff_dim=1024, num_quantizers=6)
RANDOM_CONFIGS = {
    "humanml3d": dict(PAPER, feature_dim=263, max_tokens=49, tokenizer={}),
    "tiny": dict(codebook_size=16, text_dim=8, max_segments=2, dim=32, depth=1, heads=2,
                 ff_dim=64, num_quantizers=3, feature_dim=12, max_tokens=6,
                 tokenizer=dict(width=32, code_dim=16, codebook_size=16, num_quantizers=3)),
}


# --versus: mechanism -> (mask model overrides, SamplingOptions overrides), against plain CFG.
VERSUS: dict[str, tuple[dict, dict]] = {
    "sink_ctrl": ({}, {"guidance": "sink_ctrl", "ctrl_k_base": 0.5, "sink_ratio": 0.5}),
    "memory16": ({"memory_slots": 16}, {}),
    "sink_mask": ({"sink_mask_t": 0.2}, {}),
    "local_uncond": ({}, {"unconditional": "local"}),
    # word-level conditioning (`text_tokens: words`): WORDS word keys in the prefix, or read
    # by a gated cross-attention sub-layer in every block
    "words": ({"text_tokens": "words"}, {}),
    "words_cross": ({"text_tokens": "words", "word_attention": "cross"}, {}),
}
# Word keys of the bench's captions with words: a caption of three or four actions in
# MiniLM's tokens, start and end tokens included.
WORDS = 20


def random_models(name: str, seed: int, memory_slots: int = 0, **mask_overrides):
    spec = dict(RANDOM_CONFIGS[name], memory_slots=memory_slots)
    feature_dim, tokenizer_spec = spec.pop("feature_dim"), spec.pop("tokenizer")
    num_quantizers = spec.pop("num_quantizers")
    torch.manual_seed(seed)
    mask = use_cpu_kernels(MaskTransformer(MaskTransformerConfig(**spec, **mask_overrides)))
    residual = use_cpu_kernels(
        ResidualTransformer(ResidualTransformerConfig(**spec, num_quantizers=num_quantizers)))
    try:
        from segmo.models.tokenizer import RVQVAE, RVQConfig
    except ImportError:
        tokenizer = None
    else:
        tokenizer = RVQVAE(RVQConfig(feature_dim=feature_dim, **tokenizer_spec))
    return mask, residual, tokenizer


def directory_models(directory: Path):
    found = {}
    for sub in sorted(p for p in [directory, *directory.iterdir()] if p.is_dir()):
        if (sub / "config.json").is_file():
            found.setdefault(read_config(sub)["kind"], sub)
    for kind in ("mask", "residual"):
        if kind not in found:
            sys.exit(f"bench_generate: no {kind!r} model directory under {directory}")
    load = {kind: load_pretrained(path) for kind, path in found.items()}
    return use_cpu_kernels(load["mask"]), use_cpu_kernels(load["residual"]), load.get("rvq")


def text_inputs(mask: MaskTransformer, b: int, seed: int):
    g = torch.Generator().manual_seed(seed)
    c = mask.config
    return (torch.randn(b, c.text_dim, generator=g), torch.randn(b, c.max_segments, c.text_dim, generator=g),
            torch.ones(b, c.max_segments, dtype=torch.bool))


def word_inputs(mask: MaskTransformer, b: int, seed: int) -> dict:
    """Random word features for a model with word keys (WORDS of them), none for the others."""
    if mask.config.text_tokens != "words":
        return {}
    g = torch.Generator().manual_seed(seed + 1)
    return {"words": torch.randn(b, WORDS, mask.config.text_dim, generator=g),
            "word_mask": torch.ones(b, WORDS, dtype=torch.bool)}


def sampled_counts(n: int, steps: int) -> list[int]:
    """How many positions each mask pass of a generation of n tokens samples, and so
    computes in its last block: ⌈γ(t)·n⌉ (≥ 1) for t ∈ linspace(0, 1, steps)."""
    return [int(masked_count(t, torch.tensor([n]))) for t in torch.linspace(0, 1, steps).tolist()]


def pass_macs(config, rows: int, n: int, m: int) -> int:
    """Multiply-accumulates of one motion pass (`forward_condition` / `forward_embedded`)
    over `rows` rows of n motion tokens, m of them asked for: the linear layers, the
    attention matmuls over the prefix's 1 + A keys and the n motion keys, the head and
    the projection to the codes. The prefix's own encoding (once per generation) is not
    counted."""
    d, ff, v = config.dim, config.ff_dim, config.codebook_size
    keys = 1 + config.max_segments + n
    block = n * (4 * d * d + 2 * d * ff) + 2 * n * keys * d  # QKV, output, FFN; attention
    last = n * 3 * d * d + m * (d * d + 2 * d * ff) + 2 * m * keys * d
    head = m * (d * d + d * v)
    return rows * ((config.depth - 1) * block + last + head)


def generation_macs(mask, residual, b: int, n: int, steps: int) -> int:
    """Multiply-accumulates of the motion passes of one generation of b motions of n
    tokens (what `floor_passes` runs): the arithmetic no implementation can skip."""
    total = sum(pass_macs(mask.config, 2 * b, n, m) for m in sampled_counts(n, steps))
    return total + (residual.config.num_quantizers - 1) * pass_macs(residual.config, 2 * b, n, n)


def floor_passes(mask, residual, text, n: int, steps: int, precision: str) -> None:
    """The transformer passes of one generation, without any sampling logic: each mask
    pass computed at as many positions as generation samples in it."""
    b = text[0].shape[0]
    token_mask = torch.ones(2 * b, n, dtype=torch.bool)
    ids = torch.full((2 * b, n), mask.mask_id)
    with inference([mask, residual], precision, text[0].device):
        condition = guidance_condition(mask, *text)
        for m in sampled_counts(n, steps):
            positions = None if m == n else torch.arange(m).expand(2 * b, m)
            mask.forward_condition(ids, token_mask, condition, positions)
        condition = guidance_condition(residual, *text)
        x = residual.embed_layer(ids.clamp(max=mask.config.codebook_size - 1), 0)
        for layer in range(1, residual.config.num_quantizers):
            residual.forward_embedded(x, layer, token_mask, condition)


def momask_models(dim: int = 384, depth: int = 8, heads: int = 6, ff_dim: int = 1024,
                  codes: int = 512) -> tuple[torch.nn.Module, torch.nn.Module]:
    """The MoMask reference's transformer at the paper's sizes: PyTorch's post-norm
    `nn.TransformerEncoder` (GELU) and its output head (dense, GELU, LayerNorm, projection
    to the codes), random weights, eval mode."""
    layer = torch.nn.TransformerEncoderLayer(dim, heads, ff_dim, 0.2, "gelu")
    trunk = torch.nn.TransformerEncoder(layer, depth, enable_nested_tensor=False)
    head = torch.nn.Sequential(torch.nn.Linear(dim, dim), torch.nn.GELU(),
                               torch.nn.LayerNorm(dim), torch.nn.Linear(dim, codes))
    return trunk.eval(), head.eval()


def momask_floor(trunk: torch.nn.Module, head: torch.nn.Module, b: int, n: int, steps: int,
                 num_quantizers: int) -> None:
    """The bare passes of one MoMask-reference generation of b motions (fp32), as its code
    runs them: sequence-first, the conditional and unconditional passes one after the other
    (2 per step and per residual layer), one condition token before the n motion tokens (and
    the quantizer-layer token for the residual transformer). Timed on the same machine at
    the same moment as segmo's generation, so that their ratio does not depend on the host
    (the reference figures of issue 5 were measured on another one)."""
    dim = head[0].in_features
    with torch.inference_mode():
        for tokens, passes in ((n + 1, 2 * steps), (n + 2, 2 * (num_quantizers - 1))):
            x = torch.randn(tokens, b, dim)
            padding = torch.zeros(b, tokens, dtype=torch.bool)
            for _ in range(passes):
                head(trunk(x, src_key_padding_mask=padding)[1:])


def gemm_gmacs(precision: str, dim: int = 384, tokens: int = 49, repeats: int = 20) -> float:
    """This machine's matmul throughput right now (GMAC/s): the QKV projection of a batch-32
    guidance batch of the model (paper sizes: 3136 × 384 → 1152), timed as generation runs
    it. Shared machines drift by 20 % and more between minutes; read the other figures
    against it."""
    layer = PackedLinear(dim, 3 * dim).eval()
    x = torch.randn(64, tokens, dim)
    with inference([layer], precision, x.device):
        layer(x)
        start = time.perf_counter()
        for _ in range(repeats):
            layer(x)
        seconds = (time.perf_counter() - start) / repeats
    return 64 * tokens * dim * 3 * dim / seconds / 1e9


def paired_ratios(times: dict[str, list[float]], baseline: str = "cfg") -> dict[str, dict]:
    """Each variant's per-round time over the baseline's in the same round: the median, and
    a 95 % interval (Student t over the log ratios, back-transformed; one round: 0 to inf)."""
    from segmo.evaluation.seeds import interval

    base = times[baseline]
    out = {}
    for name, values in times.items():
        if name == baseline:
            continue
        logs = [math.log(v / b) for v, b in zip(values, base)]
        mean, half = interval(logs)
        half = math.inf if math.isnan(half) else half
        out[name] = {"median_ratio": round(statistics.median(v / b for v, b in zip(values, base)), 4),
                     "ratio_interval_95": [round(math.exp(mean - half), 4), round(math.exp(mean + half), 4)],
                     "rounds": len(logs)}
    return out


def versus(args: argparse.Namespace, names: list[str]) -> dict:
    """Plain CFG against each mechanism of `names` (see VERSUS), in turns, paired by round."""
    b = args.batch_size
    variants = {"cfg": ({}, {})} | {name: VERSUS[name] for name in names}
    runs = {}
    for name, (overrides, sampling) in variants.items():
        mask, residual, _ = random_models(args.random_config, args.seed, **overrides)
        mask.eval()
        residual.eval()
        options = SamplingOptions(steps=args.steps, residual_guided_layers=args.residual_guided_layers,
                                  **sampling)
        text, words = text_inputs(mask, b, args.seed), word_inputs(mask, b, args.seed)
        lengths = torch.full((b,), 4 * mask.config.max_tokens)

        def run(mask=mask, residual=residual, options=options, text=text, words=words,
                lengths=lengths) -> float:
            start = time.process_time()
            generate_tokens(mask, residual, *text, lengths, options=options,
                            generator=torch.Generator().manual_seed(args.seed), precision=args.precision,
                            **words)
            return time.process_time() - start

        run()  # warm-up
        runs[name] = run
    order = list(runs)
    times: dict[str, list[float]] = {name: [] for name in order}
    for round_ in range(args.repeats):
        for name in order[round_ % len(order):] + order[:round_ % len(order)]:
            times[name].append(runs[name]())
    return {"cpu_ms_per_motion": {name: round(statistics.median(v) * 1000 / b, 2) for name, v in times.items()},
            "versus_cfg": paired_ratios(times)}


def timed(fn, clock=time.perf_counter) -> float:
    start = clock()
    fn()
    return clock() - start


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--model", type=Path, help="folder holding mask/residual[/rvq] model dirs")
    source.add_argument("--random-config", choices=sorted(RANDOM_CONFIGS))
    parser.add_argument("--batch-size", type=int, default=1)
    parser.add_argument("--precision", choices=["auto", "fp32", "bf16"], default="auto",
                        help="auto: bf16 on CPUs with native bf16, else fp32 (segmo.cpu)")
    parser.add_argument("--steps", type=int, default=SamplingOptions.steps)
    parser.add_argument("--residual-guided-layers", type=int, default=None,
                        help="guided residual layers, from the first (default: all)")
    parser.add_argument("--guidance", choices=("cfg", "sink_ctrl"), default="cfg",
                        help="base-token guidance (SamplingOptions.guidance)")
    parser.add_argument("--memory-slots", type=int, default=0,
                        help="--random-config models with this many memory slots")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--default-allocator", action="store_true",
                        help="leave glibc malloc at its defaults (segmo.generation.allocator)")
    parser.add_argument("--compare-precision", action="store_true",
                        help="report bf16 vs fp32 token agreement on the same seeds")
    parser.add_argument("--versus", default=None,
                        help=f"comma-separated mechanisms to time against plain CFG, paired by "
                             f"round ({', '.join(VERSUS)}; needs --random-config)")
    parser.add_argument("--momask-floor", action="store_true",
                        help="also time the MoMask reference's bare passes (fp32) on this machine")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    allocator_tuned = False if args.default_allocator else keep_freed_memory()
    asked = args.precision
    args.precision, why = resolve_precision(asked, "cpu")
    print(f"precision {args.precision} ({asked}: {why}); CPU: {cpu.describe()}")
    host = {"precision": args.precision, "precision_asked": asked, "precision_reason": why,
            "cpu": cpu.describe()}

    if args.versus is not None:
        names = [n for n in args.versus.split(",") if n]
        unknown = [n for n in names if n not in VERSUS]
        if unknown or not names or args.random_config is None:
            parser.error(f"--versus takes names from {', '.join(VERSUS)} and needs --random-config"
                         + (f"; unknown: {', '.join(unknown)}" if unknown else ""))
        result = versus(args, names)
        for name, r in result["versus_cfg"].items():
            low, high = r["ratio_interval_95"]
            print(f"{name}: {r['median_ratio']:.3f}x plain CFG's CPU time (95 % interval "
                  f"{low:.3f}-{high:.3f}, {r['rounds']} paired rounds)")
        print(json.dumps({**result, "batch": args.batch_size, **host, "threads": args.threads,
                          "steps": args.steps, "repeats": args.repeats,
                          "load_average": round(os.getloadavg()[0], 2)}))
        return

    if args.model is not None:
        mask, residual, tokenizer = directory_models(args.model)
    else:
        mask, residual, tokenizer = random_models(args.random_config, args.seed, args.memory_slots)
    for model in (mask, residual, tokenizer):
        if model is not None:
            model.eval()
    b = args.batch_size
    text = text_inputs(mask, b, args.seed)
    n = mask.config.max_tokens
    lengths = torch.full((b,), 4 * n)

    def generate(precision: str, seed: int) -> torch.Tensor:
        return generate_tokens(mask, residual, *text, lengths,
                               options=SamplingOptions(
                                   steps=args.steps,
                                   residual_guided_layers=args.residual_guided_layers,
                                   guidance=args.guidance),
                               generator=torch.Generator().manual_seed(seed), precision=precision)

    if args.compare_precision:
        seeds = range(args.seed, args.seed + args.repeats)
        pairs = [(generate("fp32", s), generate("bf16", s)) for s in seeds]
        base = statistics.mean((a[..., 0] == c[..., 0]).float().mean().item() for a, c in pairs)
        every = statistics.mean((a == c).float().mean().item() for a, c in pairs)
        first = statistics.mean(
            (a[..., 0] == c[..., 0]).all(dim=1).float().mean().item() for a, c in pairs)
        print(f"bf16 vs fp32 over {len(pairs)} seeds × batch {b}: base-token agreement "
              f"{base:.3f}, all layers {every:.3f}, identical base sequences {first:.3f}")
        print(json.dumps({"base_agreement": round(base, 4), "all_agreement": round(every, 4),
                          "identical_sequences": round(first, 4), "batch": b,
                          "threads": args.threads, "cpu": host["cpu"]}))
        return

    def run_generation() -> tuple[float, float, float]:
        cpu_start = time.process_time()
        tokens_s = timed(lambda: out.append(generate(args.precision, args.seed)))
        cpu_s = time.process_time() - cpu_start
        decode_s = 0.0
        if tokenizer is not None:
            decode_s = timed(lambda: decode_tokens(tokenizer, out[-1], lengths, args.precision))
        return tokens_s, decode_s, cpu_s

    out: list[torch.Tensor] = []
    run_generation()  # warm-up (allocator, oneDNN kernels, autocast caches)
    floor_passes(mask, residual, text, n, args.steps, args.precision)
    gmacs = [gemm_gmacs(args.precision, mask.config.dim, n)]
    reference = None
    if args.momask_floor:
        trunk, head = momask_models(dim=mask.config.dim, depth=mask.config.depth,
                                    heads=mask.config.heads, ff_dim=mask.config.ff_dim,
                                    codes=mask.config.codebook_size)
        reference = functools.partial(momask_floor, trunk, head, b, n, MOMASK_STEPS,
                                      residual.config.num_quantizers)
        reference()  # warm-up
    token_times, decode_times, floor_times, cpu_times, floor_cpu_times = [], [], [], [], []
    momask_times = []
    for _ in range(args.repeats):  # interleaved, so that drift of the host affects all alike
        tokens_s, decode_s, cpu_s = run_generation()
        token_times.append(tokens_s)
        decode_times.append(decode_s)
        cpu_times.append(cpu_s)
        cpu_start = time.process_time()
        floor_times.append(timed(lambda: floor_passes(mask, residual, text, n, args.steps,
                                                      args.precision)))
        floor_cpu_times.append(time.process_time() - cpu_start)
        if reference is not None:
            momask_times.append(timed(reference))
    gmacs.append(gemm_gmacs(args.precision, mask.config.dim, n))
    macs = generation_macs(mask, residual, b, n, args.steps) / b
    bound_ms = macs / (statistics.mean(gmacs) * 1e9) * 1000
    momask_ms = statistics.median(momask_times) * 1000 / b if momask_times else None
    tokens_ms = statistics.median(token_times) * 1000 / b
    decode_ms = statistics.median(decode_times) * 1000 / b
    floor_ms = statistics.median(floor_times) * 1000 / b
    # CPU time of all threads: on a loaded machine, wall time / threads underestimates speed.
    cpu_ms = statistics.median(cpu_times) * 1000 / b
    floor_cpu_ms = statistics.median(floor_cpu_times) * 1000 / b
    peak_rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    load = os.getloadavg()[0]
    print(f"tokens {tokens_ms:.1f} ms/motion, decode {decode_ms:.1f} ms/motion"
          f"{'' if tokenizer is not None else ' (no tokenizer: decoding excluded)'}, "
          f"floor {floor_ms:.1f} ms/motion, token CPU time {cpu_ms:.1f} ms/motion, "
          f"load average {load:.2f}, matmul {gmacs[0]:.0f}/{gmacs[1]:.0f} GMAC/s before/after")
    print(json.dumps({
        "ms_per_motion": round(tokens_ms + decode_ms, 2),
        "token_ms_per_motion": round(tokens_ms, 2),
        "decode_ms_per_motion": round(decode_ms, 2) if tokenizer is not None else None,
        "floor_ms_per_motion": round(floor_ms, 2),
        "token_cpu_ms_per_motion": round(cpu_ms, 2),
        "floor_cpu_ms_per_motion": round(floor_cpu_ms, 2),
        "floor_ratio_cpu": round(cpu_ms / floor_cpu_ms, 3),
        "floor_ratio": round(tokens_ms / floor_ms, 3),
        "peak_rss_mb": round(peak_rss_mb, 1),
        "batch": b, **host, "threads": args.threads,
        "steps": args.steps, "residual_guided_layers": args.residual_guided_layers,
        "guidance": args.guidance, "memory_slots": args.memory_slots,
        "repeats": args.repeats, "load_average": round(load, 2),
        "allocator_tuned": allocator_tuned,
        "matmul_gmacs_before_after": [round(x) for x in gmacs],
        "gmac_per_motion": round(macs / 1e9, 3),
        "matmul_bound_ms_per_motion": round(bound_ms, 2),
        "momask_floor_ms_per_motion": None if momask_ms is None else round(momask_ms, 2),
        "speedup_vs_momask_floor": (None if momask_ms is None
                                    else round(momask_ms / (tokens_ms + decode_ms), 3)),
    }))


if __name__ == "__main__":
    main()
