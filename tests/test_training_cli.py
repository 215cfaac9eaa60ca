"""`segmo fit/validate/test` over every config in configs/rvq/, resuming, and export.

The runs use a tiny HumanML3D-layout folder of random features and shrunken models; what
is checked is the plumbing (CLI, run directory, checkpoints, buffers, export), not quality.
"""

from __future__ import annotations

import json
from pathlib import Path

import lightning as L
import numpy as np
import pytest
import torch
import yaml
from conftest import load_tool

from segmo.data import MotionDataModule
from segmo.errors import SegmoError
from segmo.export import main as export_main
from segmo.models.pretrained import load_pretrained
from segmo.models.tokenizer import RVQVAE, RVQOutput
from segmo.motion.skeleton import get_skeleton
from segmo.tasks.base import adamw_with_schedule, step_schedule
from segmo.tasks.tokenizer import RVQTask
from segmo.training.cli import main as cli_main

REPO = Path(__file__).resolve().parents[1]
CONFIGS = sorted((REPO / "configs" / "rvq").glob("*.yaml"))
TINY_MODEL = dict(width=16, code_dim=8, codebook_size=8, num_quantizers=3)


def tiny_overrides(root: Path, runs: Path) -> list[str]:
    model = [f"--model.init_args.{k}={v}" for k, v in TINY_MODEL.items()]
    data = ["--data.init_args.batch_size=4", "--data.init_args.num_workers=0"]
    return [f"--data.root={root}", f"--runs_dir={runs}", *model, *data,
            "--trainer.accelerator=cpu", "--trainer.devices=1", "--trainer.enable_progress_bar=false"]


def make_dataset(root: Path, skeleton: str = "t2m", motions: int = 12, seed: int = 0) -> Path:
    """A HumanML3D-layout folder with random features: 8 train, 2 val, 2 test motions."""
    spec = get_skeleton(skeleton)
    rng = np.random.default_rng(seed)
    (root / "new_joint_vecs").mkdir(parents=True)
    ids = [f"{i:06d}" for i in range(motions)]
    for mid in ids:
        frames = int(rng.integers(64, 100))
        features = (0.1 * rng.standard_normal((frames, spec.feature_dim))).astype(np.float32)
        np.save(root / "new_joint_vecs" / f"{mid}.npy", features)
    np.save(root / "Mean.npy", np.zeros(spec.feature_dim, dtype=np.float32))
    np.save(root / "Std.npy", np.full(spec.feature_dim, 0.1, dtype=np.float32))
    splits = {"train": ids[:-4], "val": ids[-4:-2], "test": ids[-2:]}
    for split, split_ids in splits.items():
        (root / f"{split}.txt").write_text("\n".join(split_ids) + "\n")
    return root


@pytest.mark.parametrize("config", CONFIGS, ids=[c.stem for c in CONFIGS])
def test_fit_every_config(config, tmp_path):
    skeleton = yaml.safe_load(config.read_text())["data"]["init_args"]["skeleton"]
    root = make_dataset(tmp_path / "data", skeleton)
    cli = cli_main(["fit", "--config", str(config), *tiny_overrides(root, tmp_path / "runs"),
                    "--trainer.fast_dev_run=true"])
    assert cli.trainer.state.finished and cli.trainer.global_step == 1
    assert isinstance(cli.model, RVQTask) and cli.model.skeleton.name == skeleton
    assert cli.model.model.quantizer.initialised.any()
    assert torch.equal(cli.model.model.std, cli.datamodule.std)  # statistics reach the model
    assert "val/mpjpe_mm" in cli.trainer.callback_metrics


@pytest.mark.parametrize("kind, expected", [("bf16", "bf16-mixed"), ("fp32", "32-true")])
def test_precision_auto_trains_in_what_the_cpu_computes_natively(kind, expected, tmp_path, monkeypatch):
    from segmo import cpu

    monkeypatch.setattr(cpu, "auto_precision", lambda: (kind, "as this test says"))
    root = make_dataset(tmp_path / "data")
    cli = cli_main(["fit", "--config", str(CONFIGS[-1]), *tiny_overrides(root, tmp_path / "runs"),
                    "--trainer.fast_dev_run=true", "--trainer.precision=auto"])
    assert cli.trainer.state.finished and cli.trainer.precision == expected
    line = cli_failure_line(["fit", "--config", str(CONFIGS[-1]), *tiny_overrides(root, tmp_path / "r2"),
                             "--trainer.precision=fast"])
    assert "trainer.precision" in line and "fast" in line


def cli_failure_line(argv: list[str]) -> str:
    with pytest.raises(SegmoError) as caught:
        cli_main(argv)
    return str(caught.value).splitlines()[0]


def test_the_former_class_path_still_trains_and_exports(tmp_path):
    """YAMLs and checkpoints written before the tokenizer task moved name segmo.tasks.rvq."""
    from segmo.export import export
    from segmo.models.pretrained import load_pretrained

    root = make_dataset(tmp_path / "data")
    config = tmp_path / "old.yaml"
    text = (REPO / "configs/rvq/synthetic.yaml").read_text()
    config.write_text(text.replace("segmo.tasks.tokenizer.RVQTask", "segmo.tasks.rvq.RVQTask"))
    cli = cli_main(["fit", "--config", str(config), *tiny_overrides(root, tmp_path / "runs"),
                    "--trainer.max_steps=1", "--trainer.val_check_interval=1"])
    assert isinstance(cli.model, RVQTask) and cli.trainer.global_step == 1
    last = next((tmp_path / "runs" / "rvq" / "old").glob("version_*/checkpoints/last.ckpt"))
    assert torch.load(last, weights_only=False)["hyper_parameters"]["_class_path"] == \
        "segmo.tasks.rvq.RVQTask"
    assert isinstance(load_pretrained(export(last, tmp_path / "tokenizer")), RVQVAE)


def test_root_weight_adds_the_root_features_error_to_the_loss():
    task = RVQTask(**TINY_MODEL, root_weight=2.0)
    d = task.skeleton.feature_dim
    motion = torch.zeros(2, 8, d)
    wrong = motion.clone()
    wrong[..., 1] = 2.0  # only the root's forward velocity is wrong: SmoothL1 of 2 is 1.5
    nothing = torch.zeros(())
    out = RVQOutput(reconstruction=wrong, indices=torch.zeros(2, 2, 3, dtype=torch.long),
                    commitment_loss=nothing, perplexity=torch.zeros(3), code_usage=torch.zeros(3))
    terms = task.losses(motion, out, torch.ones(2, 8, dtype=torch.bool))
    assert float(terms["root"]) == pytest.approx(1.5 / 4)  # the mean over the root's 4 features
    assert float(terms["recon"]) == pytest.approx(1.5 / d) and float(terms["positions"]) == 0.0
    assert float(terms["loss"]) == pytest.approx(1.5 / d + 2.0 * 1.5 / 4)
    assert RVQTask(**TINY_MODEL).hparams.root_weight == 0.0  # the reference's loss by default


def test_a_tokenizer_seed_is_set_once_by_the_data(tmp_path):
    root = make_dataset(tmp_path / "data")
    config = str(REPO / "configs/rvq/synthetic.yaml")
    cli = cli_main(["fit", "--config", config, *tiny_overrides(root, tmp_path / "runs"),
                    "--data.init_args.seed=3", "--trainer.fast_dev_run=true"])
    assert cli.trainer.state.finished and cli.model.hparams.seed == 3 and cli.datamodule.seed == 3
    line = cli_failure_line(["fit", "--config", config, *tiny_overrides(root, tmp_path / "r2"),
                             "--model.init_args.seed=1", "--trainer.fast_dev_run=true"])
    assert "model.init_args.seed" in line and "data.init_args.seed" in line


def test_skeleton_mismatch_is_an_error(tmp_path):
    root = make_dataset(tmp_path / "data", "t2m")
    with pytest.raises(ValueError, match="skeleton"):
        cli_main(["fit", "--config", str(REPO / "configs/rvq/synthetic.yaml"),
                  *tiny_overrides(root, tmp_path / "runs"), "--model.init_args.skeleton=kit",
                  "--trainer.fast_dev_run=true"])


class _CaptureAtStart(L.Callback):
    def on_train_start(self, trainer, pl_module):
        self.state = {k: v.clone() for k, v in pl_module.model.quantizer.state_dict().items()}


def _load_eval_tokenizer():
    return load_tool("eval_tokenizer")


@pytest.fixture
def worsening_metric(monkeypatch):
    """The tokenizer's monitored metric (val/mpjpe_mm) is the global step: it gets worse at
    every validation, and the best checkpoint is the first."""
    measured = RVQTask.mpjpe_mm

    def worsening(self, motion, reconstruction, mask):
        return {**measured(self, motion, reconstruction, mask),
                "mpjpe_mm": torch.tensor(float(self.global_step))}

    monkeypatch.setattr(RVQTask, "mpjpe_mm", worsening)


def test_last_ckpt_holds_the_newest_state_when_the_metric_gets_worse(tmp_path, worsening_metric):
    """Lightning 2.6 rewrote last.ckpt only when the monitored metric improved: after a
    worse validation it kept the best step's weights, which `segmo export last.ckpt`
    shipped and ``--ckpt_path last`` resumed from."""
    from fit_helpers import LastCheckpointSteps

    root = make_dataset(tmp_path / "data")
    cli = cli_main(["fit", "--config", str(REPO / "configs/rvq/synthetic.yaml"),
                    *tiny_overrides(root, tmp_path / "runs"), "--trainer.max_steps=5",
                    "--trainer.val_check_interval=2", "--trainer.callbacks+=fit_helpers.LastCheckpointSteps"])
    checkpoints = tmp_path / "runs" / "rvq" / "synthetic" / "version_0" / "checkpoints"
    assert sorted(p.name for p in checkpoints.iterdir()) == ["best-000-2.ckpt", "last.ckpt"]
    seen = next(c for c in cli.trainer.callbacks if isinstance(c, LastCheckpointSteps)).steps
    assert seen[3] == 2 and seen[4] == 4  # written at each validation (steps 2 and 4)
    assert torch.load(checkpoints / "last.ckpt", weights_only=False)["global_step"] == 5  # and at the end


def test_resuming_from_an_older_checkpoint_keeps_the_run_it_came_from(tmp_path, worsening_metric):
    """`--ckpt_path best` continued in the best checkpoint's version folder: last.ckpt went
    back to the best step, metrics.csv lost its later rows and TensorBoard its events."""
    root = make_dataset(tmp_path / "data")
    common = ["--config", str(REPO / "configs/rvq/synthetic.yaml"), *tiny_overrides(root, tmp_path / "runs"),
              "--trainer.val_check_interval=2"]
    cli_main(["fit", *common, "--trainer.max_steps=4"])
    runs = tmp_path / "runs" / "rvq" / "synthetic"
    before = {p: p.read_bytes() for p in (runs / "version_0").rglob("*") if p.is_file()}
    cli_main(["fit", *common, "--trainer.max_steps=3", "--ckpt_path=best"])  # best: step 2
    assert {p: p.read_bytes() for p in (runs / "version_0").rglob("*") if p.is_file()} == before
    last = runs / "version_1" / "checkpoints" / "last.ckpt"
    assert torch.load(last, weights_only=False)["global_step"] == 3
    assert (runs / "version_1" / "config.yaml").is_file()
    cli_main(["fit", *common, "--trainer.max_steps=5", f"--ckpt_path={last}"])  # the newest: in place
    assert torch.load(last, weights_only=False)["global_step"] == 5
    assert sorted(p.name for p in runs.iterdir()) == ["version_0", "version_1"]


def test_a_resumed_fit_refuses_other_data_settings_and_keeps_its_config(tmp_path):
    """A resumed fit took another batch size, window or data seed silently (the saved loader
    position counts batches of the recorded order; the data seed is the tokenizer's too),
    and rewrote the run's config.yaml with the resumed command's settings."""
    root = make_dataset(tmp_path / "data")
    common = ["--config", str(REPO / "configs/rvq/synthetic.yaml"), *tiny_overrides(root, tmp_path / "runs"),
              "--trainer.val_check_interval=2"]
    cli_main(["fit", *common, "--trainer.max_steps=2"])
    run = tmp_path / "runs" / "rvq" / "synthetic" / "version_0"
    before = {p: p.read_bytes() for p in run.rglob("*") if p.is_file()}
    last = run / "checkpoints" / "last.ckpt"
    for given, recorded in (("--data.batch_size=8", 4), ("--data.init_args.window=32", 64),
                            ("--data.seed=5", 0)):
        line = cli_failure_line(["fit", *common, "--trainer.max_steps=4", "--ckpt_path=last", given])
        key, value = given[2:].replace("init_args.", "").split("=")
        assert line == (f"argument {given}: data.init_args.{key.split('.')[1]}={value}, but "
                        f"--ckpt_path {last} was trained with {recorded}; a resumed run continues "
                        "its checkpoint's data order and model, so leave it as it was, or start a new run")
        assert {p: p.read_bytes() for p in run.rglob("*") if p.is_file()} == before  # nothing written
    config = (run / "config.yaml").read_bytes()
    cli_main(["fit", *common, "--trainer.max_steps=3", "--ckpt_path=last",
              "--data.init_args.preload=false", "--data.init_args.num_workers=0"])  # how it is read
    assert torch.load(last, weights_only=False)["global_step"] == 3
    assert (run / "config.yaml").read_bytes() == config  # what the run started with
    resumed = yaml.safe_load((run / "config-resumed-at-2.yaml").read_text())
    assert resumed["trainer"]["max_steps"] == 3 and resumed["data"]["init_args"]["preload"] is False


def test_a_resumed_mask_fit_refuses_another_linked_max_segments(tmp_path):
    """It was a size-mismatch traceback from loading the weights, after the run's
    config.yaml had been rewritten."""
    ckpt = _checkpoint(tmp_path / "runs/mask/synthetic/version_0/checkpoints/last.ckpt",
                       "segmo.tasks.mask.MaskTask", datamodule_hyper_parameters={"max_segments": 5})
    line = cli_failure_line(["fit", "--config", str(REPO / "configs/mask/synthetic.yaml"),
                             f"--runs_dir={tmp_path / 'runs'}", "--ckpt_path=last", "--data.max_segments=6"])
    assert line.startswith("argument --data.max_segments=6: data.init_args.max_segments=6, but "
                           f"--ckpt_path {ckpt} was trained with 5;"), line
    assert [p for p in (tmp_path / "runs").rglob("*") if p.is_file()] == [ckpt]


@pytest.mark.slow
def test_resuming_a_run_under_a_relative_runs_dir_updates_last_ckpt(tmp_path, monkeypatch):
    """`--runs_dir runs` (relative, as the README's commands) and `--ckpt_path
    runs/.../last.ckpt`: the resumed run writes its final weights to last.ckpt, the file
    `segmo export` is given. (Lightning saw the checkpoint folder change from relative to
    absolute, wrote last-v1.ckpt, and last.ckpt kept the weights of the resume point.)"""
    root = make_dataset(tmp_path / "data")
    monkeypatch.chdir(tmp_path)
    common = ["--config", str(REPO / "configs/rvq/synthetic.yaml"), *tiny_overrides(root, Path("runs")),
              "--trainer.val_check_interval=2"]
    cli_main(["fit", *common, "--trainer.max_steps=2"])
    last = Path("runs/rvq/synthetic/version_0/checkpoints/last.ckpt")
    assert torch.load(last, weights_only=False)["global_step"] == 2
    cli_main(["fit", *common, "--trainer.max_steps=4", f"--ckpt_path={last}"])
    assert torch.load(last, weights_only=False)["global_step"] == 4
    assert sorted(p.name for p in last.parent.glob("last*")) == ["last.ckpt"]
    # `--ckpt_path last` is that run's last.ckpt (Lightning looked in a new, empty
    # version_1 and started from scratch with a warning).
    cli_main(["fit", *common, "--trainer.max_steps=6", "--ckpt_path=last"])
    assert torch.load(last, weights_only=False)["global_step"] == 6
    assert [p.name for p in Path("runs/rvq/synthetic").iterdir()] == ["version_0"]


@pytest.mark.slow
def test_run_directory_resume_export_and_eval(tmp_path, capsys):
    root = make_dataset(tmp_path / "data")
    runs = tmp_path / "runs"
    config = str(REPO / "configs/rvq/synthetic.yaml")
    common = ["--config", config, *tiny_overrides(root, runs)]
    cli_main(["fit", *common, "--trainer.max_steps=2", "--trainer.val_check_interval=2"])

    run = runs / "rvq" / "synthetic" / "version_0"
    assert (run / "config.yaml").is_file() and (run / "metrics.csv").is_file()
    assert any(p.name.startswith("events.out.tfevents") for p in run.iterdir())
    saved = yaml.safe_load((run / "config.yaml").read_text())
    assert saved["model"]["init_args"]["width"] == TINY_MODEL["width"]
    last = run / "checkpoints" / "last.ckpt"
    assert last.is_file() and any(p.name.startswith("best-") for p in last.parent.iterdir())

    # Resuming restores the codebooks and flags; nothing re-initialises them.
    checkpoint = torch.load(last, weights_only=False)
    assert checkpoint["hyper_parameters"]["_class_path"] == "segmo.tasks.tokenizer.RVQTask"
    assert checkpoint["global_step"] == 2  # the final weights, not those of an earlier check
    capture = _CaptureAtStart()
    trainer = L.Trainer(max_steps=4, callbacks=[capture], logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, limit_val_batches=0, accelerator="cpu")
    task = RVQTask(**TINY_MODEL)
    trainer.fit(task, datamodule=MotionDataModule(str(root), batch_size=4, window=64), ckpt_path=last)
    for name, value in capture.state.items():
        assert torch.equal(value, checkpoint["state_dict"][f"model.quantizer.{name}"]), name
    assert capture.state["initialised"].all() and trainer.global_step == 4
    moved = (task.model.quantizer.codebooks - capture.state["codebooks"]).abs().max()
    assert moved < capture.state["codebooks"].abs().max()  # two EMA steps, not a re-draw

    # validate/test from the checkpoint through the CLI.
    cli = cli_main(["validate", *common, f"--ckpt_path={last}"])
    assert "val/mpjpe_mm" in cli.trainer.callback_metrics
    cli = cli_main(["test", *common, f"--ckpt_path={last}"])
    assert float(cli.trainer.callback_metrics["test/mpjpe_mm"]) > 0

    # Export reproduces the tokenizer exactly.
    out = tmp_path / "rvq"
    export_main([str(last), "--out", str(out)])
    exported = load_pretrained(out)
    assert isinstance(exported, RVQVAE)
    assert exported.meta["skeleton"] == "t2m" and exported.meta["fps"] == 20.0
    reference = RVQTask.load_from_checkpoint(last, map_location="cpu").model.eval()
    x = torch.randn(2, 32, 263)
    indices = reference.encode(x)
    assert torch.equal(exported.encode(x), indices)
    assert torch.equal(exported.decode(indices), reference.decode(indices))
    assert torch.equal(exported.mean, torch.zeros(263)) and torch.allclose(exported.std, torch.full((263,), 0.1))

    # The evaluation tool reads the exported directory.
    capsys.readouterr()
    _load_eval_tokenizer().main(["--model", str(out), "--data", str(root), "--split", "test"])
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert len(result["mpjpe_mm"]) == len(result["code_usage"]) == TINY_MODEL["num_quantizers"]
    assert len(result["mpjpe_global_mm"]) == TINY_MODEL["num_quantizers"]
    assert all(v > 0 for v in result["mpjpe_mm"]) and result["clips"] == 2


def test_eval_tokenizer_reads_the_reconstructions_actions_on_the_built_in_corpus(tmp_path, tokenizer_dir, capsys):
    from segmo.models.action_classifier import ActionClassifier, ActionClassifierConfig
    from segmo.synth.actions import ACTIONS
    from segmo.synth.corpus import build_corpus

    corpus = build_corpus(tmp_path / "corpus", 6, seed=0, progress=False)
    (corpus / "test.txt").write_text("\n".join(sorted(p.stem for p in (corpus / "segments").glob("*.json"))))
    classifier = ActionClassifier(ActionClassifierConfig(num_classes=len(ACTIONS), width=8, depth=1))
    classifier.save_pretrained(tmp_path / "classifier", meta={"classes": list(ACTIONS)})
    tool = _load_eval_tokenizer()
    tool.main(["--model", str(tokenizer_dir["t2m"]), "--data", str(corpus),
               "--action-classifier", str(tmp_path / "classifier")])
    actions = json.loads(capsys.readouterr().out.strip().splitlines()[-1])["actions"]
    assert actions["clips"]["all"] == 6 and sum(v for k, v in actions["clips"].items() if k != "all") == 6
    assert all(0.0 <= v <= 1.0 for v in actions["sequence_accuracy"].values())
    assert set(actions["frame_accuracy"]) <= set(ACTIONS) and actions["frame_accuracy"]
    for confusion in actions["confusions"]:  # an untrained classifier confuses: shares of true frames
        assert confusion["true"] != confusion["read_as"] and 0 < confusion["share"] <= 1
    with pytest.raises(SegmoError, match="not an action classifier"):  # a tokenizer is not one
        tool.main(["--model", str(tokenizer_dir["t2m"]), "--data", str(corpus),
                   "--action-classifier", str(tokenizer_dir["t2m"])])
    plain = make_dataset(tmp_path / "plain")  # HumanML3D layout, no ground-truth actions
    with pytest.raises(SegmoError, match="no ground-truth actions"):  # before the evaluation
        tool.main(["--model", str(tokenizer_dir["t2m"]), "--data", str(plain),
                   "--action-classifier", str(tmp_path / "classifier")])


def test_export_without_task_class_is_an_error(tmp_path):
    path = tmp_path / "plain.ckpt"
    torch.save({"state_dict": {}, "hyper_parameters": {}}, path)
    with pytest.raises(SegmoError, match="does not name its task class"):
        export_main([str(path), "--out", str(tmp_path / "out")])


def test_mpjpe_aligns_the_root_and_global_counts_drift():
    task = RVQTask(**TINY_MODEL)
    motion = 0.1 * torch.randn(2, 8, 263, generator=torch.Generator().manual_seed(0))
    mask = torch.ones(2, 8, dtype=torch.bool)
    same = task.mpjpe_mm(motion, motion, mask)
    assert float(same["mpjpe_mm"]) == 0 and float(same["mpjpe_global_mm"]) == 0
    drifted = motion.clone()
    drifted[..., 1] += 0.05  # root velocity: the trajectory drifts, the pose does not change
    errors = task.mpjpe_mm(motion, drifted, mask)
    assert float(errors["mpjpe_mm"]) < 1e-3 and float(errors["mpjpe_global_mm"]) > 10.0


def test_learning_rate_schedule():
    factor = step_schedule(warmup_steps=10, milestones=[100, 200], gamma=0.05)
    assert factor(0) == pytest.approx(0.1) and factor(9) == pytest.approx(1.0)
    assert factor(99) == pytest.approx(1.0) and factor(100) == pytest.approx(0.05)
    assert factor(250) == pytest.approx(0.05**2)


def test_optimiser_is_the_fused_adamw_on_the_cpu_with_the_same_update():
    torch.manual_seed(0)
    weights = [torch.nn.Parameter(torch.randn(8, 4)), torch.nn.Parameter(torch.randn(4))]
    plain = [torch.nn.Parameter(w.detach().clone()) for w in weights]
    fused = adamw_with_schedule(iter(weights), 1e-2, 0.01, 0, [], 1.0)["optimizer"]
    reference = torch.optim.AdamW(plain, lr=1e-2, betas=(0.9, 0.99), weight_decay=0.01)
    assert fused.defaults["fused"] is True and len(fused.param_groups[0]["params"]) == 2
    for _ in range(5):
        for a, b in zip(weights, plain, strict=True):
            a.grad = torch.randn_like(a)
            b.grad = a.grad.clone()
        fused.step(), reference.step()
    assert all(torch.allclose(a, b, atol=1e-6) for a, b in zip(weights, plain, strict=True))
    # Where the fused kernel does not run (here: integer tensors), the default AdamW.
    assert adamw_with_schedule([torch.zeros(2, dtype=torch.long)], 1e-2, 0.0, 0, [], 1.0)[
        "optimizer"].defaults["fused"] is None


# --------------------------------------------------------------------------- hostile input

RVQ_YAML = (REPO / "configs/rvq/synthetic.yaml").read_text()


def _edited(tmp_path: Path, old: str, new: str) -> tuple[Path, int]:
    """A copy of configs/rvq/synthetic.yaml with `old` replaced, and the 1-based line of it."""
    assert RVQ_YAML.count(old) == 1, old
    text = RVQ_YAML.replace(old, new)
    path = tmp_path / "mine.yaml"
    path.write_text(text)
    return path, text[: text.index(new)].count("\n") + 1


HOSTILE = {
    # name: (YAML edit or None, extra arguments, expected message; {yaml} {line} {root} {tmp})
    "misspelt data key": (("batch_size: 64", "bach_size: 64"), [],
                          "{yaml}:{line}: data.init_args.bach_size: segmo.data.MotionDataModule has "
                          "no argument 'bach_size' (did you mean 'batch_size'?)"),
    "misspelt model key": (("width: 128", "widht: 128"), [],
                           "{yaml}:{line}: model.init_args.widht: segmo.tasks.tokenizer.RVQTask has no "
                           "argument 'widht' (did you mean 'width'?)"),
    "misspelt trainer key": (("max_steps: 6000", "max_step: 6000"), [],
                             "{yaml}:{line}: trainer.max_step: the Trainer has no argument "
                             "'max_step' (did you mean 'max_steps'?)"),
    "misspelt top-level key": (("\ntrainer:\n  max_steps", "\ntrainr:\n  max_steps"), [],
                               "trainr.max_steps: segmo fit has no key 'trainr' (did you mean "
                               "'trainer'?)"),
    "bad value type in YAML": (("batch_size: 64", "batch_size: abc"), [],
                               "{yaml}:{line}: data.init_args.batch_size: expected int, got 'abc'"),
    "bad choice in YAML": (("    skeleton: t2m\n    width", "    skeleton: t3m\n    width"), [],
                           "{yaml}:{line}: model.init_args.skeleton: expected one of 't2m', 'kit', "
                           "got 't3m'"),
    "unknown class": (("class_path: segmo.data.MotionDataModule", "class_path: segmo.data.Nope"), [],
                      "{yaml}:{line}: data.class_path: segmo.data.Nope: module 'segmo.data' has no "
                      "attribute 'Nope'"),
    "invalid YAML": (("trainer:\n", "trainer: [\n"), [],
                     "not valid YAML: expected ',' or ']', but got ':' (while parsing a flow "
                     "sequence started at line {line})"),
    "key set twice in YAML": (("betas: [0.9", "lr: 1.0\n    betas: [0.9"), [],  # the last one won
                              "{yaml}:{line}: key 'model.init_args.lr' set twice (also line "),
    "section set twice in YAML": (("trainer:\n  max_steps", "data:\n  init_args:\n    batch_size: 8\n"
                                   "trainer:\n  max_steps"), [], "{yaml}:{line}: key 'data' set twice (also line "),
    "missing config file": (None, ["--config", "{tmp}/none.yaml"], "--config {tmp}/none.yaml: no such file"),
    "misspelt argument": (None, ["--data.init_args.bach_size=3"],
                          "argument --data.init_args.bach_size=3: data.init_args.bach_size: "
                          "segmo.data.MotionDataModule has no argument 'bach_size' (did you mean "
                          "'batch_size'?)"),
    "bad argument type": (None, ["--trainer.max_steps=abc"],
                          "argument --trainer.max_steps=abc: trainer.max_steps: expected int, got 'abc'"),
    "unknown argument": (None, ["--nonsense=1"], "unrecognized arguments: --nonsense=1"),
    "missing data root": (None, ["--data.root={tmp}/nowhere"],
                          "data.init_args.root='{tmp}/nowhere': no such dataset folder"),
    "zero batch size": (None, ["--data.init_args.batch_size=0"],
                        "data.init_args.batch_size=0 must be positive"),
    "missing checkpoint": (None, ["--ckpt_path={tmp}/none.ckpt"],
                           "--ckpt_path {tmp}/none.ckpt: no such checkpoint file"),
    "not a checkpoint": (None, ["--ckpt_path={tmp}/junk.ckpt"],
                         "--ckpt_path {tmp}/junk.ckpt: not a readable checkpoint (not a torch file)"),
    "EMA decay": (None, ["--trainer.callbacks+=segmo.training.ema.EMA", "--trainer.callbacks.decay=1.5"],
                  "EMA: decay must lie strictly between 0 and 1, got 1.5"),
    "empty config": (None, ["--config", "{tmp}/empty.yaml"],
                     "{tmp}/empty.yaml: an empty config; expected a mapping of keys"),
    "negative width": (None, ["--model.init_args.width=-1"],
                       "RVQConfig: width must be a whole number >= 1, got -1"),
    "no quantizers": (None, ["--model.init_args.num_quantizers=0"],
                      "RVQConfig: num_quantizers must be a whole number >= 1, got 0"),
    "dropout above 1": (None, ["--model.init_args.dropout=5"],
                        "RVQConfig: dropout must be a number in [0, 1), got 5"),
    "negative max_steps": (None, ["--trainer.max_steps=-5"],
                           "trainer: `max_steps` must be a non-negative integer or -1"),
    "negative gamma": (None, ["--model.init_args.gamma=-1"],  # trained uphill, exit 0
                       "RVQTask: gamma must be a number > 0 (the learning rate's factor at each "
                       "milestone), got -1.0"),
    "zero learning rate": (None, ["--model.init_args.lr=0"],  # trained nothing, exit 0
                           "RVQTask: lr must be a number > 0, got 0.0"),
    "negative learning rate": (None, ["--model.init_args.lr=-1"],
                               "RVQTask: lr must be a number > 0, got -1.0"),
    "betas above 1": (None, ["--model.init_args.betas=[2,0.99]"],
                      "RVQTask: betas must be two numbers in [0, 1), got [2.0, 0.99]"),
    "negative weight decay": (None, ["--model.init_args.weight_decay=-1"],
                              "RVQTask: weight_decay must be a number >= 0, got -1.0"),
    "seed beyond numpy's": (None, ["--seed_everything=5000000000"],
                            "--seed_everything 5000000000: expected a whole number from 0 to 4294967295"),
    "negative data seed": (None, ["--data.init_args.seed=-1"],
                           "data.init_args.seed=-1 must be a whole number from 0 to 2^63 - 1"),
    "data seed beyond 64 bits": (None, ["--data.init_args.seed=99999999999999999999999"],
                                 "data.init_args.seed=99999999999999999999999 must be a whole number"),
    "negative max_motions": (None, ["--data.init_args.max_motions=-1"],  # dropped the last motion
                             "data.init_args.max_motions=-1 must be a whole number from 1"),
    "negative num_workers": (None, ["--data.init_args.num_workers=-1"],
                             "data.init_args.num_workers=-1 must be a whole number from 0"),
    "batch beyond 64 bits": (None, ["--data.init_args.batch_size=1000000000000000000000000000000"],
                             "data.init_args.batch_size=1000000000000000000000000000000 must be"),
    "zero val_check_interval": (None, ["--trainer.val_check_interval=0"],
                                "--trainer.val_check_interval 0: expected a number > 0 (or null)"),
    "zero check_val_every_n_epoch": (None, ["--trainer.check_val_every_n_epoch=0"],
                                     "--trainer.check_val_every_n_epoch 0: expected a number > 0"),
    "run name outside runs_dir": (None, ["--run_name=../../escaped"],
                                  "--run_name '../../escaped': a folder name (no '/' or '..')"),
    "runs_dir a file": (None, ["--runs_dir={tmp}/junk.ckpt"],
                        "--runs_dir {tmp}/junk.ckpt: exists and is not a directory"),
    "last checkpoint of no run": (None, ["--ckpt_path=last"],
                                  "--ckpt_path last: no last.ckpt in {tmp}/runs/rvq/synthetic/version_*"),
    "best checkpoint of no run": (None, ["--ckpt_path=best"],
                                  "--ckpt_path best: no best-*.ckpt in {tmp}/runs/rvq/synthetic/"),
    "every motion shorter than the window": (None, ["--data.init_args.window=100000"],
                                             "train.txt: no usable samples"),
    "no training batches": (None, ["--trainer.limit_train_batches=0"],  # exit 0, no checkpoint
                            "--trainer.limit_train_batches 0: trains nothing"),
    "default_root_dir": (None, ["--trainer.default_root_dir={tmp}/elsewhere"],
                         "--trainer.default_root_dir is not used by segmo: the run directory is "
                         "RUNS_DIR/STAGE/RUN_NAME/version_K; set --runs_dir (and --run_name) instead"),
}


@pytest.mark.parametrize("case", HOSTILE, ids=list(HOSTILE))
def test_hostile_fit_input_is_one_line_with_exit_2(case, tmp_path, capsys):
    from segmo.cli import main as segmo_main

    edit, extra, expected = HOSTILE[case]
    root = make_dataset(tmp_path / "data")
    (tmp_path / "junk.ckpt").write_bytes(b"not a checkpoint")
    (tmp_path / "empty.yaml").write_text("# nothing here yet\n")
    yaml_path, line = _edited(tmp_path, *edit) if edit else (REPO / "configs/rvq/synthetic.yaml", 0)
    config = [] if "--config" in extra else ["--config", str(yaml_path)]
    argv = ["fit", *config, *tiny_overrides(root, tmp_path / "runs"), "--trainer.max_steps=1",
            *[a.format(tmp=tmp_path) for a in extra]]
    capsys.readouterr()
    with pytest.raises(SystemExit) as exit_:
        segmo_main(argv)
    err = capsys.readouterr().err
    lines = [x for x in err.splitlines() if x.strip()]
    assert exit_.value.code == 2 and "Traceback" not in err and len(lines) == 1, err
    assert lines[0].startswith(f"segmo fit: {yaml_path}:" if edit else "segmo fit: ")
    assert expected.format(yaml=yaml_path, line=line, root=root, tmp=tmp_path) in lines[0]
    assert not (tmp_path / "runs").exists()  # refused before a run folder was made


def _checkpoint(path: Path, class_path: str = "segmo.tasks.tokenizer.RVQTask",
                hparams: dict | None = None, **changes) -> Path:
    """A file shaped as a checkpoint of `segmo fit` of the tiny tokenizer (no weights)."""
    checkpoint = {"state_dict": {}, "global_step": 3, "pytorch-lightning_version": "2.6.6",
                  "hyper_parameters": {"_class_path": class_path, **TINY_MODEL, **(hparams or {})}}
    checkpoint.update(changes)
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(checkpoint, path)
    return path


class _RunsCode:
    """Unpickling this object runs code: it touches the file it names."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (Path.touch, (self.marker,))


def test_checkpoints_that_would_train_another_model_are_refused(tmp_path, capsys):
    """Lightning builds the model from the settings a checkpoint records: a tokenizer
    checkpoint given to the length config trained the tokenizer (and rewrote that run's
    last.ckpt and config.yaml), and a width given on resume was silently dropped."""
    from segmo.cli import main as segmo_main

    root = make_dataset(tmp_path / "data")
    runs = tmp_path / "runs"
    marker = tmp_path / "ran"
    cases = {
        _checkpoint(runs / "length/x/version_0/checkpoints/last.ckpt", "segmo.tasks.length.LengthTask"):
            "a checkpoint of segmo.tasks.length.LengthTask, but the config trains "
            "segmo.tasks.tokenizer.RVQTask; give a checkpoint of this stage",
        _checkpoint(tmp_path / "wide.ckpt", hparams={"width": 32}):
            "argument --model.init_args.width=16: model.init_args.width=16, but --ckpt_path "
            f"{tmp_path / 'wide.ckpt'} was trained with 32, and the model is built from its "
            "checkpoint's settings",
        _checkpoint(tmp_path / "code.ckpt", callbacks=_RunsCode(marker)):
            "holds Python objects other than tensors and plain values, which segmo does not "
            "unpickle",
        _checkpoint(tmp_path / "no_version.ckpt", **{"pytorch-lightning_version": None}):
            "not a Lightning checkpoint (no pytorch-lightning_version)",
        _checkpoint(tmp_path / "step.ckpt", global_step="abc"):
            "not a Lightning checkpoint (no global_step)",
    }
    before = {path: path.read_bytes() for path in cases}
    for path, expected in cases.items():
        for command in ("fit", "validate"):
            with pytest.raises(SystemExit) as exit_:
                segmo_main([command, "--config", str(REPO / "configs/rvq/synthetic.yaml"),
                            *tiny_overrides(root, runs), f"--ckpt_path={path}"])
            err = capsys.readouterr().err.strip()
            assert exit_.value.code == 2 and "\n" not in err and expected in err, err
    assert not marker.exists()  # the pickle's code did not run
    assert {path: path.read_bytes() for path in cases} == before
    assert sorted(p.relative_to(runs).as_posix() for p in runs.rglob("*") if p.is_file()) == \
        ["length/x/version_0/checkpoints/last.ckpt"]


def test_validate_and_test_refuse_to_score_an_untrained_model(tmp_path, capsys):
    from segmo.cli import main as segmo_main

    root = make_dataset(tmp_path / "data")
    for command in ("validate", "test"):
        with pytest.raises(SystemExit) as exit_:
            segmo_main([command, "--config", str(REPO / "configs/rvq/synthetic.yaml"),
                        *tiny_overrides(root, tmp_path / "runs")])
        err = capsys.readouterr().err.strip()
        assert exit_.value.code == 2 and "\n" not in err, err
        assert err.startswith(f"segmo {command}: --ckpt_path is needed: {command} scores the model "
                              "of a checkpoint"), err


@pytest.mark.parametrize("stage", ["mask", "length"])
def test_a_model_shorter_than_the_data_is_refused_before_training(stage, text_dataset,
                                                                   tokenizer_dir, tmp_path, capsys):
    """It was a ValueError at the first batch holding a longer motion."""
    from segmo.cli import main as segmo_main

    tokenizer = [f"--model.init_args.tokenizer={tokenizer_dir['t2m']}"] if stage == "mask" else []
    with pytest.raises(SystemExit) as exit_:
        segmo_main(["fit", "--config", str(REPO / f"configs/{stage}/synthetic.yaml"),
                    f"--data.root={text_dataset['t2m']}", f"--runs_dir={tmp_path / 'runs'}",
                    *tokenizer, "--model.init_args.max_tokens=2",
                    "--trainer.enable_progress_bar=false"])
    err = capsys.readouterr().err.strip()
    assert exit_.value.code == 2 and "\n" not in err, err
    assert err.startswith("segmo fit: model.init_args.max_tokens=2: the data's longest motion is ")
    assert not (tmp_path / "runs").exists()


def test_tokenizer_that_is_not_a_model_directory(text_dataset, tmp_path, capsys):
    from segmo.cli import main as segmo_main

    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "config.json").write_text("{not json")
    for tokenizer, expected in ((tmp_path, f"model.init_args.tokenizer='{tmp_path}': not an exported "
                                           "tokenizer directory (no config.json)"),
                                (broken, f"model.init_args.tokenizer='{broken}': "
                                         f"{broken / 'config.json'}:1: not valid JSON")):
        with pytest.raises(SystemExit) as exit_:
            segmo_main(["fit", "--config", str(REPO / "configs/mask/synthetic.yaml"),
                        f"--data.root={text_dataset['t2m']}", f"--runs_dir={tmp_path / 'runs'}",
                        f"--model.init_args.tokenizer={tokenizer}"])
        err = capsys.readouterr().err.strip()
        assert exit_.value.code == 2 and "\n" not in err and err.startswith(f"segmo fit: {expected}"), err


def test_export_from_another_directory_keeps_the_corpus_on_the_model_card(tmp_path, monkeypatch):
    """`data.root` relative to the fit's directory: `segmo export` run from elsewhere looked
    for corpus.json beside itself and left the corpus out of the model card."""
    from segmo.export import export
    from segmo.models.pretrained import read_config

    fit_dir, other = tmp_path / "project", tmp_path / "elsewhere"
    other.mkdir()
    make_dataset(fit_dir / "data")
    (fit_dir / "data" / "corpus.json").write_text('{"name": "synthetic", "version": 2, "seed": 7}')
    monkeypatch.chdir(fit_dir)
    cli_main(["fit", "--config", str(CONFIGS[0]), *tiny_overrides(Path("data"), Path("runs")),
              "--trainer.max_steps=1", "--trainer.val_check_interval=1"])
    last = next(fit_dir.glob("runs/*/*/version_*/checkpoints/last.ckpt"))
    monkeypatch.chdir(other)
    card = read_config(export(last, other / "model"))
    assert card["meta"]["data"]["root"] == "data"
    assert card["meta"]["data"]["corpus"] == {"name": "synthetic", "version": 2, "seed": 7}
