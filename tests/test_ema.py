"""`segmo.training.ema.EMA` under `segmo fit`: the average it keeps is the formula's, the
frozen tokenizer inside a token-level task is not touched, training itself is not changed,
`segmo export` writes the average, and a resumed run ends with the average of an
uninterrupted one."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from conftest import REPO
from test_training_resume import TINY_MASK

from segmo.export import main as export_main
from segmo.models.pretrained import load_pretrained
from segmo.training.cli import main as cli_main

DECAY = 0.5  # a short average, so that six steps leave it far from the last weights
EMA = ["--trainer.callbacks+=segmo.training.ema.EMA", f"--trainer.callbacks.decay={DECAY}"]


@pytest.fixture()
def fit(text_dataset, tokenizer_dir, tmp_path):
    def run(name: str, *extra: str) -> Path:
        cli_main(["fit", "--config", str(REPO / "configs/mask/synthetic.yaml"),
                  f"--data.root={text_dataset['t2m']}", f"--model.init_args.tokenizer={tokenizer_dir['t2m']}",
                  *TINY_MASK, "--data.init_args.batch_size=4", "--trainer.check_val_every_n_epoch=null",
                  "--trainer.val_check_interval=3", "--trainer.enable_progress_bar=false",
                  "--trainer.enable_model_summary=false", f"--runs_dir={tmp_path / name}", *extra])
        return tmp_path / name / "mask" / "synthetic" / "version_0" / "checkpoints" / "last.ckpt"
    return run


def load(path: Path) -> dict:
    return torch.load(path, map_location="cpu", weights_only=False)


@pytest.mark.slow
def test_ema_is_the_average_of_the_steps_and_leaves_the_rest_alone(fit, tmp_path):
    steps = 6
    plain = load(fit("plain", f"--trainer.max_steps={steps}"))
    record = ["--trainer.callbacks+=fit_helpers.SaveStepWeights",
              f"--trainer.callbacks.directory={tmp_path / 'steps'}"]
    checkpoint = load(last := fit("ema", f"--trainer.max_steps={steps}", *EMA, *record))
    average, trained = checkpoint["state_dict"], checkpoint["current_model_state"]
    history = torch.load(tmp_path / "steps" / "steps.pt")
    assert sorted(history) == list(range(1, steps + 1))

    # Training is not changed by keeping the average (no random draw, no other weights).
    assert plain["state_dict"].keys() == trained.keys()
    assert all(torch.equal(plain["state_dict"][k], trained[k]) for k in trained)
    # The first update copies the weights, every later one moves 1 - decay of the way.
    for name, weight in history[steps].items():
        expected = history[1][name].clone()
        for step in range(2, steps + 1):
            expected = expected + (1 - DECAY) * (history[step][name] - expected)
        assert torch.allclose(average[name], expected, atol=1e-6), name
        assert torch.equal(trained[name], weight), name
    assert sum(not torch.equal(average[k], trained[k]) for k in history[steps]) == len(history[steps])
    # The frozen tokenizer is carried bit for bit (a weight that never moves stays put).
    frozen = [k for k in trained if k.startswith("tokenizer.")]
    assert frozen and all(torch.equal(average[k], trained[k]) for k in frozen)

    # `segmo export` writes the average.
    export_main([str(last), "--out", str(tmp_path / "exported")])
    exported = load_pretrained(tmp_path / "exported").state_dict()
    assert exported and all(torch.equal(v, average[f"model.{k}"]) for k, v in exported.items())


@pytest.mark.slow
def test_a_resumed_run_ends_with_the_average_of_an_uninterrupted_one(fit):
    every = "--trainer.val_check_interval=2"  # last.ckpt at steps 2, 4, 6, 8
    whole = load(fit("whole", "--trainer.max_steps=8", every, *EMA))
    first = fit("parts", "--trainer.max_steps=4", every, *EMA)
    assert load(first)["global_step"] == 4
    resumed = load(fit("parts", "--trainer.max_steps=8", every, *EMA, f"--ckpt_path={first}"))
    assert resumed["global_step"] == 8
    for key in ("state_dict", "current_model_state"):
        assert all(torch.equal(whole[key][k], resumed[key][k]) for k in whole[key]), key
    assert whole["averaging_state"]["n_averaged"] == resumed["averaging_state"]["n_averaged"] == 8


def test_decay_outside_0_1_is_refused():
    from segmo.errors import SegmoError
    from segmo.training.ema import EMA as Callback

    for decay in (0.0, 1.0, 1.5, -0.1):
        with pytest.raises(SegmoError, match=f"EMA: decay must lie strictly between 0 and 1, got {decay}"):
            Callback(decay=decay)
    with pytest.raises(SegmoError, match="EMA: start_step must be 0 or more, got -1"):
        Callback(start_step=-1)
    assert Callback(decay=0.9).should_update(step_idx=0)
    assert not Callback(decay=0.9, start_step=3).should_update(step_idx=2)
    assert Callback(decay=0.9, start_step=3).should_update(step_idx=3)
    assert not Callback(decay=0.9).should_update(epoch_idx=1)  # steps only
