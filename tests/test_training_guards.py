"""Non-finite guards: a corrupt motion is refused before training, a NaN loss stops every
stage naming the step and the batch's ids, and no checkpoint or export holds NaN/inf."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import REPO, build_text_dataset

from segmo.cli import main as segmo_main
from segmo.errors import SegmoError
from segmo.tasks.base import NonFiniteError
from segmo.training.cli import main as cli_main

TESTS = Path(__file__).resolve().parent
TINY = {
    "rvq": ["--model.init_args.width=16", "--model.init_args.code_dim=8",
            "--model.init_args.codebook_size=8", "--model.init_args.num_quantizers=3"],
    "mask": ["--model.init_args.dim=32", "--model.init_args.depth=1", "--model.init_args.heads=2",
             "--model.init_args.ff_dim=32", "--model.init_args.alignment_dim=16"],
    "residual": ["--model.init_args.dim=32", "--model.init_args.depth=1",
                 "--model.init_args.heads=2", "--model.init_args.ff_dim=32"],
    "length": ["--model.init_args.hidden=16"],
    "evaluator": [f"--model.init_args.{k}=8" for k in ("word_dim", "text_hidden", "movement_hidden",
                                                       "movement_dim", "motion_hidden")],
}


def fit_args(stage: str, root: Path, runs: Path, tokenizer: Path | None = None) -> list[str]:
    args = ["fit", "--config", str(REPO / "configs" / stage / "synthetic.yaml"), f"--data.root={root}",
            f"--runs_dir={runs}", "--data.init_args.batch_size=4", "--trainer.enable_progress_bar=false",
            "--trainer.enable_model_summary=false", *TINY[stage]]
    if stage in ("mask", "residual"):
        args.append(f"--model.init_args.tokenizer={tokenizer}")
    return args


@pytest.fixture
def own_dataset(tmp_path) -> Path:
    """A dataset this test may damage (the session's text_dataset is shared)."""
    return build_text_dataset(tmp_path / "data", encoders={"minilm": 384})


def _one_error_line(stderr: str, command: str) -> str:
    """The error line, which must be the only line of stderr and name the command."""
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert "Traceback" not in stderr and len(lines) == 1, stderr
    assert lines[0].startswith(f"segmo {command}: ")
    return lines[0]


def test_fit_refuses_a_1e30_motion_before_training(own_dataset, tmp_path):
    mid = (own_dataset / "train.txt").read_text().split()[1]
    path = own_dataset / "new_joint_vecs" / f"{mid}.npy"
    features = np.load(path)
    features[7, 42] = 1e30
    np.save(path, features)
    runs = tmp_path / "runs"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    done = subprocess.run([sys.executable, "-m", "segmo", *fit_args("rvq", own_dataset, runs),
                           "--trainer.max_steps=2"], capture_output=True, text=True, env=env, timeout=300)
    assert done.returncode == 2
    line = _one_error_line(done.stderr, "fit")
    assert f"{own_dataset}/train.txt: 1 of 8 motion files" in line
    assert f"{path}: frame 7 dim 42 is 1e+30" in line
    assert not list(runs.rglob("*.ckpt"))  # refused before training started
    # Lazy loading checks the values up front too.
    with pytest.raises(SegmoError, match=rf"{mid}\.npy: frame 7 dim 42 is 1e\+30"):
        cli_main([*fit_args("rvq", own_dataset, runs), "--data.init_args.preload=false",
                  "--trainer.max_steps=2"])


@pytest.mark.parametrize("stage", ["rvq", "mask", "residual", "length", "evaluator"])
def test_a_nan_loss_stops_every_stage_naming_the_step_and_ids(stage, text_dataset, tokenizer_dir,
                                                              tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(TESTS))  # fit_helpers for jsonargparse
    runs = tmp_path / "runs"
    args = fit_args(stage, text_dataset["t2m"], runs, tokenizer_dir["t2m"])
    with pytest.raises(NonFiniteError) as error:
        cli_main([*args, "--trainer.max_steps=4", "--trainer.log_every_n_steps=1",
                  "--trainer.limit_val_batches=0", "--trainer.callbacks+=fit_helpers.PoisonBatch",
                  "--trainer.callbacks.at_batch=2",
                  "--trainer.callbacks+=ModelCheckpoint", "--trainer.callbacks.every_n_train_steps=1",
                  "--trainer.callbacks.save_top_k=-1", "--trainer.callbacks.filename={step}"])
    message = str(error.value)
    assert "\n" not in message
    assert re.search(r"the training loss is nan at step 2 \(epoch \d, batch \d\)", message), message
    ids = re.search(r"the batch's samples: ([^;]+);", message).group(1).split(", ")
    train = set((text_dataset["t2m"] / "train.txt").read_text().split())
    assert len(ids) == 4 and set(ids) <= train
    # The checkpoints of steps 1 and 2 were written and are finite; nothing after them.
    checkpoints = sorted(runs.rglob("step=*.ckpt"))
    assert [p.name for p in checkpoints] == ["step=1.ckpt", "step=2.ckpt"]
    for path in checkpoints:
        state = torch.load(path, map_location="cpu", weights_only=False)["state_dict"]
        assert all(torch.isfinite(v).all() for v in state.values() if v.is_floating_point())


def test_no_checkpoint_with_non_finite_tensors_is_written_or_exported(text_dataset, tmp_path, capsys):
    runs = tmp_path / "runs"
    cli = cli_main([*fit_args("rvq", text_dataset["t2m"], runs), "--trainer.max_steps=1"])
    with torch.no_grad():
        cli.model.model.decoder.layers[0].weight[0, 0, 0] = float("inf")
    with pytest.raises(NonFiniteError, match=r"not writing a checkpoint at step 1: 1 of \d+ tensors "
                                             r"hold NaN/inf \(model\.decoder\.layers\.0\.weight\)"):
        cli.trainer.save_checkpoint(tmp_path / "diverged.ckpt")
    assert not (tmp_path / "diverged.ckpt").exists()

    # A checkpoint damaged after the fact (or by an older segmo) is refused by export.
    last = Path(cli.trainer.checkpoint_callback.last_model_path)
    checkpoint = torch.load(last, map_location="cpu", weights_only=False)
    for name in ("model.encoder.layers.0.weight", "model.quantizer.codebooks"):
        checkpoint["state_dict"][name].view(-1)[0] = float("nan")
    torch.save(checkpoint, tmp_path / "nan.ckpt")
    capsys.readouterr()
    with pytest.raises(SystemExit) as exit_:
        segmo_main(["export", str(tmp_path / "nan.ckpt"), "--out", str(tmp_path / "model")])
    assert exit_.value.code == 2
    line = _one_error_line(capsys.readouterr().err, "export")
    assert f"{tmp_path / 'nan.ckpt'}: 2 of " in line
    assert "model.encoder.layers.0.weight, model.quantizer.codebooks" in line
    assert not (tmp_path / "model").exists()


def test_a_version_folder_named_with_a_superscript_digit_is_not_a_version(tmp_path):
    """`--ckpt_path last` beside a folder `version_²` (a digit to str.isdigit(), not to
    int()) was a ValueError traceback."""
    from segmo.training.runs import named_checkpoint

    last = tmp_path / "version_3" / "checkpoints" / "last.ckpt"
    last.parent.mkdir(parents=True)
    last.write_bytes(b"")
    (tmp_path / "version_²" / "checkpoints").mkdir(parents=True)
    assert named_checkpoint(tmp_path, "last") == last
