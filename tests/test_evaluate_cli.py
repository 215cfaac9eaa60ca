"""`segmo evaluate` end to end on a tiny random bundle, a tiny random evaluator and a tiny
built-in corpus: metrics.json, report.md, plots, --real-only, --compare, and the ablation
tool's dry run."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from conftest import build_tokenizer, cli_failure, hash_encoder, load_tool

from segmo.cli import run as run_command
from segmo.errors import SegmoError
from segmo.evaluation import report
from segmo.evaluation.cli import main
from segmo.evaluation.sections import SECTIONS
from segmo.pipeline import SegMo

REPO = Path(__file__).resolve().parents[1]
ENCODER = "hash16"
# The transformers of the tiny random bundles.
TINY = dict(codebook_size=16, text_dim=16, max_segments=5, max_tokens=49, dim=32, depth=1,
            heads=2, ff_dim=64)
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
    tokenizer = RVQVAE.from_pretrained(build_tokenizer(root / "rvq", 263))
    paths = {"data": corpus}
    for name, alignment, timing in (("segmo", AlignmentConfig(out_dim=16), False),
                                    ("no_align", None, False),
                                    ("timed", AlignmentConfig(out_dim=16), True)):
        mask = MaskTransformer(MaskTransformerConfig(**TINY, alignment=alignment,
                                                     segment_timing=timing))
        residual = ResidualTransformer(ResidualTransformerConfig(**TINY, num_quantizers=3))
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
    from segmo.data.attributes import num_attribute_classes
    from segmo.models.action_classifier import AttributeClassifier
    from segmo.tasks.action_classifier import AttributeClassifierTask

    attributes = AttributeClassifier(ActionClassifierConfig(num_classes=num_attribute_classes(),
                                                            width=8, depth=1))
    attributes.meta = {"classes": AttributeClassifierTask.CLASSES}
    paths["attributes"] = attributes.save_pretrained(root / "attributes")
    return paths


@pytest.fixture()
def hash_text_encoder(monkeypatch):
    """The bundles name a hash encoder that `get_text_encoder` cannot build: stand it in."""
    import segmo.text.encoders as encoders

    real = encoders.get_text_encoder
    monkeypatch.setattr(encoders, "get_text_encoder",
                        lambda name, *a, **k: hash_encoder(name, 16) if name == ENCODER else real(name, *a, **k))


def _strict_json(path: Path) -> dict:
    """A file as a strict JSON reader (JavaScript's JSON.parse) reads it: no NaN or Infinity."""
    def refuse(constant: str):
        raise ValueError(f"{path}: {constant} is not JSON")

    return json.loads(path.read_text(), parse_constant=refuse)


def _check_repeated(values: dict, names) -> None:
    for name in names:
        entry = values[name]
        assert set(entry) == {"mean", "interval"}, name
        assert entry["interval"] >= 0 and entry["mean"] == entry["mean"], name  # no NaN


def test_evaluate_writes_every_metric(setup, hash_text_encoder, tmp_path: Path) -> None:
    out = tmp_path / "segmo"
    main(["--model", str(setup["segmo"]), "--data", str(setup["data"]), "--evaluator", str(setup["evaluator"]),
          "--action-classifier", str(setup["classifier"]), "--mm-prompts", "2", "--mm-repeats", "11",
          "--attribute-classifier", str(setup["attributes"]),
          "--retrieval-motions", "6", "--similarity-maps", "1", "--out", str(out), *COMMON])
    metrics = _strict_json(out / "metrics.json")
    generation = metrics["generation"]
    _check_repeated(generation["real"], GENERATION)
    _check_repeated(generation["generated"], GENERATION)
    # One MultiModality run (--mm-runs 1, the default): a mean without an interval (null)
    multimodality = generation["generated"]["multimodality"]
    assert multimodality["mean"] >= 0 and multimodality["interval"] is None
    assert 0 <= generation["generated"]["top1"]["mean"] <= generation["generated"]["top3"]["mean"] <= 1
    assert generation["real"]["fid"]["mean"] < 1e-6 + generation["real"]["fid"]["interval"] * 10
    reconstruction = generation["reconstruction"]
    _check_repeated(reconstruction, GENERATION)
    assert 0 < reconstruction["mpjpe_mm"] < 1e6 and reconstruction["motions"] == 10
    assert reconstruction["mpjpe_global_mm"] >= reconstruction["mpjpe_mm"] * 0.5
    buckets = generation["by_num_segments"]
    assert sum(v["count"] for v in buckets.values()) == metrics["config"]["captions"]
    model = SegMo.from_pretrained(setup["segmo"])
    captions = _split_captions(setup["data"], model)
    counts = [len(s) for s in model.segment_texts(captions)]
    assert ("1" in buckets) == (1 in counts) and ("2" in buckets) == (2 in counts)
    assert set(buckets) <= {"1", "2", "3", "4-5"} and {k for k in buckets if buckets[k]["count"]} == set(buckets)
    for entry in buckets.values():
        assert {"real", "generated", "reconstruction"} <= set(entry)
        # A bucket some repeat drew no caption of leaves its metrics out, and says so.
        assert ("matching" in entry["generated"]) == ("matching" not in entry["left_out"])
        if "matching" not in entry["left_out"]:
            _check_repeated(entry["generated"], ("matching",))
        # Batches of 8 within a bucket: R-precision only where a bucket fills one every repeat.
        assert ("top1" in entry["real"]) == ("top1" not in entry["left_out"])
    assert sum("matching" in entry["generated"] for entry in buckets.values()) >= 2
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
    assert {"cpd/R@1,IoU=0.5", "kmeans/mIoU"} <= set(grounding)
    assert {"attention/R@1,IoU=0.5", "attention_spans/mIoU"} <= set(grounding)
    assert all(0 <= grounding[k] <= 1 for k in grounding if k.startswith("attention"))
    assert "| k-means |" in (out / "report.md").read_text()
    assert set(metrics["isc"]) == {"uniform", "cpd", "kmeans"}
    assert all(v["pairs"] > 0 and -1 <= v["mean"] <= 1 for v in metrics["isc"].values())
    order = metrics["action_order"]
    assert order["real"]["motions"] == 10 and order["generated"]["motions"] == 10
    assert 0 <= order["generated"]["sequence_accuracy"] <= 1
    assert order["reconstruction"]["motions"] == 10
    assert sum(v["count"] for v in order["by_num_segments"].values()) == 10
    for row in ("generated", "reconstruction"):
        errors = order[row]["errors"]
        assert set(errors) == {"missing", "extra", "substituted", "reordered"}
        assert sum(errors.values()) == pytest.approx(1 - order[row]["sequence_accuracy"])
        found = order[row]["recall_by_share"]
        assert set(found) <= {"<0.2", "0.2-0.4", ">=0.4"} and all(0 <= v["recall"] <= 1 for v in found.values())
        assert sum(v["actions"] for v in found.values()) >= 10  # every first caption's actions
    assert "How sequences fail" in (out / "report.md").read_text()
    attributes = metrics["attributes"]
    assert set(attributes) == {"real", "reconstruction", "generated"}
    checks = attributes["real"]["checks"]
    assert checks > 0 and all(v["checks"] == checks for v in attributes.values())
    assert all(0 <= v["overall"] <= 1 and set(v) <= {"side", "count", "speed", "overall", "checks"}
               for v in attributes.values())
    config = metrics["config"]
    assert config["repeats"] == 2 and config["seed"] == 0 and config["timings"]["total"] > 0
    assert config["model"] == str(setup["segmo"]) and config["motions"] == 10
    text = (out / "report.md").read_text()
    assert "| Method | Top-1 | Top-2 | Top-3 | FID | MM-Dist | Diversity | MModality |" in text
    real_cell = f"{generation['real']['top1']['mean']:.3f}±{generation['real']['top1']['interval']:.3f}"
    assert f"| Real | {real_cell} |" in text and "| segmo |" in text
    assert "| segmo tokenizer (reconstruction) |" in text and "### By number of text segments" in text
    assert f"MPJPE {reconstruction['mpjpe_mm']:.1f} mm" in text
    for title in ("## Retrieval", "## Grounding", "## Intra-segment consistency", "## Action order",
                  "## Attribute accuracy"):
        assert title in text
    for row in ("| ordered spans |", "| best span |", "| sliding window |", "| uniform split |"):
        assert row in text
    assert (out / "isc.png").stat().st_size > 0
    assert len(list((out / "similarity_maps").glob("*.png"))) == 1

    # Same seed, same numbers: generation is seeded per batch. Into a folder that holds an
    # earlier evaluation's plots, which this one, skipping grounding and ISC, does not draw:
    # they were kept beside its metrics.json.
    again = tmp_path / "again"
    shutil.copytree(out, again, ignore=shutil.ignore_patterns("metrics.json", "report.md"))
    main(["--model", str(setup["segmo"]), "--data", str(setup["data"]), "--evaluator", str(setup["evaluator"]),
          "--mm-prompts", "0", "--skip", "reconstruction,retrieval,grounding,isc", "--action-classifier", "train",
          "--out", str(again), *COMMON])
    repeat = json.loads((again / "metrics.json").read_text())
    assert repeat["generation"]["generated"]["top1"] == generation["generated"]["top1"]
    assert "multimodality" not in repeat["generation"]["generated"]
    assert not {"retrieval", "grounding", "isc"} & set(repeat)
    assert not (again / "isc.png").exists() and not (again / "similarity_maps").exists()
    assert "reconstruction" not in repeat["generation"] and "reconstruction" not in repeat["action_order"]
    assert repeat["generation"]["by_num_segments"]["2"]["generated"] == buckets["2"]["generated"]
    # `--action-classifier train` fits one on the train split and keeps it.
    assert (again / "action_classifier" / "config.json").is_file()
    assert repeat["action_order"]["real"]["motions"] == 10

    # No alignment head: the learned-space sections are skipped; grounding keeps what needs
    # only the mask transformer (attention) and the text-free baselines, on the same queries.
    plain = tmp_path / "no_align"
    main(["--model", str(setup["no_align"]), "--data", str(setup["data"]), "--evaluator", str(setup["evaluator"]),
          "--mm-prompts", "0", "--skip", "action_order", "--out", str(plain), *COMMON])
    plain_metrics = json.loads((plain / "metrics.json").read_text())
    assert "isc" not in plain_metrics
    assert set(plain_metrics["retrieval"]) == {"evaluator"}
    attention_only = plain_metrics["grounding"]
    assert attention_only["queries"] == grounding["queries"]
    assert {"attention/R@1,IoU=0.5", "attention_spans/mIoU", "uniform/mIoU", "kmeans/mIoU"} <= set(attention_only)
    assert not {"mIoU", "R@1,IoU=0.5", "spans/mIoU", "window/mIoU"} & set(attention_only)
    assert attention_only["uniform/mIoU"] == grounding["uniform/mIoU"]  # text-free: the same spans
    assert "no alignment head" in plain_metrics["notes"]["grounding"]
    plain_report = (plain / "report.md").read_text()
    assert "| attention, ordered spans |" in plain_report and "| ordered spans |" not in plain_report
    assert not (plain / "similarity_maps").exists()
    _check_repeated(plain_metrics["generation"]["generated"], GENERATION)

    main(["--compare", str(out), str(plain / "metrics.json"), "--out", str(tmp_path / "cmp")])
    table = (tmp_path / "cmp" / "compare.md").read_text().splitlines()
    assert table[0].startswith("| Method | Top-1") and [r.split(" |")[0] for r in table[2:]] == [
        "| Real", "| segmo tokenizer (reconstruction)", "| segmo", "| no_align tokenizer (reconstruction)",
        "| no_align"]
    # The null interval of MultiModality reads as NaN: the mean alone.
    assert table[4].endswith(f"| {multimodality['mean']:.3f} |")


def test_multimodality_records_the_prompts_it_had(setup, hash_text_encoder, tmp_path: Path) -> None:
    """Fewer motions than --mm-prompts: MultiModality ran over every motion there was, but
    the report said "of 100 prompts" and metrics.json kept only the request."""
    out = tmp_path / "mm"
    with pytest.warns(UserWarning, match="--mm-prompts 100: the split has 10 motions"):
        main(["--model", str(setup["segmo"]), "--data", str(setup["data"]), "--evaluator",
              str(setup["evaluator"]), "--mm-prompts", "100", "--mm-repeats", "11",
              "--skip", ",".join(SECTIONS), "--out", str(out), *COMMON])
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["generation"]["generated"]["multimodality_prompts"] == 10
    assert metrics["config"]["mm_prompts"] == 100  # what was asked, beside what ran
    text = (out / "report.md").read_text()
    assert "MModality over 1 run(s) of 10 prompts × 11 generations (--mm-prompts 100" in text


def test_real_only(setup, tmp_path: Path) -> None:
    out = tmp_path / "real"
    main(["--real-only", "--data", str(setup["data"]), "--evaluator", str(setup["evaluator"]),
          "--out", str(out), *COMMON])
    metrics = json.loads((out / "metrics.json").read_text())
    assert set(metrics["generation"]) == {"real", "by_num_segments"}
    # Without a model nor --text-segments, the data give each caption one segment.
    assert list(metrics["generation"]["by_num_segments"]) == ["1"]
    assert metrics["generation"]["by_num_segments"]["1"]["count"] == metrics["config"]["captions"]
    _check_repeated(metrics["generation"]["real"], GENERATION)
    assert set(metrics["retrieval"]) == {"evaluator"}
    text = (out / "report.md").read_text()
    assert "| Real |" in text and "## Grounding" not in text


def _split_captions(data: Path, model) -> list[str]:
    from segmo.evaluation.sections import EvaluateConfig, load_batches

    cfg = EvaluateConfig(data=str(data), evaluator="", out="", split="train", max_motions=10)
    _, batches = load_batches(cfg, model.skeleton.name)
    return [c for b in batches for c in b["caption"]]


def test_reconstruction_is_decode_of_encode(setup) -> None:
    """Each row of the reconstruction is the tokenizer's decode(encode(motion)) at the
    motion's length, in the dataset's z-score, and zero past it."""
    from segmo.evaluation.cli import Reconstructor
    from segmo.evaluation.sections import EvaluateConfig, load_batches

    model = SegMo.from_pretrained(setup["segmo"])
    cfg = EvaluateConfig(data=str(setup["data"]), evaluator="", out="", split="train", max_motions=3,
                         progress=False)
    ds, batches = load_batches(cfg, model.skeleton.name)
    reconstruct = Reconstructor(model, cfg, ds, batches)
    b = batches[0]
    got = reconstruct(b["motion"], b["lengths"], b["id"])
    assert got.shape == b["motion"].shape and reconstruct.errors["motions"] == 3
    tok = model.tokenizer
    mean, std = torch.as_tensor(ds.mean), torch.as_tensor(ds.std)
    for r in range(len(b["id"])):
        t = int(b["lengths"][r])
        raw = b["motion"][r, :t] * std + mean
        with torch.no_grad():
            want = tok.denormalize(tok.decode(tok.encode(tok.normalize(raw)[None])))[0]
        torch.testing.assert_close(got[r, :t], (want - mean) / std, atol=1e-4, rtol=1e-4)
        assert not got[r, t:].any()
    assert not torch.allclose(got[0, :int(b["lengths"][0])], b["motion"][0, :int(b["lengths"][0])])


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
    wordless = tmp_path / "wordless"  # an evaluator without its vocabulary: refused before the work
    shutil.copytree(setup["evaluator"], wordless)
    config = json.loads((wordless / "config.json").read_text())
    del config["meta"]["words"]
    (wordless / "config.json").write_text(json.dumps(config))
    line = cli_failure([*base, "--real-only", "--evaluator", str(wordless)], capsys)
    assert line == (f"segmo evaluate: --evaluator {wordless}: config.json's meta has no 'words' (the "
                    "vocabulary `segmo export` of an evaluator writes)")
    for flag, value in (("--repeats", "0"), ("--batch-size", "1"), ("--seed", "-2"),
                        ("--grounding-window", "4,x"), ("--split", "nosuch")):
        assert flag in cli_failure([*base, "--real-only", flag, value], capsys)


def test_metrics_readers_take_null_as_nan_and_older_files_read_as_before(tmp_path: Path) -> None:
    """metrics.json holds null where a figure is NaN (one repeat, one MultiModality run);
    one written before holds bare NaN. Every reader shows both alike."""
    from segmo.evaluation.seeds import figures, seed_table
    from segmo.pipeline.bundle import SegMoConfig
    from segmo.pipeline.model_card import model_card, read_metrics

    nan = float("nan")
    row = {"top1": {"mean": 0.5, "interval": nan}, "fid": {"mean": 1.25, "interval": nan},
           "multimodality": {"mean": 2.0, "interval": nan}}
    metrics = {"generation": {"real": row, "generated": row},
               "action_order": {"generated": {"sequence_accuracy": nan, "motions": 3.0}},
               "isc": {"uniform": {"mean": 0.25, "cv": nan, "pairs": 4.0}},
               "config": {"name": "m", "segmenter": None}}
    older = json.dumps(metrics, indent=2)
    assert "NaN" in older
    newer = older.replace("NaN", "null")
    outputs = []
    for name, text in (("older", older), ("newer", newer)):
        (tmp_path / name).mkdir()
        path = tmp_path / name / "metrics.json"
        path.write_text(text)
        read = read_metrics(path)
        main(["--compare", str(path), "--out", str(tmp_path / name)])
        grid = load_tool("ablation_grid")
        seeds = load_tool("compare_seeds")
        outputs.append([
            (tmp_path / name / "compare.md").read_text(),
            report.generation_table([("m", read["generation"]["generated"])]),
            seed_table([("m", [read], ["generation/generated/top1", "generation/generated/fid"])], ["a", "b"]),
            sorted(k for k, v in figures(read).items() if v == v),
            grid.isc_grid({"in_sample": read}),
            seeds.compare([seeds.read_result(path)], [read], ("a", "b"), ["generation/generated/top1"]),
            model_card(SegMoConfig(text_encoder="hash16"), {}, read)])
    assert outputs[0] == outputs[1]
    assert "| m | 0.500 | - | - | 1.250 | - | - | 2.000 |" in outputs[1][1]
    assert "| Top-1 | FID |" in outputs[1][-1] and "| 0.500 | 0.500 | 1.250 |" in outputs[1][-1]
    assert "nan |" in outputs[1][-1]  # the NaN (null) action order figure, as before


def test_report_tables() -> None:
    entry = {"mean": 0.5534, "interval": 0.0031}
    table = report.generation_table([("SegMo", {"top1": entry, "fid": {"mean": 0.042, "interval": 0.002}})])
    assert table.splitlines()[2] == "| SegMo | 0.553±0.003 | - | - | 0.042±0.002 | - | - | - |"
    with pytest.raises(ValueError, match="no run"):
        report.compare_table([("a", {"generation": {}})])
    # A row name holding '|' or a line break (a --name, a config.name) stays one table row.
    table = report.generation_table([("x | y\nz", {"fid": 1.0})])
    assert table.splitlines()[2].startswith("| x \\| y z | ") and len(table.splitlines()) == 3


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


def test_ablation_dry_run_with_seeds(tmp_path: Path) -> None:
    result = subprocess.run(
        [sys.executable, str(REPO / "tools" / "ablation_grid.py"), "--data", "D", "--tokenizer", "T",
         "--evaluator", "E", "--variants", "in_sample,none", "--seeds", "0,1,2", "--parallel", "2",
         "--residual", "R", "--length", "L", "--out", str(tmp_path), "--dry-run"],
        capture_output=True, text=True, cwd=REPO, check=True)
    fits = [line for line in result.stdout.splitlines() if " fit " in line]
    assert len(fits) == 6
    for variant in ("in_sample", "none"):
        for seed in (0, 1, 2):
            assert sum(f"--seed_everything {seed}" in line and f"mask_{variant}_s{seed}" in line
                       for line in fits) == 1


def test_ablation_paths_are_the_callers_and_a_failed_command_is_one_line(tmp_path, monkeypatch,
                                                                          capsys) -> None:
    grid = load_tool("ablation_grid")
    monkeypatch.chdir(tmp_path)
    for folder in ("D", "T", "E"):
        (tmp_path / folder).mkdir()
    argv = ["--data", "D", "--tokenizer", "T", "--evaluator", "E", "--variants", "none",
            "--residual", "R", "--length", "L", "--out", "out"]
    grid.main([*argv, "--dry-run"])
    fit = next(line for line in capsys.readouterr().out.splitlines() if " fit " in line)
    # the commands run in the repository: relative paths are the caller's, made absolute
    assert f"--data.root {tmp_path / 'D'} " in fit and f"--runs_dir {tmp_path / 'out' / 'runs'} " in fit
    monkeypatch.setattr(grid, "SEGMO", [sys.executable, "-c", "import sys; sys.exit(3)"])
    with pytest.raises(SystemExit) as stop:  # as a command: one line, exit status 2
        run_command("ablation_grid.py", grid.main, argv)
    error = capsys.readouterr().err.strip()
    assert stop.value.code == 2 and len(error.splitlines()) == 1
    assert error.startswith("ablation_grid.py: exit status 3, see its output above: ")
    assert not (tmp_path / "out" / "table3.md").exists()
    with pytest.raises(SegmoError) as refused:  # before any training
        grid.main([*argv, "--eval-args", "'unclosed"])
    assert str(refused.value) == ("--eval-args \"'unclosed\": No closing quotation "
                                  "(see `ablation_grid.py --help`)")


def test_seeds_report_has_a_table_per_bucket() -> None:
    grid = load_tool("ablation_grid")
    entry = {"mean": 0.7, "interval": 0.01}
    run = {"generation": {"real": {"top1": entry}, "generated": {"top1": {"mean": 0.6}},
                          "by_num_segments": {"1": {"generated": {"top1": {"mean": 0.8}}}}},
           "action_order": {"by_num_segments": {"1": {"generated": {"sequence_accuracy": 0.9}}}}}
    text = grid.seeds_report({"in_sample": [run, run]})
    assert "| real motions | 1 | 0.700 |" in text
    assert "| SegMo | 2 | 0.600±0.000 |" in text
    assert "Captions with 1 text segment(s):" in text
    assert "| SegMo | 2 | 0.800±0.000 | – | – | – | 0.900±0.000 |" in text


def test_isc_grid_has_a_row_per_training_segmenter() -> None:
    grid = load_tool("ablation_grid")
    run = {"isc": {"uniform": {"mean": 0.61, "cv": 0.25}, "cpd": {"mean": 0.52, "cv": 0.4}}}
    table = grid.isc_grid({"in_sample": run, "cpd": {"isc": {"cpd": {"mean": 0.7, "cv": 0.1}}}})
    lines = table.splitlines()
    assert lines[0].endswith("| cpd | uniform |")
    assert lines[2] == "| uniform | 0.520 (CV 0.40) | 0.610 (CV 0.25) |"
    assert lines[3] == "| cpd | 0.700 (CV 0.10) | – |"


def test_ablation_truth_variant_trains_and_evaluates_on_the_truth_segments(tmp_path: Path) -> None:
    result = subprocess.run(
        [sys.executable, str(REPO / "tools" / "ablation_grid.py"), "--data", "D", "--tokenizer", "T",
         "--evaluator", "E", "--variants", "truth", "--residual", "R", "--length", "L",
         "--out", str(tmp_path), "--dry-run"], capture_output=True, text=True, cwd=REPO, check=True)
    lines = result.stdout.splitlines()
    assert any(" fit " in line and "--data.text_segments truth" in line for line in lines)
    assert any(" evaluate " in line and "--text-segments truth" in line for line in lines)
    (tmp_path / "data").mkdir()
    refused = subprocess.run(
        [sys.executable, str(REPO / "tools" / "ablation_grid.py"), "--data", str(tmp_path / "data"),
         "--tokenizer", str(tmp_path), "--evaluator", str(tmp_path), "--variants", "truth",
         "--out", str(tmp_path / "out")], capture_output=True, text=True, cwd=REPO)
    assert refused.returncode == 2 and "tools/truth_segments.py" in refused.stderr.splitlines()[-1]


def test_attention_report_writes_tables_plots_and_a_json_line(setup, hash_text_encoder, tmp_path, capsys):
    tool = load_tool("attention_report")
    out = tmp_path / "attention"
    assert tool.main(["--model", str(setup["segmo"]), "--data", str(setup["data"]), "--split", "train",
                      "--out", str(out), "--motions", "6", "--plots", "2"]) == 0
    last = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert last == json.loads((out / "attention.json").read_text())
    assert last["motions"] == 6 and set(last["sink_ratio"]["by_block"]) == {"0"}
    for name in ("sink_ratio", "prefix_share", "sentence_share", "attention_grounding"):
        assert 0.0 <= last[name]["mean"] <= 1.0, name
    assert last["attention_grounding"]["tokens"] > 0
    # A model without word keys: the prefix mass is the sentence's and the segments'.
    shares = last["kind_share"]
    assert set(shares) == {"sentence", "segments"} and "cross_gate" not in last
    assert shares["sentence"]["mean"] + shares["segments"]["mean"] == pytest.approx(1.0)
    assert 1 <= len(last["plots"]) <= 2 and all(Path(p).is_file() for p in last["plots"])
    assert "| all |" in (out / "attention.md").read_text()


def test_attention_report_on_words_read_by_cross_attention(setup, hash_text_encoder, tmp_path, capsys):
    # Words read by cross-attention are not keys of the recorded self-attention: no word
    # panel (it once asked the recording for word keys it does not have), the gates instead.
    from segmo.models.mask_transformer import MaskTransformer, MaskTransformerConfig
    from segmo.models.residual_transformer import ResidualTransformer, ResidualTransformerConfig
    from segmo.pipeline.bundle import SegMoConfig

    tool = load_tool("attention_report")
    tokenizer = SegMo.from_pretrained(setup["segmo"]).tokenizer
    torch.manual_seed(0)
    tiny = dict(TINY, text_tokens="words", word_attention="cross")
    bundle = SegMo(tokenizer, MaskTransformer(MaskTransformerConfig(**tiny)),
                   ResidualTransformer(ResidualTransformerConfig(**tiny, num_quantizers=3)),
                   config=SegMoConfig(text_encoder=ENCODER), text_encoder=hash_encoder(ENCODER, 16))
    assert bundle.uses_words and not bundle.has_word_keys
    folder = bundle.save_pretrained(tmp_path / "cross")
    out = tmp_path / "attention"
    assert tool.main(["--model", str(folder), "--data", str(setup["data"]), "--split", "train",
                      "--out", str(out), "--motions", "6", "--plots", "2"]) == 0
    last = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert set(last["kind_share"]) == {"sentence", "segments"} and set(last["cross_gate"]) == {"0"}
    assert 1 <= len(last["plots"]) <= 2 and all(Path(p).is_file() for p in last["plots"])


def test_order_by_template_scores_each_caption_template(setup, hash_text_encoder, tmp_path, capsys):
    tool = load_tool("order_by_template")
    assert tool.main(["--model", str(setup["segmo"]), "--data", str(setup["data"]), "--split", "train",
                      "--action-classifier", str(setup["classifier"]), "--repeats", "1"]) == 0
    last = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    rows = tool.multi_segment_rows(setup["data"], "train", 196)
    assert last["all"]["motions"] == len(rows) == sum(v["motions"] for v in last["by_template"].values())
    assert set(last["by_template"]) == {r["template"] for r in rows}
    assert all(0.0 <= v["sequence_accuracy"] <= 1.0 for v in last["by_template"].values())
    # by the true number of actions: every row once in 2 / 3 / 4-5, the 3+ rows again in "3+"
    counts = {k: v["motions"] for k, v in last["by_num_actions"].items()}
    assert sum(counts.get(k, 0) for k in ("2", "3", "4-5")) == len(rows)
    assert counts.get("3+", 0) == sum(r["num_actions"] >= 3 for r in rows)
    assert counts.get("3+", 0) == counts.get("3", 0) + counts.get("4-5", 0)
    # Train captions never use the held-out templates.
    assert "held_out" not in last and last["trained"] == last["all"]
    assert last["word_text"] == "caption"  # the bundle's
    assert tool.main(["--model", str(setup["segmo"]), "--data", str(setup["data"]), "--split", "train",
                      "--action-classifier", str(setup["classifier"]), "--repeats", "1",
                      "--word-text", "segments"]) == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["word_text"] == "segments"
    assert tool.main(["--model", str(setup["segmo"]), "--data", str(setup["data"]), "--split", "train",
                      "--action-classifier", str(setup["classifier"]), "--repeats", "1",
                      "--segment-guidance", "0.5"]) == 0
    last = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert (last["segment_guidance"], last["choice_temperature"]) == (0.5, 0.0)
    assert tool.main(["--model", str(setup["segmo"]), "--data", str(setup["data"]), "--split", "train",
                      "--action-classifier", str(setup["classifier"]), "--repeats", "1",
                      "--choice-temperature", "4.5"]) == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["choice_temperature"] == 4.5
    sink = tmp_path / "sink"  # options that clash: one line, no generation
    shutil.copytree(setup["segmo"], sink)
    config = json.loads((sink / "segmo.json").read_text())
    (sink / "segmo.json").write_text(json.dumps({**config, "guidance": "sink_ctrl"}))
    assert tool.main(["--model", str(sink), "--data", str(setup["data"]), "--split", "train",
                      "--action-classifier", str(setup["classifier"]),
                      "--segment-guidance", "1"]) == 2
    assert "segment_guidance works with guidance 'cfg' only" in capsys.readouterr().err
    plain = tmp_path / "plain"
    (plain / "new_joint_vecs").mkdir(parents=True)
    assert tool.main(["--model", str(setup["segmo"]), "--data", str(plain),
                      "--action-classifier", str(setup["classifier"])]) == 2
    assert "ground truth" in capsys.readouterr().err


def test_order_by_template_splits_generation_by_the_tokenizers_reconstruction(
        setup, hash_text_encoder, capsys):
    tool = load_tool("order_by_template")
    assert tool.main(["--model", str(setup["segmo"]), "--data", str(setup["data"]), "--split", "train",
                      "--action-classifier", str(setup["classifier"]), "--repeats", "2",
                      "--reconstruction"]) == 0
    last = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    for bucket, value in last["by_num_actions"].items():
        kept = last["generated_where_reconstructed"].get(bucket, {"motions": 0, "sequence_accuracy": 0.0})
        lost = last["generated_where_not"].get(bucket, {"motions": 0, "sequence_accuracy": 0.0})
        # every caption of the bucket on one side, and the two sides average to the whole
        assert kept["motions"] + lost["motions"] == value["motions"]
        assert last["reconstruction"][bucket]["motions"] == value["motions"]
        assert kept["motions"] == round(last["reconstruction"][bucket]["sequence_accuracy"] * value["motions"])
        assert (kept["sequence_accuracy"] * kept["motions"] + lost["sequence_accuracy"] * lost["motions"]
                == pytest.approx(value["sequence_accuracy"] * value["motions"]))
        assert 0 <= value["never_right"] <= value["motions"]

    # A reader that reads every motion right, or none: the split and never_right follow.
    model = SegMo.from_pretrained(setup["segmo"])
    rows = tool.multi_segment_rows(setup["data"], "train", model.max_frames)[:3]

    class Reader:  # the rows' true actions in turn (the tool reads rows in order), or nothing
        def __init__(self, right: bool):
            self.right, self.frames = right, []

        def predict_sequence(self, features):
            row = rows[len(self.frames) % len(rows)]
            self.frames.append(len(features))
            return row["actions"] if self.right else ["nothing"]

    for right in (True, False):
        reader = Reader(right)
        read_right = tool.reconstructions_read_right(model, reader, rows, setup["data"])
        assert read_right.tolist() == [right] * len(rows)
        assert reader.frames == [r["frames"] for r in rows]  # each motion at its own length
        result = tool.order_by_template(model, reader, rows, 1, 0, reconstructed=read_right)
        assert result["all"]["sequence_accuracy"] == float(right)
        assert result["all"]["never_right"] == (0 if right else len(rows))
        assert sum(v["motions"] for k, v in result["generated_where_reconstructed"].items()
                   if k != "3+") == (len(rows) if right else 0)


def test_order_by_template_gives_a_timing_model_the_true_durations(setup, hash_text_encoder,
                                                                    capsys, monkeypatch):
    tool = load_tool("order_by_template")
    common = ["--data", str(setup["data"]), "--split", "train", "--action-classifier",
              str(setup["classifier"]), "--repeats", "1"]
    seen = []
    real = SegMo.generate

    def spy(self, texts, lengths, **options):
        seen.append(options)
        return real(self, texts, lengths, **options)

    monkeypatch.setattr(SegMo, "generate", spy)
    assert tool.main(["--model", str(setup["timed"]), *common, "--segment-timing", "truth"]) == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["segment_timing"] == "truth"
    rows = tool.multi_segment_rows(setup["data"], "train", 196)
    durations = [d for options in seen for d in options["durations"]]
    assert durations == [r["durations"] for r in rows]
    segments = [s for options in seen for s in options["segments"]]
    assert all(len(s) == len(d) for s, d in zip(segments, durations))
    assert tool.main(["--model", str(setup["timed"]), *common, "--segment-timing", "none"]) == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["segment_timing"] == "none"
    assert tool.main(["--model", str(setup["segmo"]), *common, "--segment-timing", "truth"]) == 2
    assert "has no segment timing" in capsys.readouterr().err


def test_order_by_template_composes_each_caption_segment_by_segment(setup, hash_text_encoder,
                                                                     capsys, monkeypatch):
    tool = load_tool("order_by_template")
    common = ["--model", str(setup["segmo"]), "--data", str(setup["data"]), "--split", "train",
              "--action-classifier", str(setup["classifier"]), "--repeats", "1"]
    parts, real = [], SegMo.compose

    def spy(self, given, transition, **options):
        parts.append((given, transition))
        return real(self, given, transition, **options)

    monkeypatch.setattr(SegMo, "compose", spy)
    assert tool.main([*common, "--compose", "8"]) == 0
    last = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    rows = tool.multi_segment_rows(setup["data"], "train", 196)
    assert last["compose"] == 8 and last["all"]["motions"] == len(rows) == len(parts)
    for row, (given, transition) in zip(rows, parts):
        frames = [f for _, f in given]
        assert transition == 8 and len(given) == row["num_actions"]
        assert all(f % 4 == 0 and f >= tool.COMPOSE_MIN_PART for f in frames)
        # each segment its true share of the frames beside the transitions, in whole tokens
        left = row["frames"] - 8 * (len(given) - 1)
        shares = [left * d / sum(row["durations"]) for d in row["durations"]]
        assert all(abs(f - max(w, tool.COMPOSE_MIN_PART)) <= 2 for f, w in zip(frames, shares))
    for bad in (["--compose", "6"], ["--compose", "8", "--segment-timing", "none"]):
        with pytest.raises(SystemExit):
            tool.main([*common, *bad])
        assert "--compose" in capsys.readouterr().err


def test_attention_report_refuses_data_without_ground_truth(setup, hash_text_encoder, tmp_path, capsys):
    tool = load_tool("attention_report")
    plain = tmp_path / "plain"
    (plain / "new_joint_vecs").mkdir(parents=True)
    assert tool.main(["--model", str(setup["segmo"]), "--data", str(plain), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(plain) in err[0] and "ground truth" in err[0]


def test_sampling_options_only_a_sampling_carries_reach_generate(setup, hash_text_encoder) -> None:
    """--ctrl-k-base, --unconditional and --word-text replace the bundle's values and keep its others;
    without them the bundle's sampling is used as it is."""
    import numpy as np

    from segmo.evaluation.cli import Generator
    from segmo.evaluation.sections import EvaluateConfig

    model = SegMo.from_pretrained(setup["segmo"])
    seen = []
    real = model.generate
    model.generate = lambda *a, **k: seen.append(k.get("sampling")) or real(*a, **k)
    mean, std = np.zeros(263, np.float32), np.ones(263, np.float32)
    for given in ({}, {"ctrl_k_base": 0.25, "unconditional": "local", "word_text": "segments",
                       "segment_timing": "none", "remasking": "segments",
                       "segment_guidance": 0.5, "choice_temperature": 2.0}):
        cfg = EvaluateConfig(data="", evaluator="", out="", progress=False, **given)
        Generator(model, cfg, mean, std)(["a person walks forward"], torch.tensor([8]), seed=0)
    assert seen[0] is None
    assert (seen[1].ctrl_k_base, seen[1].unconditional, seen[1].word_text,
            seen[1].segment_timing, seen[1].remasking, seen[1].segment_guidance,
            seen[1].choice_temperature) == (0.25, "local", "segments", "none", "segments", 0.5, 2.0)
    assert seen[1].guidance_scale == model.sampling.guidance_scale


def test_fid_floor_rows_follow_the_draws() -> None:
    """Two draws of the whole split are the same set (FID 0); other motions of the same
    distribution lie apart by a bias that shrinks with N; a shifted distribution lies far;
    a remade row pairs each motion with its remake and its caption (R-precision)."""
    import numpy as np

    tool = load_tool("fid_floor")
    rng = np.random.default_rng(0)
    split, same = rng.normal(size=(64, 4)), rng.normal(size=(2000, 4))
    text = [np.stack([m + 0.1 * rng.normal(size=4) for _ in range(3)]) for m in split]  # 3 captions beside each
    remade = {"same parameters": [split + 0.01 * rng.normal(size=split.shape) for _ in range(3)]}
    rows = tool.floor(split, text, same, n=64, sizes=[16, 512], repeats=5, seed=0, resampled=remade)
    assert list(rows) == ["itself", "other", "disjoint 16", "disjoint 512", "resampled, same parameters"]
    assert abs(rows["itself"]["fid"]["mean"]) < 1e-6 and rows["itself"]["motions"] == 64
    assert rows["disjoint 16"]["fid"]["mean"] > 5 * rows["disjoint 512"]["fid"]["mean"] > 0
    assert set(rows["other"]) == {"motions", "fid"}
    remake = rows["resampled, same parameters"]
    assert set(remake) == {"motions", "top1", "matching", "fid", "diversity"}
    assert remake["top1"]["mean"] > 0.9 and rows["itself"]["top1"]["mean"] > 0.9
    assert 0 < remake["fid"]["mean"] < 0.01 * rows["other"]["fid"]["mean"]
    shuffled = tool.floor(split, text[::-1], same, n=64, sizes=[], repeats=5, seed=0, resampled=remade)
    assert shuffled["resampled, same parameters"]["top1"]["mean"] < 0.5  # captions of other motions
    shifted = tool.floor(split, text, same + 3.0, n=64, sizes=[], repeats=5, seed=0)
    assert shifted["other"]["fid"]["mean"] > 30 > 3 * rows["other"]["fid"]["mean"]  # 4 dims × 3² apart
    table = tool.table(rows, "test", "train")
    assert "| test against as many train motions | 64 | – | – |" in table
    assert "| test made again, same parameters | 64 |" in table
    assert "order" not in table  # no classifier, no order columns
    orders = {"itself": [{"order, 3+ actions": 1.0}] * 5,
              "same parameters": [{"order, 3+ actions": x} for x in (0.5, 0.6, 0.7)]}
    read = tool.floor(split, text, same, n=64, sizes=[], repeats=5, seed=0, resampled=remade, orders=orders)
    assert read["itself"]["order, 3+ actions"] == {"mean": 1.0, "interval": 0.0}
    assert abs(read["resampled, same parameters"]["order, 3+ actions"]["mean"] - 0.6) < 1e-9
    assert read["resampled, same parameters"]["fid"] == pytest.approx(remake["fid"])  # same draws, orders beside
    assert "| Top-1 | MM-Dist | FID | Diversity | order, 3+ actions |" in tool.table(read, "test", "train")


def test_fid_floor_mistakes_leave_out_short_actions_or_draw_parameters_anew() -> None:
    import numpy as np

    tool = load_tool("fid_floor")
    actions = [{"action": "walk_forward", "params": {"speed": 1.1, "steps": 8}},
               {"action": "clap", "params": {"count": 3, "tempo": 1.9}},
               {"action": "sit_down", "params": {"duration": 1.3}}]
    rng = np.random.default_rng(0)
    assert [a["action"] for a in tool.with_mistake(actions, "left out", 1.0, rng, 3)] == ["walk_forward", "sit_down"]
    assert tool.with_mistake(actions[1:2], "left out", 1.0, rng, 3) == actions[1:2]  # never the last one
    assert tool.with_mistake(actions, "left out", 1e-9, rng, 3) == actions
    misnamed = tool.with_mistake(actions, "misnamed", 1.0, rng, 3)
    assert [a["action"] for a in misnamed] == [a["action"] for a in actions]
    assert all(new["params"] != old["params"] for new, old in zip(misnamed, actions))
    from segmo.synth.actions import ACTIONS
    from segmo.synth.sequence import SHORT_V2

    for _ in range(20):  # substituted: only the clap, by a short action unlike its neighbours and itself
        names = [a["action"] for a in tool.with_mistake(actions, "substituted", 1.0, rng, 3)]
        assert names[::2] == ["walk_forward", "sit_down"] and names[1] in SHORT_V2
        assert names[1] not in ("walk_forward", "clap", "sit_down")
        extra = [a["action"] for a in tool.with_mistake(actions, "extra", 1.0, rng, 3)]  # one before each but the first
        assert extra[::2] == [a["action"] for a in actions] and len(extra) == 5
        assert all(x in SHORT_V2 and x not in (extra[i], extra[i + 2]) for i, x in zip((0, 2), extra[1::2]))
        assert ACTIONS[extra[3]].needs in ("any", "standing")  # before sit_down: still standing
    mixed = [[a["action"] for a in tool.with_mistake(actions, "mixed", 0.9, rng, 3)] for _ in range(200)]
    assert {len(m) for m in mixed} >= {2, 3, 4}  # some left out, some put in
    assert any(len(m) == 3 and m[1] != "clap" for m in mixed)  # some substituted
    seated = [{"action": "sit_down", "params": {"duration": 1.3}}, {"action": "clap", "params": {"count": 3}}]
    assert all(ACTIONS[a["action"]].needs in ("any", "sitting")
               for _ in range(20) for a in tool.with_mistake(seated, "substituted", 1.0, rng, 3)[1:])
    # stretched to a length: the ends kept, evenly in between
    from segmo.synth.actions import resample_frames

    joints = np.arange(11, dtype=float)[:, None, None] * np.ones((1, 2, 3))
    longer = resample_frames(joints, 21)
    assert longer.shape == (21, 2, 3) and longer[0, 0, 0] == 0 and longer[-1, 0, 0] == 10
    assert np.allclose(np.diff(longer[:, 0, 0]), 0.5)
    assert np.allclose(resample_frames(joints, 11), joints)


def test_fid_floor_end_to_end_and_its_errors(setup, tmp_path: Path, capsys) -> None:
    tool = load_tool("fid_floor")
    common = ["--data", str(setup["data"]), "--evaluator", str(setup["evaluator"]), "--batch-size", "2"]
    out = tmp_path / "floor.json"
    assert tool.main([*common, "--repeats", "2", "--sizes", "4", "--resample", "--mistakes", "0.5",
                      "--action-classifier", str(setup["classifier"]), "--out", str(out)]) == 0
    rows = json.loads(out.read_text())["rows"]
    assert list(rows) == ["itself", "other", "disjoint 4", "resampled, same parameters",
                          "resampled, the caption's parameters", "resampled, new parameters",
                          "resampled, the caption's parameters, 50% of the short actions left out",
                          "resampled, the caption's parameters, 50% of the short actions left out, stretched",
                          "resampled, the caption's parameters, 50% of the short actions substituted",
                          "resampled, the caption's parameters, 50% of the actions with a short one before",
                          "resampled, the caption's parameters, 50% of the actions misnamed",
                          "resampled, the caption's parameters, 50% of the actions wrong, a third each left out, "
                          "substituted, extra"]
    assert rows["disjoint 4"]["motions"] == 4 and "top1" in rows["resampled, new parameters"]
    # action order beside every row a classifier reads (the tiny test split: 2, 3 and 4 actions)
    assert all({"order, 2+ actions", "order, 3+ actions"} <= set(r) for name, r in rows.items()
               if name == "itself" or name.startswith("resampled"))
    assert all(0 <= r["order, 3+ actions"]["mean"] <= 1 for r in rows.values() if "order, 3+ actions" in r)
    assert "order" not in str(rows["other"]) + str(rows["disjoint 4"])
    assert all(m["mean"] == m["mean"] and m["interval"] >= 0 for r in rows.values()
               for k, m in r.items() if k != "motions")  # no NaN
    assert "| train against train, disjoint | 4 |" in capsys.readouterr().out
    assert tool.main([*common, "--repeats", "1", "--resample", "--mistakes", "0.5", "--kinds", "mixed",
                      "--out", str(out)]) == 0  # --kinds picks the error rows
    assert [r for r in json.loads(out.read_text())["rows"] if "%" in r] == [
        "resampled, the caption's parameters, 50% of the actions wrong, a third each left out, substituted, extra"]
    plain = tmp_path / "plain"  # a folder that is no built-in corpus
    plain.mkdir()
    mean = (setup["data"] / "Mean.npy").read_bytes()
    for argv, names in ((["--sizes", "4,x"], "--sizes"), (["--other", "test"], "--other"),
                        (["--sizes", "50"], "--other train"), (["--split", "nope"], "nope"),
                        (["--resample", "--data", str(plain)], "corpus.json"),
                        (["--mistakes", "0.5"], "--resample"), (["--resample", "--mistakes", "0,2"], "--mistakes"),
                        (["--data", str(tmp_path / "nowhere")], "--data"), (["--out", str(tmp_path)], "--out"),
                        (["--out", str(tmp_path / "no" / "floor.json")], "--out"),
                        (["--action-classifier", str(setup["evaluator"])], "--action-classifier"),
                        (["--action-classifier", str(tmp_path / "none")], "--action-classifier"),
                        (["--resample", "--mistakes", "0.5", "--kinds", "mixed,typo"], "--kinds"),
                        (["--resample", "--kinds", "mixed"], "--kinds"), (["--seed", "-1"], "--seed"),
                        (["--out", str(setup["data"] / "Mean.npy")], "inside --data")):
        assert tool.main([*common, *argv]) == 2
        err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
        assert len(err) == 1 and names in err[0], err
    assert (setup["data"] / "Mean.npy").read_bytes() == mean  # an input named as --out is left alone
    # a ground truth the corpus' generator cannot make again is named, in one line
    import shutil

    from segmo.data.layout import ground_truth_file

    broken = tmp_path / "broken"
    shutil.copytree(setup["data"], broken)
    truth_file = ground_truth_file(broken, (broken / "test.txt").read_text().split()[0])
    truth = json.loads(truth_file.read_text())
    truth["actions"][0]["action"] = "levitate"
    truth_file.write_text(json.dumps(truth))
    assert tool.main([*common, "--data", str(broken), "--resample", "--repeats", "1"]) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and str(truth_file) in err[0] and "levitate" in err[0], err


def test_order_by_stage_takes_the_stages_apart(setup, hash_text_encoder, capsys, monkeypatch):
    tool = load_tool("order_by_stage")
    model = SegMo.from_pretrained(setup["timed"])
    rows = tool.multi_segment_rows(setup["data"], "train", model.max_frames)
    answer = rows[0]["actions"]

    class Reader:  # reads every motion as the first row's actions: right exactly on its rows
        def eval(self):
            return self

        def predict_sequence(self, features):
            return answer

    right = [r["actions"] == answer for r in rows]
    layers, kept = tool.tokenizer_layers(model, Reader(), rows, setup["data"])
    assert kept.tolist() == right
    for bucket, value in layers.items():
        inside = [ok for r, ok in zip(rows, right) if bucket in tool.buckets(r["num_actions"])]
        assert value["motions"] == len(inside)
        assert value["sequence_accuracy"] == [sum(inside) / len(inside)] * model.tokenizer.num_quantizers
    kept_rows = [r for r, ok in zip(rows, right) if ok]
    result = tool.order_by_stage(model, Reader(), kept_rows, setup["data"], repeats=2, seed=0)
    for name in ("generated", "residual"):  # every kept caption read once per repeat
        assert {k: v["reads"] for k, v in result[name].items()} == {
            k: 2 * sum(k in tool.buckets(r["num_actions"]) for r in kept_rows) for k in result[name]}
        assert all(v["sequence_accuracy"] == 1.0 for v in result[name].values())
    q = model.residual.config.num_quantizers
    assert list(result["residual_layers"]) == [str(j) for j in range(1, q)]  # each layer alone
    for value in result["residual_layers"].values():
        assert value == result["residual"]
    for bucket, value in result["fill"].items():  # every segment once per repeat, in one place and size
        places = sum(value.get(k, {"reads": 0})["reads"] for k in ("first", "middle", "last"))
        sizes = sum(value.get(name, {"reads": 0})["reads"] for *_, name in tool.SHARES)
        segments = sum(r["num_actions"] for r in kept_rows if bucket in tool.buckets(r["num_actions"]))
        assert places == sizes == value["all"]["reads"] == 2 * segments

    # Drawing one segment keeps every other token; the residual draw keeps the base layer.
    b = tool.Batch(model, kept_rows[:3], setup["data"])
    span = b.inside[:, 0]
    drawn = tool.draw(model, b, span, seed=0)
    outside = b.token_mask & ~span
    assert torch.equal(drawn[outside], b.real[outside]) and bool(span.any())
    redrawn = tool.redraw_residual(model, b, seed=0)
    assert torch.equal(redrawn[..., 0], b.real[..., 0])
    assert not torch.equal(redrawn[b.token_mask][:, 1:], b.real[b.token_mask][:, 1:])
    first = tool.redraw_residual(model, b, seed=0, layers=[1])  # layer 1 alone: the rest real
    kept_layers = [j for j in range(q) if j != 1]
    assert torch.equal(first[b.token_mask][:, kept_layers], b.real[b.token_mask][:, kept_layers])
    assert not torch.equal(first[b.token_mask][:, 1], b.real[b.token_mask][:, 1])

    # The command: the JSON line, and one line when no reconstruction is read right.
    monkeypatch.setattr(tool, "load_pretrained", lambda path: Reader())
    common = ["--model", str(setup["timed"]), "--data", str(setup["data"]), "--split", "train",
              "--action-classifier", str(setup["classifier"]), "--repeats", "1"]
    assert tool.main(common) == 0
    last = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert last["kept"] == sum(right) and set(last) >= {"tokenizer_layers", "residual", "residual_layers",
                                                        "fill", "generated"}
    answer = ["nothing"]
    assert tool.main(common) == 2
    assert "no train caption's reconstruction is read right" in capsys.readouterr().err
