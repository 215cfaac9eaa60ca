"""`segmo fit` under Lightning DDP with 2 CPU ranks (gloo): rvq, mask (in-sample alignment,
with validation), residual, length and evaluator train, and the ranks end with identical
weights. The mask stage runs as users start it (`segmo fit --trainer.devices=2`: Lightning
starts the second rank); the others in two ranks started as torchrun does, each fitting
the four stages in turn (one start-up a rank instead of two a stage: about 20 s against
110 s on a 2-core host).

The mask run's validation split is built so that only rank 0's share has ground-truth
spans: the segment top-1 metrics are then logged by one rank's batches only, the case
that left the other rank waiting in the end-of-epoch all-reduce forever.
"""

from __future__ import annotations

import csv
import json
import os
import signal
import socket
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from conftest import REPO, build_text_dataset

TESTS = Path(__file__).resolve().parent
TINY = {
    "rvq": ["--model.init_args.width=16", "--model.init_args.code_dim=8",
            "--model.init_args.codebook_size=8", "--model.init_args.num_quantizers=3"],
    "mask": ["--model.init_args.dim=32", "--model.init_args.depth=1", "--model.init_args.heads=2",
             "--model.init_args.ff_dim=32", "--model.init_args.alignment=in_sample",
             "--model.init_args.alignment_dim=16"],
    "residual": ["--model.init_args.dim=32", "--model.init_args.depth=1",
                 "--model.init_args.heads=2", "--model.init_args.ff_dim=32"],
    "length": ["--model.init_args.hidden=16"],
    "evaluator": [f"--model.init_args.{k}=8" for k in ("word_dim", "text_hidden", "movement_hidden",
                                                       "movement_dim", "motion_hidden")],
}
STEPS = 4


@pytest.fixture(scope="module")
def ddp_data(tmp_path_factory) -> Path:
    """Text dataset whose val split (2 motions x 2 captions: DDP gives rank 0 entries 0 and 2,
    rank 1 entries 1 and 3) has ground-truth spans that only entry 0 can use."""
    root = build_text_dataset(tmp_path_factory.mktemp("ddp") / "data", encoders={"minilm": 384})
    first = (root / "val.txt").read_text().split()[0]
    segments = [line.split("#") for line in
                (root / "text_segments" / "rule" / f"{first}.txt").read_text().splitlines()]
    assert len(segments[0]) >= 2, "the fixture needs a multi-segment first caption"
    import numpy as np

    frames = len(np.load(root / "new_joint_vecs" / f"{first}.npy"))
    cuts = [round(i * frames / len(segments[0])) for i in range(len(segments[0]) + 1)]
    captions = [{"segments": [{"start": s, "end": e} for s, e in zip(cuts, cuts[1:])]},
                {"segments": [{"start": 0, "end": frames}]}]  # one span: not usable
    (root / "segments").mkdir()
    (root / "segments" / f"{first}.json").write_text(json.dumps({"captions": captions}))
    return root


def run_fit(args: list[str], timeout: float = 300) -> str:
    env = {**os.environ, "OMP_NUM_THREADS": "1",
           "PYTHONPATH": os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.Popen([sys.executable, "-m", "segmo", "fit", *args], env=env, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        out, _ = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:  # a deadlock: kill both ranks
        os.killpg(proc.pid, signal.SIGKILL)
        out, _ = proc.communicate()
        pytest.fail(f"DDP fit did not finish in {timeout} s (ranks deadlocked?):\n{out[-3000:]}")
    assert proc.returncode == 0, out[-3000:]
    return out


def stage_args(stage: str, data: Path, tokenizer_dir: dict, out: Path) -> list[str]:
    """`segmo fit` arguments of a tiny `stage` on 2 CPU ranks, writing under `out`."""
    args = ["--config", str(REPO / "configs" / stage / "synthetic.yaml"), f"--data.root={data}",
            f"--runs_dir={out / 'runs'}", *TINY[stage], "--data.init_args.batch_size=2",
            f"--trainer.max_steps={STEPS}", "--trainer.check_val_every_n_epoch=null",
            "--trainer.val_check_interval=2", "--trainer.log_every_n_steps=1",
            "--trainer.enable_progress_bar=false", "--trainer.enable_model_summary=false",
            "--trainer.accelerator=cpu", "--trainer.devices=2", "--trainer.strategy=ddp",
            "--trainer.callbacks+=fit_helpers.SaveRankState",
            f"--trainer.callbacks.directory={out / 'states' / stage}"]
    if stage in ("mask", "residual"):
        args.append(f"--model.init_args.tokenizer={tokenizer_dir['t2m']}")
    return args


def check_ranks(stage: str, out: Path) -> None:
    """Both ranks trained `stage` on their own shares and end with identical weights."""
    states = out / "states" / stage
    rank0, rank1 = (torch.load(states / f"rank{r}.pt") for r in (0, 1))
    assert rank0["world_size"] == rank1["world_size"] == 2
    assert rank0["step"] == rank1["step"] == STEPS
    assert rank0["ids"] != rank1["ids"]  # each rank trained on its own share of the data
    assert rank0["state"].keys() == rank1["state"].keys()
    for name, value in rank0["state"].items():
        assert torch.equal(value, rank1["state"][name]), f"{name} differs between the ranks"
    with open(out / "runs" / stage / "synthetic" / "version_0" / "metrics.csv", newline="") as f:
        logged = {key for row in csv.DictReader(f) for key, value in row.items() if value}
    assert {"val/loss", "train/loss"} <= logged
    if stage == "mask":
        assert "val/segment_top1" in logged  # from rank 0's batches alone
    if stage == "evaluator":
        assert "val/matching" in logged  # over the embeddings of both ranks


def skip_without_distributed() -> None:
    if not torch.distributed.is_available():
        pytest.skip("torch.distributed is not available in this build")


@pytest.mark.slow
@pytest.mark.xdist_group("ddp")  # under `make test`, one DDP run at a time (two ranks each)
def test_segmo_fit_launches_two_cpu_ranks_that_end_with_identical_weights(ddp_data, tokenizer_dir,
                                                                           tmp_path):
    """`segmo fit --trainer.devices=2`: Lightning starts the second rank itself."""
    skip_without_distributed()
    run_fit(stage_args("mask", ddp_data, tokenizer_dir, tmp_path))
    check_ranks("mask", tmp_path)


LAUNCHED = ["rvq", "residual", "length", "evaluator"]


@pytest.mark.slow
@pytest.mark.xdist_group("ddp")
def test_ranks_started_as_torchrun_starts_them_end_with_identical_weights(ddp_data, tokenizer_dir,
                                                                           tmp_path):
    """Two ranks started as torchrun or a cluster starts them, each fitting every stage of
    LAUNCHED in turn (one import of Lightning a rank for all of them). One test, not one a
    stage: a module fixture shared by four tests was built again whenever the random test
    order put another module's test between them."""
    skip_without_distributed()
    out = tmp_path
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    runs = json.dumps([stage_args(stage, ddp_data, tokenizer_dir, out) for stage in LAUNCHED])
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(port),
           "WORLD_SIZE": "2", "NODE_RANK": "0",
           "PYTHONPATH": os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")])}
    # Each rank writes to a file: a full pipe would stop one rank while the other waits
    # for it in a collective.
    logs = [out / f"rank{r}.log" for r in (0, 1)]
    ranks = []
    for r, log in enumerate(logs):
        with open(log, "w") as f:
            ranks.append(subprocess.Popen([sys.executable, str(TESTS / "ddp_ranks.py"), runs],
                                          env={**env, "LOCAL_RANK": str(r), "RANK": str(r)},
                                          stdout=f, stderr=subprocess.STDOUT, start_new_session=True))
    try:
        for rank in ranks:
            rank.wait(timeout=300)
    except subprocess.TimeoutExpired:  # a deadlock: kill both ranks
        for rank in ranks:
            os.killpg(rank.pid, signal.SIGKILL)
        pytest.fail("the launched DDP ranks did not finish in 300 s (deadlocked?)")
    for r, (rank, log) in enumerate(zip(ranks, logs)):
        assert rank.returncode == 0, f"rank {r}:\n{log.read_text()[-3000:]}"
    failed = []
    for stage in LAUNCHED:
        try:
            check_ranks(stage, out)
        except AssertionError as error:
            failed.append(f"{stage}: {error}")
    assert not failed, "\n".join(failed)
