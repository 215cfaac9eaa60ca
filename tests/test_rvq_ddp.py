"""Two CPU processes (gloo): codebooks and dropout depths stay identical across ranks."""

from __future__ import annotations

import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp

from segmo.models.tokenizer import RVQVAE, RVQConfig

STEPS = 6


def _worker(rank: int, world_size: int, directory: str) -> None:
    torch.set_num_threads(1)
    dist.init_process_group(
        "gloo", init_method=f"file://{directory}/rendezvous", rank=rank, world_size=world_size
    )
    try:
        torch.manual_seed(0)  # identical initial weights, as DDP would broadcast them
        model = RVQVAE(
            RVQConfig(feature_dim=263, width=16, code_dim=8, codebook_size=16, num_quantizers=4,
                      quantizer_dropout=0.6)
        ).train()
        # Different data and different generators on each rank: only the synchronisation
        # can keep the ranks agreeing.
        data = torch.Generator().manual_seed(100 + rank)
        generator = torch.Generator().manual_seed(rank)
        kept = []
        for _ in range(STEPS):
            out = model(torch.randn(2, 16, 263, generator=data), generator=generator)
            kept.append(int((out.indices[0, 0] >= 0).sum()))
        torch.save(
            {"state": model.quantizer.state_dict(), "kept": kept},
            f"{directory}/rank{rank}.pt",
        )
    finally:
        dist.destroy_process_group()


@pytest.mark.slow
@pytest.mark.xdist_group("ddp")  # under `make test`, one DDP run at a time (two ranks each)
def test_ranks_share_codebooks_and_dropout(tmp_path):
    if not dist.is_available():
        pytest.skip("torch.distributed is not available in this build")
    mp.spawn(_worker, args=(2, str(tmp_path)), nprocs=2, join=True)
    rank0 = torch.load(tmp_path / "rank0.pt")
    rank1 = torch.load(tmp_path / "rank1.pt")
    assert rank0["kept"] == rank1["kept"]
    assert len(set(rank0["kept"])) > 1, "dropout never changed the depth; the test proves nothing"
    for name, value in rank0["state"].items():
        assert torch.equal(value, rank1["state"][name]), f"buffer {name} differs between ranks"
    assert rank0["state"]["initialised"].all()
