"""A `segmo fit` killed with SIGKILL and resumed with --ckpt_path logs exactly what an
uninterrupted run logs, in the same version directory, with a clean metrics.csv."""

from __future__ import annotations

import csv
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import REPO

TESTS = Path(__file__).resolve().parent
TINY_MASK = ["--model.init_args.dim=32", "--model.init_args.depth=1", "--model.init_args.heads=2",
             "--model.init_args.ff_dim=32", "--model.init_args.alignment_dim=16"]
CHECKPOINT_EVERY, KILL_AT, MAX_STEPS = 6, 9, 24


def segmo_fit(args: list[str]) -> subprocess.Popen:
    env = {**os.environ, "OMP_NUM_THREADS": "1",
           "PYTHONPATH": os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")])}
    # Its own process group, so that a hung run and its children can be killed together.
    return subprocess.Popen([sys.executable, "-m", "segmo", "fit", *args], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            start_new_session=True)


def finish(proc: subprocess.Popen, timeout: float = 300) -> str:
    try:
        out, _ = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, _ = proc.communicate()
        pytest.fail(f"segmo fit did not finish in {timeout} s:\n{out[-3000:]}")
    assert proc.returncode == 0, out[-3000:]
    return out


def rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


@pytest.mark.slow
def test_killed_and_resumed_fit_logs_the_same_losses(text_dataset, tokenizer_dir, tmp_path):
    args = ["--config", str(REPO / "configs/mask/synthetic.yaml"), f"--data.root={text_dataset['t2m']}",
            f"--model.init_args.tokenizer={tokenizer_dir['t2m']}", *TINY_MASK,
            "--data.init_args.batch_size=4",  # 16 samples: 4 batches an epoch
            f"--trainer.max_steps={MAX_STEPS}", "--trainer.check_val_every_n_epoch=null",
            "--trainer.val_check_interval=5", "--trainer.log_every_n_steps=1",
            "--trainer.enable_progress_bar=false", "--trainer.enable_model_summary=false",
            "--trainer.callbacks+=ModelCheckpoint",
            f"--trainer.callbacks.every_n_train_steps={CHECKPOINT_EVERY}",
            "--trainer.callbacks.save_top_k=-1", "--trainer.callbacks.filename={step}",
            "--trainer.callbacks.save_last=true"]
    whole = tmp_path / "whole"
    finish(segmo_fit([*args, f"--runs_dir={whole}"]))

    runs = tmp_path / "killed"
    run = runs / "mask" / "synthetic" / "version_0"
    marker = tmp_path / "hanging"
    proc = segmo_fit([*args, f"--runs_dir={runs}", "--trainer.callbacks+=fit_helpers.HangAt",
                      f"--trainer.callbacks.step={KILL_AT}", f"--trainer.callbacks.marker={marker}"])
    deadline = time.monotonic() + 300
    try:
        while not marker.exists() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.1)
    finally:
        if proc.poll() is None:  # kill -9, mid-epoch, steps after the checkpoint logged
            os.killpg(proc.pid, signal.SIGKILL)
        out, _ = proc.communicate()
    assert marker.exists(), out[-3000:]
    checkpoint = run / "checkpoints" / f"step={CHECKPOINT_EVERY}.ckpt"
    assert checkpoint.is_file()
    killed_steps = {int(r["step"]) for r in rows(run / "metrics.csv")}
    assert max(killed_steps) == KILL_AT - 1  # rows past the checkpoint were on disk

    finish(segmo_fit([*args, f"--runs_dir={runs}", f"--ckpt_path={checkpoint}"]))

    assert sorted(p.name for p in run.parent.iterdir()) == ["version_0"]  # the same run directory
    resumed = rows(run / "metrics.csv")
    reference = rows(whole / "mask" / "synthetic" / "version_0" / "metrics.csv")
    keys = [(r["step"], bool(r.get("val/loss"))) for r in resumed]
    assert len(keys) == len(set(keys)), "a step of the killed run is logged twice"
    assert resumed == reference  # every value of every row, the validation rows included
    after = [r for r in resumed if r.get("train/loss") and int(r["step"]) >= CHECKPOINT_EVERY]
    assert len(after) == MAX_STEPS - CHECKPOINT_EVERY >= 10
