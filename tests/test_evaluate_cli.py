"""`segmo evaluate` end to end on a tiny random bundle, a tiny random evaluator and a tiny
built-in corpus: metrics.json, report.md, plots, --real-only, --compare, and the ablation
tool's dry run."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from conftest import build_tokenizer, cli_failure, hash_encoder

from segmo.evaluation import report
from segmo.evaluation.cli import main

REPO = Path(__file__).resolve().parents[1]
ENCODER = "hash16"
GENERATION = ("top1", "top2", "top3", "fid", "matching", "diversity")
COMMON = ["--split", "train", "--max-motions", "10", "--repeats", "2", "--batch-size", "8", "--no-progress"]


@pytest.fixture(scope="module")
def setup(tmp_path_factory) -> dict[str, Path]:
    """Corpus of 24 motions (19 in train), a random bundle, evaluator and action classifier."""
    from segmo.models.action_classifier import ActionClassifier, ActionClassifierConfig
    from segmo.models.alignment import AlignmentConfig
    from segmo.models.evaluator import EvaluatorConfig, T2MEvaluator
    from segmo.models.mask_transformer import MaskTransformer, MaskTransformerConfig
    from segmo.models.residual_transformer import ResidualTransformer, ResidualTransformerConfig
    from segmo.models.tokenizer import RVQVAE
    from segmo.pipeline.segmo import SegMo, SegMoConfig
    from segmo.synth.corpus import build_corpus
    from segmo.text.vocabulary import Vocabulary

    root = tmp_path_factory.mktemp("evaluate")
    corpus = build_corpus(root / "synth", 24, seed=0, progress=False)
    torch.manual_seed(0)
    tiny = dict(codebook_size=16, text_dim=16, max_segments=5, max_tokens=49, dim=32, depth=1,
                heads=2, ff_dim=64)
    tokenizer = RVQVAE.from_pretrained(build_tokenizer(root / "rvq", 263))
    paths = {"data": corpus}
    for name, alignment in (("segmo", AlignmentConfig(out_dim=16)), ("no_align", None)):
        mask = MaskTransformer(MaskTransformerConfig(**tiny, alignment=alignment))
        residual = ResidualTransformer(ResidualTransformerConfig(**tiny, num_quantizers=3))
        SegMo(tokenizer, mask, residual, config=SegMoConfig(text_encoder=ENCODER),
              text_encoder=hash_encoder(ENCODER, 16)).save_pretrained(root / name)
        paths[name] = root / name
    words = ["sos", "eos", "unk", "a", "person", "walks", "forward", "then", "waves", "runs"]
    evaluator = T2MEvaluator(EvaluatorConfig(num_words=len(words), word_dim=12, text_hidden=8,
                                             movement_hidden=10, movement_dim=6, motion_hidden=8,
                                             embed_dim=5))
    evaluator.set_vocabulary(Vocabulary(words))
    paths["evaluator"] = evaluator.save_pretrained(root / "evaluator", meta={"skeleton": "t2m"})
    classes = json.loads((corpus / "corpus.json").read_text())["actions"]
    classes = sorted(classes if isinstance(classes, list) else classes.keys())
    clf = ActionClassifier(ActionClassifierConfig(num_classes=len(classes), width=8, depth=1))
    clf.meta = {"classes": classes}
    paths["classifier"] = clf.save_pretrained(root / "classifier")
    return paths


@pytest.fixture()
def hash_text_encoder(monkeypatch):
    """The bundles name a hash encoder that `get_text_encoder` cannot build: stand it in."""
    import segmo.text.encoders as encoders

    real = encoders.get_text_encoder
    monkeypatch.setattr(encoders, "get_text_encoder",
                        lambda name, *a, **k: hash_encoder(name, 16) if name == ENCODER else real(name, *a, **k))


def _check_repeated(values: dict, names) -> None:
    for name in names:
        entry = values[name]
        assert set(entry) == {"mean", "interval"}, name
        assert entry["interval"] >= 0 and entry["mean"] == entry["mean"], name  # no NaN


def test_evaluate_writes_every_metric(setup, hash_text_encoder, tmp_path: Path) -> None:
    out = tmp_path / "segmo"
    main(["--model", str(setup["segmo"]), "--data", str(setup["data"]), "--evaluator", str(setup["evaluator"]),
          "--action-classifier", str(setup["classifier"]), "--mm-prompts", "2", "--mm-repeats", "11",
          "--retrieval-motions", "6", "--similarity-maps", "1", "--out", str(out), *COMMON])
    metrics = json.loads((out / "metrics.json").read_text())
    generation = metrics["generation"]
    _check_repeated(generation["real"], GENERATION)
    _check_repeated(generation["generated"], (*GENERATION, "multimodality"))
    assert 0 <= generation["generated"]["top1"]["mean"] <= generation["generated"]["top3"]["mean"] <= 1
    assert generation["real"]["fid"]["mean"] < 1e-6 + generation["real"]["fid"]["interval"] * 10
    retrieval = metrics["retrieval"]
    assert set(retrieval) == {"evaluator", "segmo"}
    assert set(retrieval["evaluator"]) == {"full", "batches of 8"}
    assert set(retrieval["segmo"]) == {"full (6 motions)", "batches of 8"}
    for protocols in retrieval.values():
        for values in protocols.values():
            assert 0 <= values["t2m/R@1"] <= values["t2m/R@10"] <= 1 and values["m2t/MedR"] >= 1
    grounding = metrics["grounding"]
    assert grounding["queries"] > 0 and 0 <= grounding["mIoU"] <= 1
    assert {"R@1,IoU=0.3", "R@1,IoU=0.5", "R@1,IoU=0.7", "uniform/mIoU"} <= set(grounding)
    assert {"spans/R@1,IoU=0.5", "spans/mIoU", "window/R@1,IoU=0.5", "window/mIoU"} <= set(grounding)
    assert set(metrics["isc"]) == {"uniform", "cpd", "kmeans"}
    assert all(v["pairs"] > 0 and -1 <= v["mean"] <= 1 for v in metrics["isc"].values())
    order = metrics["action_order"]
    assert order["real"]["motions"] == 10 and order["generated"]["motions"] == 10
    assert 0 <= order["generated"]["sequence_accuracy"] <= 1
    config = metrics["config"]
    assert config["repeats"] == 2 and config["seed"] == 0 and config["timings"]["total"] > 0
    assert config["model"] == str(setup["segmo"]) and config["motions"] == 10
    text = (out / "report.md").read_text()
    assert "| Method | Top-1 | Top-2 | Top-3 | FID | MM-Dist | Diversity | MModality |" in text
    real_cell = f"{generation['real']['top1']['mean']:.3f}±{generation['real']['top1']['interval']:.3f}"
    assert f"| Real | {real_cell} |" in text and "| segmo |" in text
    for title in ("## Retrieval", "## Grounding", "## Intra-segment consistency", "## Action order"):
        assert title in text
    for row in ("| ordered spans |", "| best span |", "| sliding window |", "| uniform split |"):
        assert row in text
    assert (out / "isc.png").stat().st_size > 0
    assert len(list((out / "similarity_maps").glob("*.png"))) == 1

    # Same seed, same numbers: generation is seeded per batch.
    again = tmp_path / "again"
    main(["--model", str(setup["segmo"]), "--data", str(setup["data"]), "--evaluator", str(setup["evaluator"]),
          "--mm-prompts", "0", "--skip", "retrieval,grounding,isc", "--action-classifier", "train",
          "--out", str(again), *COMMON])
    repeat = json.loads((again / "metrics.json").read_text())
    assert repeat["generation"]["generated"]["top1"] == generation["generated"]["top1"]
    assert "multimodality" not in repeat["generation"]["generated"]
    assert not {"retrieval", "grounding", "isc"} & set(repeat)
    # `--action-classifier train` fits one on the train split and keeps it.
    assert (again / "action_classifier" / "config.json").is_file()
    assert repeat["action_order"]["real"]["motions"] == 10

    # No alignment head: generation metrics only, the learned-space sections are skipped.
    plain = tmp_path / "no_align"
    main(["--model", str(setup["no_align"]), "--data", str(setup["data"]), "--evaluator", str(setup["evaluator"]),
          "--mm-prompts", "0", "--skip", "action_order", "--out", str(plain), *COMMON])
    plain_metrics = json.loads((plain / "metrics.json").read_text())
    assert "isc" not in plain_metrics and "grounding" not in plain_metrics
    assert set(plain_metrics["retrieval"]) == {"evaluator"}
    _check_repeated(plain_metrics["generation"]["generated"], GENERATION)

    main(["--compare", str(out), str(plain / "metrics.json"), "--out", str(tmp_path / "cmp")])
    table = (tmp_path / "cmp" / "compare.md").read_text().splitlines()
    assert table[0].startswith("| Method | Top-1") and [r.split(" |")[0] for r in table[2:]] == [
        "| Real", "| segmo", "| no_align"]


def test_real_only(setup, tmp_path: Path) -> None:
    out = tmp_path / "real"
    main(["--real-only", "--data", str(setup["data"]), "--evaluator", str(setup["evaluator"]),
          "--out", str(out), *COMMON])
    metrics = json.loads((out / "metrics.json").read_text())
    assert set(metrics["generation"]) == {"real"}
    _check_repeated(metrics["generation"]["real"], GENERATION)
    assert set(metrics["retrieval"]) == {"evaluator"}
    text = (out / "report.md").read_text()
    assert "| Real |" in text and "## Grounding" not in text


def test_errors_name_the_flag(setup, tmp_path: Path, capsys) -> None:
    base = ["evaluate", "--data", str(setup["data"]), "--evaluator", str(setup["evaluator"]),
            "--out", str(tmp_path)]
    assert "--model is required" in cli_failure(base, capsys)
    line = cli_failure(["evaluate", "--real-only", "--data", str(tmp_path / "nope"), "--evaluator",
                        str(setup["evaluator"]), "--out", str(tmp_path)], capsys)
    assert "--data" in line
    line = cli_failure(["evaluate", "--compare", str(tmp_path / "missing"), "--out", str(tmp_path)],
                       capsys)
    assert "no metrics.json" in line
    line = cli_failure([*base, "--real-only", "--evaluator", str(setup["segmo"] / "mask")], capsys)
    assert "--evaluator" in line and "'mask'" in line
    for flag, value in (("--repeats", "0"), ("--batch-size", "1"), ("--seed", "-2"),
                        ("--grounding-window", "4,x"), ("--split", "nosuch")):
        assert flag in cli_failure([*base, "--real-only", flag, value], capsys)


def test_report_tables() -> None:
    entry = {"mean": 0.5534, "interval": 0.0031}
    table = report.generation_table([("SegMo", {"top1": entry, "fid": {"mean": 0.042, "interval": 0.002}})])
    assert table.splitlines()[2] == "| SegMo | 0.553±0.003 | - | - | 0.042±0.002 | - | - | - |"
    with pytest.raises(ValueError, match="no run"):
        report.compare_table([("a", {"generation": {}})])


def test_ablation_dry_run(tmp_path: Path) -> None:
    result = subprocess.run(
        [sys.executable, str(REPO / "tools" / "ablation_grid.py"), "--data", "D", "--tokenizer", "T",
         "--evaluator", "E", "--steps", "3", "--variants", "in_sample,none,cpd", "--out", str(tmp_path),
         "--dry-run"], capture_output=True, text=True, cwd=REPO, check=True)
    lines = result.stdout.splitlines()
    fits = [line for line in lines if " fit " in line and "configs/mask/" in line]
    assert len(fits) == 3 and all("--trainer.max_steps 3" in line for line in fits)
    assert any("--model.init_args.alignment none" in line for line in fits)
    assert any("--model.init_args.segmenter cpd" in line and "alignment in_sample" in line for line in fits)
    assert sum(" evaluate " in line for line in lines) == 3
    assert any("configs/residual/" in line for line in lines)  # trained once when not given
