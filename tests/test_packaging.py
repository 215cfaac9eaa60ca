"""A non-editable install works without the source tree: the wheel holds every package,
the prompts and the configs, and `segmo segment-texts --backend openai`, installed from
it into a fresh virtual environment, finds its prompts."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest
from fake_openai import FakeOpenAI

from segmo.text.llm import load_prompt

REPO = Path(__file__).resolve().parents[1]
SOURCES = ("pyproject.toml", "README.md", "segmo", "prompts", "configs")  # what a build reads


def shipped(folder: str) -> set[str]:
    """The data files of a top-level folder, as the wheel must name them."""
    base = REPO / folder
    return {f"segmo/_{folder}/{p.relative_to(base).as_posix()}" for p in base.rglob("*")
            if p.is_file() and "__pycache__" not in p.parts}


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    """The wheel of a copy of the sources (a build writes build/ and *.egg-info beside them)."""
    tmp = tmp_path_factory.mktemp("wheel")
    source = tmp / "source"
    source.mkdir()
    for name in SOURCES:
        if (REPO / name).is_dir():
            shutil.copytree(REPO / name, source / name, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            shutil.copy2(REPO / name, source / name)
    subprocess.run([sys.executable, "-m", "pip", "wheel", str(source), "--no-deps",
                    "--no-build-isolation", "-q", "-w", str(tmp / "dist")], check=True,
                   capture_output=True)
    [built] = (tmp / "dist").glob("segmo-*.whl")
    return built


def test_pyproject_lists_every_package() -> None:
    tomllib = pytest.importorskip("tomllib")  # Python >= 3.11
    listed = set(tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    found = {".".join(p.parent.relative_to(REPO).parts) for p in (REPO / "segmo").rglob("__init__.py")}
    mapped = {f"segmo._configs.{p.name}" for p in (REPO / "configs").iterdir() if p.is_dir()
              and p.name != "__pycache__"}
    assert found | {"segmo._prompts", "segmo._configs"} | mapped == listed


def test_the_huggingface_hub_floor_has_the_modules_segmo_imports() -> None:
    """segmo.models.hub imports from huggingface_hub.errors, which came in 0.25; the floor
    said 0.23, and an install that pip judged valid crashed with ModuleNotFoundError."""
    tomllib = pytest.importorskip("tomllib")  # Python >= 3.11
    needs = {"huggingface_hub.errors": (0, 25)}  # module -> first huggingface_hub release with it
    deps = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["dependencies"]
    [spec] = [d for d in deps if d.startswith("huggingface_hub")]
    floor = tuple(int(part) for part in spec.split(">=")[1].split("."))
    code = "\n".join(p.read_text() for p in (REPO / "segmo").rglob("*.py"))
    for module, first in needs.items():
        if f"from {module} import" in code or f"import {module}" in code:
            assert floor >= first, f"pyproject.toml allows {spec}, but segmo imports {module}"


@pytest.mark.slow
def test_the_wheel_holds_the_code_prompts_and_configs(wheel: Path) -> None:
    names = set(zipfile.ZipFile(wheel).namelist())
    code = {p.relative_to(REPO).as_posix() for p in (REPO / "segmo").rglob("*.py")}
    assert code <= names
    assert shipped("prompts") <= names and "segmo/_prompts/segment_system.md" in names
    assert shipped("configs") <= names and "segmo/_configs/rvq/synthetic.yaml" in names


@pytest.mark.slow
def test_an_installed_copy_finds_its_prompts(wheel: Path, tmp_path: Path) -> None:
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    python = venv / "bin" / "python"
    # The dependencies (torch, ...) come from this interpreter's site-packages through a .pth
    # line; .pth files of that folder are not run, so an editable segmo there stays invisible.
    site = subprocess.run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                          check=True, capture_output=True, text=True).stdout.strip()
    Path(site, "dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    subprocess.run([sys.executable, "-m", "pip", "--python", str(python), "install", "-q", "--no-deps",
                    "--no-index", str(wheel)], check=True, capture_output=True)
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    where = subprocess.run([str(python), "-c", "import segmo.text.llm as m; print(m.PROMPT_DIR)"],
                           check=True, capture_output=True, text=True, cwd=tmp_path, env=env)
    assert Path(where.stdout.strip()).is_relative_to(venv)  # not the source tree's prompts/

    data = tmp_path / "data"
    (data / "texts").mkdir(parents=True)
    (data / "texts" / "000001.txt").write_text("a man walks forward then waves#x#0#0\n")
    with FakeOpenAI() as server:
        run = subprocess.run([str(venv / "bin" / "segmo"), "segment-texts", "--data", str(data),
                              "--backend", "openai", "--base-url", server.url, "--model", "tiny",
                              "--quiet"], capture_output=True, text=True, cwd=tmp_path, env=env)
    assert run.returncode == 0, run.stderr
    folder = data / "text_segments" / "openai-tiny"
    assert (folder / "000001.txt").read_text().strip() == "a man walks forward#a man waves"
    meta = json.loads((folder / "meta.json").read_text())
    assert meta["prompt_hash"] == load_prompt(REPO / "prompts").hash
