"""Shared fixtures: tiny text-conditioned datasets and tokenizers for the stage tests.

The text features come from `HashEncoder`, a deterministic stand-in for a real encoder
(real encoders are tested in test_text_encoders.py): it keeps the stage tests fast while
exercising the real cache, dataset and collate code.
"""

from __future__ import annotations

import importlib.util
import os
import zlib
from pathlib import Path

# No test reaches a model hub: huggingface_hub reads this when it is imported.
os.environ["HF_HUB_OFFLINE"] = "1"

import numpy as np
import pytest
import torch

from segmo.motion.skeleton import get_skeleton

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"

CAPTIONS = [
    "a person walks forward, then waves.",
    "someone jumps twice and then sits down.",
    "a man turns left after walking.",
    "the figure claps three times.",
    "a person runs, then stops, then bows.",
    "a woman kicks with her right foot.",
]


def load_tool(name: str):
    """tools/<name>.py as a module (the tools are scripts, not a package)."""
    spec = importlib.util.spec_from_file_location(name, REPO / "tools" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def cli_failure(argv: list[str], capsys) -> str:
    """Run `segmo ARGV` in-process, expecting the one-line failure every command gives on
    bad input (exit status 2, no traceback); returns that line."""
    from segmo.cli import main

    capsys.readouterr()
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    err = capsys.readouterr().err
    assert exit_info.value.code == 2, f"exit {exit_info.value.code}: {err}"
    lines = [line for line in err.splitlines() if line.strip()]
    assert lines and "Traceback" not in err, err
    return lines[-1]


def tool_failure(name: str, argv: list[str], capsys) -> str:
    """Run tools/<name>.py as its command does (`segmo.cli.run`), expecting the one-line
    failure on bad input (exit status 2, no traceback); returns that line."""
    from segmo.cli import run

    tool = load_tool(name)
    capsys.readouterr()
    with pytest.raises(SystemExit) as exit_info:
        run(f"{name}.py", tool.main, argv)
    err = capsys.readouterr().err
    assert exit_info.value.code == 2, f"exit {exit_info.value.code}: {err}"
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def hash_vector(text: str, dim: int) -> torch.Tensor:
    generator = torch.Generator().manual_seed(zlib.crc32(text.encode()))
    return torch.nn.functional.normalize(
        torch.randn(dim, generator=generator, dtype=torch.float32), dim=0)


def hash_encoder(name: str, dim: int):
    """A `TextEncoder` whose vectors are a fixed function of the text (no model)."""
    from segmo.text.encoders import TextEncoder, TextEncoding

    class HashEncoder(TextEncoder):
        def __init__(self):
            super().__init__(name, torch.nn.Identity(), None, dim, 32, "hash")

        def encode(self, texts, batch_size=64):
            words = [t.split()[:8] for t in texts]
            length = max([len(w) for w in words] + [1])
            tokens = torch.zeros(len(texts), length, dim, dtype=torch.float32)
            mask = torch.zeros(len(texts), length, dtype=torch.bool)
            for i, ws in enumerate(words):
                for j, w in enumerate(ws):
                    tokens[i, j], mask[i, j] = hash_vector(w, dim), True
            sentence = torch.stack([hash_vector(t, dim) for t in texts]) if texts else tokens[:, 0]
            return TextEncoding(sentence, tokens, mask)

        def token_texts(self, texts):
            return [t.split()[:8] for t in texts]

    return HashEncoder()


def build_text_dataset(root: Path, skeleton: str = "t2m", motions: int = 12, seed: int = 0,
                       encoders: dict[str, int] | None = None) -> Path:
    """HumanML3D layout with random features, captions, rule segments and text caches."""
    from segmo.text.cache import update_cache
    from segmo.text.extract import segment_folder
    from segmo.text.rules import RuleSegmenter

    spec = get_skeleton(skeleton)
    rng = np.random.default_rng(seed)
    for folder in ("new_joint_vecs", "texts"):
        (root / folder).mkdir(parents=True)
    ids = [f"{i:06d}" for i in range(motions)]
    for k, mid in enumerate(ids):
        frames = int(rng.integers(max(spec.min_frames, 48), 100))
        features = (0.1 * rng.standard_normal((frames, spec.feature_dim))).astype(np.float32)
        np.save(root / "new_joint_vecs" / f"{mid}.npy", features)
        lines = [CAPTIONS[(k + j) % len(CAPTIONS)] for j in range(2)]
        (root / "texts" / f"{mid}.txt").write_text(
            "".join(f"{c}#{' '.join(w + '/OTHER' for w in c.split())}#0.0#0.0\n" for c in lines))
    np.save(root / "Mean.npy", np.zeros(spec.feature_dim, dtype=np.float32))
    np.save(root / "Std.npy", np.full(spec.feature_dim, 0.1, dtype=np.float32))
    splits = {"train": ids[:-4], "val": ids[-4:-2], "test": ids[-2:]}
    for split, split_ids in splits.items():
        (root / f"{split}.txt").write_text("\n".join(split_ids) + "\n")
    segment_folder(root, RuleSegmenter(), "rule", progress=False)
    for name, dim in (encoders or {"minilm": 384, "clip": 512}).items():
        update_cache(root, hash_encoder(name, dim), segments=["rule"], progress=False)
    return root


def build_tokenizer(path: Path, feature_dim: int, codebook_size: int = 16,
                    num_quantizers: int = 3, skeleton: str = "t2m") -> Path:
    """A randomly initialised, exported RVQ-VAE (the stages only need its interface)."""
    from segmo.models.tokenizer import RVQVAE, RVQConfig

    torch.manual_seed(0)
    model = RVQVAE(RVQConfig(feature_dim=feature_dim, width=16, code_dim=16,
                             codebook_size=codebook_size, num_quantizers=num_quantizers))
    model.set_statistics(torch.zeros(feature_dim), torch.full((feature_dim,), 0.1))
    model.save_pretrained(path, meta={"skeleton": skeleton, "fps": get_skeleton(skeleton).fps})
    return path


@pytest.fixture(scope="session", autouse=True)
def single_thread():
    """Tiny models run faster on one thread, and the suite's timing stays predictable."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


@pytest.fixture(scope="session")
def text_dataset(tmp_path_factory) -> dict[str, Path]:
    """{skeleton name: dataset root} for t2m and kit."""
    return {s: build_text_dataset(tmp_path_factory.mktemp(f"data-{s}"), s) for s in ("t2m", "kit")}


@pytest.fixture(scope="session")
def tokenizer_dir(tmp_path_factory) -> dict[str, Path]:
    """{skeleton name: exported tiny tokenizer directory}."""
    return {s: build_tokenizer(tmp_path_factory.mktemp(f"rvq-{s}"), get_skeleton(s).feature_dim,
                               skeleton=s) for s in ("t2m", "kit")}


@pytest.fixture
def hub_cache(tmp_path, monkeypatch) -> Path:
    """An empty Hugging Face cache, read offline."""
    import huggingface_hub.constants

    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_CACHE", str(tmp_path / "hub"))
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    return tmp_path / "hub"
