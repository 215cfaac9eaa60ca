"""The generator stages (mask, residual, length) through the real `segmo fit` CLI.

Every config under configs/{mask,residual,length}/ runs a fast dev run with shrunken
models on a tiny dataset; export gives a model directory that reproduces the task's
network; the alignment ablations all train a step.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import torch
import yaml
from conftest import cli_failure

from segmo.data.motion_tokens import tokenizer_digest
from segmo.models.mask_transformer import masked_token_loss
from segmo.models.pretrained import load_pretrained
from segmo.tasks.common import text_condition, token_lengths
from segmo.tasks.mask import (
    MaskTask,
    gt_token_spans,
    mask_whole_segment,
    reversed_order,
    segment_balanced_weights,
    segment_top1,
)
from segmo.training.cli import main as cli_main

REPO = Path(__file__).resolve().parents[1]
STAGES = ("mask", "residual", "length")
CONFIGS = sorted(p for s in STAGES for p in (REPO / "configs" / s).glob("*.yaml"))
TINY_TRANSFORMER = ["--model.init_args.dim=32", "--model.init_args.depth=1",
                    "--model.init_args.heads=2", "--model.init_args.ff_dim=32"]


def overrides(config: Path, data: dict, tokenizers: dict, runs: Path) -> list[str]:
    spec = yaml.safe_load(config.read_text())
    skeleton = spec["data"]["init_args"]["skeleton"]
    args = [f"--data.root={data[skeleton]}", f"--runs_dir={runs}",
            "--data.init_args.batch_size=4", "--trainer.enable_progress_bar=false"]
    if "tokenizer" in spec["model"]["init_args"]:
        args += [f"--model.init_args.tokenizer={tokenizers[skeleton]}", *TINY_TRANSFORMER]
        if "alignment_dim" in spec["model"]["init_args"]:
            args.append("--model.init_args.alignment_dim=16")
    else:
        args.append("--model.init_args.hidden=16")
    return args


@pytest.mark.parametrize("config", CONFIGS, ids=[f"{c.parent.name}/{c.stem}" for c in CONFIGS])
def test_fit_every_config(config, text_dataset, tokenizer_dir, tmp_path):
    cli = cli_main(["fit", "--config", str(config),
                    *overrides(config, text_dataset, tokenizer_dir, tmp_path / "runs"),
                    "--trainer.fast_dev_run=true"])
    assert cli.trainer.state.finished and cli.trainer.global_step == 1
    metrics = cli.trainer.callback_metrics
    assert torch.isfinite(metrics["train/loss"])
    assert "val/loss" in metrics or "val/mask_loss" in metrics
    # The encoder the model was trained with is recorded for inference.
    assert cli.model.hparams.text_encoder == cli.datamodule.hparams.text_features


@pytest.mark.parametrize("method,segmenter", [("none", "uniform"), ("batch", "cpd"),
                                              ("global", "uniform"), ("token", "kmeans")])
def test_alignment_ablations_train(method, segmenter, text_dataset, tokenizer_dir, tmp_path):
    config = REPO / "configs/mask/synthetic.yaml"
    cli = cli_main(["fit", "--config", str(config),
                    *overrides(config, text_dataset, tokenizer_dir, tmp_path / "runs"),
                    f"--model.init_args.alignment={method}",
                    f"--model.init_args.segmenter={segmenter}", "--trainer.fast_dev_run=true"])
    assert (cli.model.model.alignment is None) == (method == "none")
    assert ("train/align" in cli.trainer.callback_metrics) == (method != "none")


def _alignment_arguments(task, batch) -> tuple:
    """The arguments `task.step(batch)` (eval mode, no grad) hands its alignment loss."""
    handed, loss = [], task.alignment_loss

    class Recorder:  # the loss as it is, remembering what it was handed
        weight = loss.weight

        def __call__(self, *args):
            handed.append(args)
            return loss(*args)

    task.alignment_loss = Recorder()
    task.eval()
    with torch.no_grad():
        task.step(batch)
    task.alignment_loss = loss
    return handed[0]


def test_alignment_loss_is_handed_the_batch_s_related_samples(text_dataset, tokenizer_dir, tmp_path):
    """The task tells the loss which samples are one motion or one caption, so that the
    batch and global ablations do not take them as each other's negatives."""
    from segmo.data.collate import collate, related_samples

    config = REPO / "configs/mask/synthetic.yaml"
    cli = cli_main(["fit", "--config", str(config),
                    *overrides(config, text_dataset, tokenizer_dir, tmp_path / "runs"),
                    "--model.init_args.alignment=global", "--trainer.fast_dev_run=true"])
    task, ds = cli.model, cli.datamodule.dataset("train")
    assert ds[0]["id"] == ds[1]["id"] != ds[2]["id"]  # two captions of one motion, another
    batch = collate([ds[0], ds[1], ds[2]])
    related = _alignment_arguments(task, batch)[7]
    assert torch.equal(related.cpu(), related_samples(batch)) and related[0, 1]


@pytest.mark.parametrize("stage,option", [
    ("mask", "--model.init_args.sink_mask_t=0.2"), ("mask", "--model.init_args.memory_slots=4"),
    ("mask", "--model.init_args.local_uncond_prob=0.5"),
    ("residual", "--model.init_args.memory_slots=4"),
    ("residual", "--model.init_args.local_uncond_prob=0.5")])
def test_mlagen_options_train_and_reach_the_model(stage, option, text_dataset, tokenizer_dir,
                                                  tmp_path):
    config = REPO / f"configs/{stage}/synthetic.yaml"
    cli = cli_main(["fit", "--config", str(config),
                    *overrides(config, text_dataset, tokenizer_dir, tmp_path / "runs"), option,
                    "--trainer.fast_dev_run=true"])
    assert torch.isfinite(cli.trainer.callback_metrics["train/loss"])
    name, value = option.removeprefix("--model.init_args.").split("=")
    assert str(cli.model.hparams[name]) == value
    if hasattr(cli.model.model.config, name):  # a model option, not a training one
        assert str(getattr(cli.model.model.config, name)) == value


def test_a_mask_config_naming_the_former_temperature_still_trains(text_dataset, tokenizer_dir,
                                                                tmp_path):
    """Configs (and checkpoints) written before the alignment temperature got its own name
    hold `temperature`: it is read as alignment_temperature, with a warning."""
    old = tmp_path / "old.yaml"
    text = (REPO / "configs/mask/synthetic.yaml").read_text()
    old.write_text(text.replace("    alignment_temperature: 0.1", "    temperature: 0.2")
                   .replace("    max_tokens: 49\n", "    max_segments: 5\n    max_tokens: 49\n", 1))
    with pytest.warns(FutureWarning, match="former name of alignment_temperature"):
        cli = cli_main(["fit", "--config", str(old),
                        *overrides(old, text_dataset, tokenizer_dir, tmp_path / "runs"),
                        "--trainer.fast_dev_run=true"])
    assert cli.trainer.state.finished and cli.model.alignment_loss.temperature == 0.2
    assert cli.model.hparams.alignment_temperature == 0.2 and cli.model.hparams.temperature is None
    with pytest.raises(ValueError, match="former name of alignment_temperature; set only"):
        MaskTask(tokenizer=str(tokenizer_dir["t2m"]), text_dim=384, temperature=0.2,
                 alignment_temperature=0.3)


def test_max_segments_is_stated_by_the_data_and_reaches_the_model(text_dataset, tokenizer_dir,
                                                                 tmp_path):
    """data.init_args.max_segments is linked to the transformer's. Configs written before
    state it for the model too: they run when both agree; a model value that differs is
    one error naming its place."""
    import re

    from segmo.errors import SegmoError

    config = REPO / "configs/residual/synthetic.yaml"
    args = [*overrides(config, text_dataset, tokenizer_dir, tmp_path / "runs"),
            "--trainer.fast_dev_run=true"]
    cli = cli_main(["fit", "--config", str(config), *args, "--data.init_args.max_segments=4"])
    assert cli.model.model.config.max_segments == 4 == cli.datamodule.max_segments
    assert cli.datamodule.dataset("train")[0]["segment_mask"].shape == (4,)
    assert cli.model.export_model().meta["tokenizer_digest"] == tokenizer_digest(
        load_pretrained(tokenizer_dir["t2m"]))  # what `segmo bundle` compares
    old = tmp_path / "old.yaml"
    old.write_text(config.read_text().replace("    max_tokens: 49\n",
                                              "    max_segments: 5\n    max_tokens: 49\n", 1))
    cli = cli_main(["fit", "--config", str(old), *args])
    assert cli.trainer.state.finished and cli.model.model.config.max_segments == 5
    expected = (f"{old}:" + r"\d+: model.init_args.max_segments=5, but the model takes max_segments "
                r"from data.init_args.max_segments \(4\)")
    with pytest.raises(SegmoError, match=expected):
        cli_main(["fit", "--config", str(old), *args, "--data.init_args.max_segments=4"])
    with pytest.raises(SegmoError, match=re.escape("argument --model.init_args.max_segments=3")):
        cli_main(["fit", "--config", str(config), *args, "--model.init_args.max_segments=3"])


def test_a_misspelt_argument_of_the_shared_transformer_task_gets_a_suggestion(
        text_dataset, tokenizer_dir, tmp_path):
    from segmo.errors import SegmoError

    config = REPO / "configs/mask/synthetic.yaml"
    with pytest.raises(SegmoError, match=r"MaskTask has no argument 'ff_dimm' \(did you mean "
                                         r"'ff_dim'\?\)"):
        cli_main(["fit", "--config", str(config),
                  *overrides(config, text_dataset, tokenizer_dir, tmp_path / "runs"),
                  "--model.init_args.ff_dimm=3", "--trainer.fast_dev_run=true"])


def test_text_dim_mismatch_is_an_error(text_dataset, tokenizer_dir, tmp_path):
    config = REPO / "configs/mask/synthetic.yaml"
    with pytest.raises(ValueError, match="text_dim=512"):
        cli_main(["fit", "--config", str(config),
                  *overrides(config, text_dataset, tokenizer_dir, tmp_path / "runs"),
                  "--model.init_args.text_dim=512", "--trainer.fast_dev_run=true"])


def test_export_reproduces_the_task(text_dataset, tokenizer_dir, tmp_path):
    from segmo.export import export

    config = REPO / "configs/mask/synthetic.yaml"
    cli = cli_main(["fit", "--config", str(config),
                    *overrides(config, text_dataset, tokenizer_dir, tmp_path / "runs"),
                    "--trainer.max_steps=2", "--trainer.check_val_every_n_epoch=1"])
    checkpoint = Path(cli.trainer.checkpoint_callback.last_model_path)
    model = load_pretrained(export(checkpoint, tmp_path / "mask"))
    assert model.alignment is not None and model.meta["text_encoder"] == "minilm"
    # no absolute path of this machine in a model that may be published
    for key in ("checkpoint", "tokenizer"):
        assert not Path(model.meta[key]).is_absolute() and model.meta[key].endswith(
            ("last.ckpt", "rvq", checkpoint.name, Path(str(tokenizer_dir["t2m"])).name)), model.meta[key]
    assert model.meta["data"]["root"] and model.meta["global_step"] == 2
    # the digest `segmo bundle` compares: that of the exported tokenizer it was trained with
    assert model.meta["tokenizer_digest"] == tokenizer_digest(load_pretrained(tokenizer_dir["t2m"]))
    task = MaskTask.load_from_checkpoint(checkpoint).eval()
    g = torch.Generator().manual_seed(0)
    b, n, a = 2, 6, 5
    args = (torch.randint(0, 16, (b, n), generator=g), torch.ones(b, n, dtype=torch.bool),
            torch.randn(b, 384, generator=g), torch.randn(b, a, 384, generator=g),
            torch.tensor([[True, True, False, False, False]] * b))
    with torch.no_grad():
        assert torch.equal(model(*args).logits, task.model(*args).logits)


def test_export_works_from_any_folder(text_dataset, tokenizer_dir, tmp_path, monkeypatch, capsys):
    """A fit given the tokenizer relative to its folder records it absolute, so the export
    runs anywhere; a checkpoint naming it relative (as before) is one line there, and
    --tokenizer names it."""
    from segmo.export import main as export_main

    config = REPO / "configs/mask/synthetic.yaml"
    (tmp_path / "train").mkdir()
    shutil.copytree(tokenizer_dir["t2m"], tmp_path / "train" / "rvq")
    monkeypatch.chdir(tmp_path / "train")
    cli = cli_main(["fit", "--config", str(config),
                    *overrides(config, text_dataset, {"t2m": "rvq"}, tmp_path / "runs"),
                    "--trainer.fast_dev_run=true"])
    cli.trainer.save_checkpoint(tmp_path / "final.ckpt")
    checkpoint = torch.load(tmp_path / "final.ckpt", weights_only=False)
    assert checkpoint["hyper_parameters"]["tokenizer"] == str((tmp_path / "train/rvq").resolve())
    monkeypatch.chdir(tmp_path)
    export_main([str(tmp_path / "final.ckpt"), "--out", str(tmp_path / "mask")])
    assert load_pretrained(tmp_path / "mask").meta["tokenizer"].endswith("rvq")

    checkpoint["hyper_parameters"]["tokenizer"] = "rvq"  # as fits recorded it before
    torch.save(checkpoint, tmp_path / "old.ckpt")
    line = cli_failure(["export", str(tmp_path / "old.ckpt"), "--out", str(tmp_path / "m2")], capsys)
    assert line.startswith("segmo export: ") and "rvq (relative to the folder `segmo fit` ran in" in line
    assert "pass --tokenizer DIR" in line and not (tmp_path / "m2").exists()
    line = cli_failure(["export", str(tmp_path / "old.ckpt"), "--out", str(tmp_path / "m2"),
                        "--tokenizer", str(tmp_path / "train")], capsys)
    assert "--tokenizer" in line and "not an exported tokenizer directory" in line
    export_main([str(tmp_path / "old.ckpt"), "--out", str(tmp_path / "m2"), "--tokenizer",
                 str(tmp_path / "train/rvq")])
    assert load_pretrained(tmp_path / "m2").kind == "mask"


def test_export_replaces_only_its_own_model_directory(text_dataset, tokenizer_dir, tmp_path, capsys):
    """Exporting again into the same folder works; a folder holding anything else (the
    user's config.json, a file beside a model) is refused without --overwrite, untouched."""
    from segmo.export import main as export_main

    config = REPO / "configs/length/synthetic.yaml"
    cli = cli_main(["fit", "--config", str(config),
                    *overrides(config, text_dataset, tokenizer_dir, tmp_path / "runs"),
                    "--trainer.fast_dev_run=true"])
    ckpt = str(tmp_path / "final.ckpt")
    cli.trainer.save_checkpoint(ckpt)
    out = tmp_path / "out"
    export_main([ckpt, "--out", str(out)])
    export_main([ckpt, "--out", str(out)])
    (out / "notes.txt").write_text("mine\n")
    line = cli_failure(["export", ckpt, "--out", str(out)], capsys)
    assert "holds another model and notes.txt, which the export would delete" in line
    assert "--overwrite" in line and (out / "notes.txt").read_text() == "mine\n"
    export_main([ckpt, "--out", str(out), "--overwrite"])
    assert sorted(p.name for p in out.iterdir()) == ["config.json", "model.safetensors"]
    user = tmp_path / "user"
    user.mkdir()
    (user / "config.json").write_text('{"mine": 1}\n')
    line = cli_failure(["export", ckpt, "--out", str(user)], capsys)
    assert "is not empty and holds no segmo model" in line and "--overwrite" in line
    assert (user / "config.json").read_text() == '{"mine": 1}\n'
    # A model of another kind (--out models/rvq for the length model: a slip copying a
    # README line) was replaced without a word, and the tokenizer was gone.
    rvq = tmp_path / "rvq"
    shutil.copytree(tokenizer_dir["t2m"], rvq)
    line = cli_failure(["export", ckpt, "--out", str(rvq)], capsys)
    assert f"{rvq} holds a 'rvq' model; exporting a 'length' model" in line and "--overwrite" in line
    assert load_pretrained(rvq).kind == "rvq"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["final.ckpt", "out", "runs", "rvq",
                                                           "user"]


def test_gt_token_spans_and_segment_top1():
    spans = [[(0, 40), (40, 100)], None, [(0, 20), (20, 60), (60, 64)]]
    tokens, usable = gt_token_spans(spans, torch.tensor([2, 2, 2]), torch.tensor([100, 64, 64]), 5)
    assert usable.tolist() == [True, False, False]  # no ground truth; count mismatch
    assert tokens[0, :2].tolist() == [[0, 10], [10, 25]]
    text = torch.eye(3)[None].repeat(2, 1, 1)
    motion = torch.stack([torch.eye(3), torch.eye(3)[[1, 0, 2]]])
    mask = torch.ones(2, 3, dtype=torch.bool)
    assert segment_top1(text, motion, mask) == (4, 6)


def test_reversed_order_is_an_involution_on_valid_slots():
    mask = torch.tensor([[True, True, True, False, False], [True, False, False, False, False]])
    order = reversed_order(mask)
    assert order.tolist() == [[2, 1, 0, 3, 4], [0, 1, 2, 3, 4]]
    assert torch.equal(order.gather(1, order), torch.arange(5).expand(2, 5))


def test_segment_probe_tool_scores_any_mask_transformer(tmp_path, capsys):
    """tools/segment_probe.py fits a head on a frozen model (with or without alignment) and
    scores every ground-truth segment of the split whose caption the rule backend split
    into as many segments."""
    import json

    from conftest import build_tokenizer, hash_encoder, load_tool

    from segmo.models.alignment import AlignmentConfig
    from segmo.models.mask_transformer import MaskTransformer, MaskTransformerConfig
    from segmo.synth.corpus import build_corpus
    from segmo.text.cache import update_cache
    from segmo.text.extract import segment_folder
    from segmo.text.rules import RuleSegmenter

    # seed 1: in corpus version 2 the two val motions of seed 0 have one segment each
    root = build_corpus(tmp_path / "synth", 40, seed=1, progress=False)
    segment_folder(root, RuleSegmenter(), "rule", progress=False)
    update_cache(root, hash_encoder("minilm", 16), segments=["rule"], progress=False)
    tokenizer = build_tokenizer(tmp_path / "rvq", 263)
    tool = load_tool("segment_probe")

    expected = 0  # segments with a ground-truth span, counted from the files themselves
    for mid in (root / "val.txt").read_text().split():
        truth = json.loads((root / "segments" / f"{mid}.json").read_text())["captions"]
        rule = (root / "text_segments" / "rule" / f"{mid}.txt").read_text().splitlines()
        for caption, line in zip(truth, rule):
            a = len(line.split("#"))
            expected += a if len(caption["segments"]) == a >= 2 else 0
    assert expected > 0
    tiny = dict(codebook_size=16, text_dim=16, max_segments=5, max_tokens=49, dim=32, depth=1,
                heads=2, ff_dim=64)
    for alignment in (AlignmentConfig(out_dim=16), None):
        torch.manual_seed(0)
        path = tmp_path / f"mask-{alignment is None}"
        MaskTransformer(MaskTransformerConfig(**tiny, alignment=alignment)).save_pretrained(
            path, meta={"text_encoder": "minilm"})
        for mode in ([], ["--unordered"]):
            tool.main(["--mask", str(path), "--tokenizer", str(tokenizer), "--data", str(root),
                       "--steps", "3", "--batch-size", "8", *mode])
            result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
            assert result["segments"] == expected and result["unordered"] == bool(mode)
            assert 0.0 <= result["probe"] <= 1.0
            assert ("own_head" in result) == (alignment is not None)


def test_segment_probe_refuses_bad_arguments_in_one_line(tmp_path, capsys):
    from conftest import tool_failure

    def line(*argv: str) -> str:
        return tool_failure("segment_probe", ["--tokenizer", str(tmp_path / "rvq"), *argv], capsys)

    assert line("--mask", str(tmp_path / "nothing"), "--data", str(tmp_path)) == (
        f"segment_probe.py: {tmp_path / 'nothing'}: no such model folder (nor a hub id like 'owner/name')")
    assert line("--mask", "m", "--data", str(tmp_path / "nowhere")).startswith(
        f"segment_probe.py: --data {tmp_path / 'nowhere'}: no such folder")
    for flag in ("--steps", "--batch-size"):  # 0 steps would report an untrained probe
        assert f"argument {flag}: expected a whole number >= 1, got '0'" in line(
            "--mask", "m", "--data", str(tmp_path), flag, "0")


@pytest.mark.parametrize("source", ["truth", "segmenter"])
def test_segment_timing_trains_its_head_and_reaches_the_model(source, text_dataset,
                                                              tokenizer_dir, tmp_path):
    """Timing from the corpus' ground-truth spans or from the motion segmenter: the head
    learns (a loss above 0 needs segments with a span of less than the whole motion) and
    the exported model carries it; the truth case also trains `position_text`."""
    from conftest import hash_encoder

    from segmo.synth.corpus import build_corpus
    from segmo.text.cache import update_cache
    from segmo.text.extract import segment_folder
    from segmo.text.rules import RuleSegmenter

    config = REPO / "configs/mask/synthetic.yaml"
    args = overrides(config, text_dataset, tokenizer_dir, tmp_path / "runs")
    if source == "truth":  # the built-in corpus has ground-truth spans
        root = build_corpus(tmp_path / "synth", 24, seed=1, progress=False)
        segment_folder(root, RuleSegmenter(), "rule", progress=False)
        update_cache(root, hash_encoder("minilm", 384), segments=["rule"], progress=False)
        args = [a for a in args if not a.startswith("--data.root")] + [f"--data.root={root}"]
    cli = cli_main(["fit", "--config", str(config), *args,
                    f"--model.init_args.segment_timing={source}", "--model.init_args.segmenter=cpd",
                    f"--model.init_args.position_text={source == 'truth'}",
                    "--data.init_args.batch_size=16", "--trainer.fast_dev_run=true"])
    metrics = cli.trainer.callback_metrics
    assert torch.isfinite(metrics["train/timing_loss"]) and float(metrics["train/timing_loss"]) > 0
    assert 0.0 <= float(metrics["val/timing_iou"]) <= 1.0
    model = cli.model.export_model()
    assert model.config.segment_timing and model.meta["segment_timing"] == source
    assert model.config.position_text == (source == "truth")


@pytest.mark.parametrize("source", ["truth", "segmenter"])
def test_alignment_spans_come_from_the_ground_truth_or_the_segmenter(source, text_dataset,
                                                                     tokenizer_dir, tmp_path):
    """`alignment_spans: truth` hands the loss the corpus' ground-truth spans where a sample
    has usable ones and the segmenter's elsewhere; `segmenter` (the default) the segmenter's."""
    from conftest import hash_encoder

    from segmo.synth.corpus import build_corpus
    from segmo.text.cache import update_cache
    from segmo.text.extract import segment_folder
    from segmo.text.rules import RuleSegmenter

    root = build_corpus(tmp_path / "synth", 24, seed=1, progress=False)
    segment_folder(root, RuleSegmenter(), "rule", progress=False)
    update_cache(root, hash_encoder("minilm", 384), segments=["rule"], progress=False)
    config = REPO / "configs/mask/synthetic.yaml"
    args = [a for a in overrides(config, text_dataset, tokenizer_dir, tmp_path / "runs")
            if not a.startswith("--data.root")] + [f"--data.root={root}"]
    cli = cli_main(["fit", "--config", str(config), *args,
                    f"--model.init_args.alignment_spans={source}", "--model.init_args.segmenter=cpd",
                    "--data.init_args.batch_size=16", "--trainer.fast_dev_run=true"])
    assert torch.isfinite(cli.trainer.callback_metrics["train/align"])
    task, batch = cli.model, next(iter(cli.datamodule.train_dataloader()))
    handed_spans = _alignment_arguments(task, batch)[5]
    _, segments, segment_mask = text_condition(batch)
    lengths = token_lengths(batch["lengths"])
    num_segments = torch.minimum(segment_mask.sum(1), lengths)
    cut = task.spans(batch, num_segments, lengths)
    truth, usable = gt_token_spans(batch["spans"], segment_mask.sum(1), batch["lengths"],
                                   segment_mask.shape[1])
    assert usable.any() and not torch.equal(truth[usable], cut[usable])  # the two sources differ
    expected = torch.where(usable[:, None, None], truth, cut) if source == "truth" else cut
    assert torch.equal(handed_spans.cpu(), expected)


def test_segment_balanced_weights_give_every_segment_the_same_total():
    """A 2-token segment beside an 8-token one: each holds half of the sample's weight; a
    sample with one known span, a token outside every span and padding are as documented."""
    spans = torch.tensor([[[0, 2], [2, 10], [0, 0]],
                          [[0, 4], [4, 8], [0, 0]],
                          [[0, 3], [4, 10], [0, 0]]])
    known = torch.tensor([[True, True, False], [True, False, False], [True, True, False]])
    valid = torch.arange(12)[None] < torch.tensor([10, 8, 11])[:, None]
    w = segment_balanced_weights(spans, known, valid)
    assert torch.allclose(w[0, :2], torch.full((2,), 2.5)) and torch.allclose(w[0, 2:10], torch.full((8,), 0.625))
    assert w[0, :2].sum() == w[0, 2:10].sum() == 5.0 and w[0, 10:].eq(0).all()
    assert torch.equal(w[1], valid[1].float())  # one known span: unweighted
    assert w[2, 3] == 1.0 and w[2, 10] == 1.0 and w[2, 11] == 0.0  # outside every span; padding
    assert torch.allclose(w[2, :3].sum(), w[2, 4:10].sum())


def test_weighted_masked_token_loss():
    g = torch.Generator().manual_seed(0)
    logits, targets = torch.randn(2, 5, 7, generator=g), torch.randint(0, 7, (2, 5), generator=g)
    target = torch.rand(2, 5, generator=g) < 0.6
    target[0, 1] = True
    plain = masked_token_loss(logits, targets, target)
    assert torch.allclose(masked_token_loss(logits, targets, target, torch.full((2, 5), 3.0)), plain)
    only = torch.zeros(2, 5)
    only[0, 1] = 1.0
    ce = torch.nn.functional.cross_entropy(logits[0, 1][None], targets[0, 1][None])
    assert torch.allclose(masked_token_loss(logits, targets, target, only), ce)


def test_the_segment_options_train_and_a_wrong_value_is_named(text_dataset, tokenizer_dir,
                                                              tmp_path):
    from segmo.errors import SegmoError

    config = REPO / "configs/mask/synthetic.yaml"
    cli = cli_main(["fit", "--config", str(config),
                    *overrides(config, text_dataset, tokenizer_dir, tmp_path / "runs"),
                    "--model.init_args.loss_weighting=segment",
                    "--model.init_args.segment_mask_prob=0.5", "--trainer.fast_dev_run=true"])
    assert cli.model.hparams.segment_mask_prob == 0.5
    metrics = cli.trainer.callback_metrics
    # training follows the balanced loss; the plain masked-token loss is still logged
    assert torch.isfinite(metrics["train/mask_loss_balanced"]) and "train/mask_loss" in metrics
    assert torch.isclose(metrics["train/loss"] - metrics["train/align"],
                         metrics["train/mask_loss_balanced"], atol=1e-4)
    with pytest.raises(SegmoError, match="model.init_args.loss_weighting='segments': one of "
                                         "token, segment"):
        MaskTask(tokenizer=str(tokenizer_dir["t2m"]), text_dim=384, loss_weighting="segments")
    with pytest.raises(SegmoError, match=r"model.init_args.segment_mask_prob=1.5: a share in \[0, 1\]"):
        MaskTask(tokenizer=str(tokenizer_dir["t2m"]), text_dim=384, segment_mask_prob=1.5)
    with pytest.raises(SegmoError, match="model.init_args.alignment_spans='gt': one of "
                                         "segmenter, truth"):
        MaskTask(tokenizer=str(tokenizer_dir["t2m"]), text_dim=384, alignment_spans="gt")
    with pytest.raises(SegmoError, match="model.init_args.position_text=true needs "
                                         "segment_timing truth or segmenter"):
        MaskTask(tokenizer=str(tokenizer_dir["t2m"]), text_dim=384, position_text=True)


def test_mask_whole_segment_masks_one_known_segment_of_the_chosen_samples():
    mask_id = 16
    inputs = torch.tensor([[1, 2, 3, 4, 5, 6], [1, 2, 3, 4, 17, 17], [1, 2, 3, 4, 5, 6]])
    valid = inputs != 17
    target = torch.zeros(3, 6, dtype=torch.bool)
    target[0, 5] = True
    spans = torch.tensor([[[0, 2], [2, 5], [5, 6]], [[0, 1], [1, 6], [0, 0]], [[0, 3], [3, 6], [0, 0]]])
    known = torch.tensor([[True, True, False], [False, True, False], [True, True, False]])
    chosen = torch.tensor([True, True, False])
    for seed in range(8):
        g = torch.Generator().manual_seed(seed)
        new, new_target = mask_whole_segment(inputs, target, valid, spans, known, chosen, mask_id, g)
        masked = new == mask_id
        # sample 0: exactly one of its two known segments, whole; the slot-2 span stays
        assert masked[0].tolist() in ([True, True] + [False] * 4, [False, False, True, True, True, False])
        assert new_target[0, 5] and torch.equal(new_target[0], masked[0] | target[0])
        # sample 1: its one known span, but never its padded positions
        assert masked[1].tolist() == [False, True, True, True, False, False]
        assert torch.equal(new[1, 4:], inputs[1, 4:])
        assert torch.equal(new[2], inputs[2]) and not new_target[2].any()  # not chosen


def test_segment_dropout_hides_present_segments_in_training_only(text_dataset, tokenizer_dir,
                                                                 tmp_path):
    from segmo.errors import SegmoError

    config = REPO / "configs/mask/synthetic.yaml"
    cli = cli_main(["fit", "--config", str(config),
                    *overrides(config, text_dataset, tokenizer_dir, tmp_path / "runs"),
                    "--model.init_args.segment_drop_prob=0.5", "--trainer.fast_dev_run=true"])
    task, batch = cli.model, next(iter(cli.datamodule.train_dataloader()))
    assert torch.isfinite(cli.trainer.callback_metrics["train/loss"])
    assert task.export_model().meta["segment_drop_prob"] == 0.5
    seen = []
    forward = task.model.forward
    task.model.forward = lambda *a, **k: seen.append(k.get("hidden_segments")) or forward(*a, **k)
    task.log = task.log_dict = lambda *a, **k: None  # outside a fit loop
    _, _, segment_mask = text_condition(batch)
    torch.manual_seed(0)
    with torch.no_grad():
        task.step(batch)
        task._evaluate("val", batch, 0)
    hidden, validation = seen[0], seen[1]
    assert bool(hidden.any()) and not bool((hidden & ~segment_mask).any())  # present ones only
    assert 0.25 < hidden.sum() / segment_mask.sum() < 0.75
    assert not bool(validation.any())  # validation sees every segment
    with pytest.raises(SegmoError, match=r"model.init_args.segment_drop_prob=-0.1: a share in \[0, 1\]"):
        MaskTask(tokenizer=str(tokenizer_dir["t2m"]), text_dim=384, segment_drop_prob=-0.1)


@pytest.mark.parametrize("stage,option,value,message", [
    ("mask", "cond_drop_prob", 1.5, "a share in [0, 1]"),
    ("mask", "order_drop_prob", 2.0, "a share in [0, 1]"),
    ("mask", "local_uncond_prob", -1.0, "a share in [0, 1]"),
    ("mask", "alignment_weight", -1.0, "a weight >= 0"),
    ("mask", "timing_weight", -0.5, "a weight >= 0"),
    ("mask", "alignment_temperature", 0.0, "a temperature > 0"),
    ("mask", "alignment_temperature", float("nan"), "a temperature > 0"),
    ("mask", "alignment_dim", 0, "a width >= 1"),
    ("residual", "cond_drop_prob", 1.5, "a share in [0, 1]"),
    ("residual", "local_uncond_prob", -1.0, "a share in [0, 1]"),
])
def test_out_of_range_training_options_are_refused(stage, option, value, message, tokenizer_dir):
    """They trained without a word (shares, weights) or stopped with an 80-line ValueError
    traceback (temperature 0, dim 0)."""
    import re

    from segmo.errors import SegmoError
    from segmo.tasks.residual import ResidualTask

    task = MaskTask if stage == "mask" else ResidualTask
    with pytest.raises(SegmoError, match=re.escape(f"model.init_args.{option}={value}: {message}")):
        task(tokenizer=str(tokenizer_dir["t2m"]), text_dim=384, **{option: value})


@pytest.mark.parametrize("option", ["alignment_temperature=0", "alignment_dim=0"])
def test_fit_with_a_zero_alignment_temperature_or_width_is_one_line(option, text_dataset, tokenizer_dir,
                                                                    tmp_path, capsys):
    config = REPO / "configs/mask/synthetic.yaml"
    line = cli_failure(["fit", "--config", str(config),
                        *overrides(config, text_dataset, tokenizer_dir, tmp_path / "runs"),
                        f"--model.init_args.{option}", "--trainer.fast_dev_run=true"], capsys)
    assert f"model.init_args.{option}" in line
