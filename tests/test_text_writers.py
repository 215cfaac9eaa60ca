"""The text writers as separate processes: kill -9 and resume, two writers at once, and a
lock left by a killed writer. `segment-texts` talks to a fake OpenAI-compatible server in
a thread of this test (tests/fake_openai.py); `encode-texts` runs with a deterministic hash
encoder through a small driver script, so that the kill can be timed exactly."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from fake_openai import FakeOpenAI

TESTS = Path(__file__).resolve().parent
TEXTS = {  # 8 files, 12 captions, several actions each (so the LLM answers are split)
    "000001": ["a person walks forward, then waves twice.", "someone jumps after walking"],
    "000002": ["before sitting down, a man waves"],
    "000003": ["a person stands and waves", "a man runs then stops then bows"],
    "000004": ["a man runs after walking", "a person crawls then stands up then jumps"],
    "000005": ["a woman kicks then punches"],
    "000006": ["a person turns around and walks back"],
    "000007": ["a man claps three times then sits down"],
    "000008": ["the figure hops forward then spins"],
}
ENV = {**os.environ, "NO_PROXY": "127.0.0.1,localhost", "PYTHONUNBUFFERED": "1"}


def _dataset(root: Path) -> Path:
    (root / "texts").mkdir(parents=True)
    for mid, captions in TEXTS.items():
        (root / "texts" / f"{mid}.txt").write_text("".join(f"{c}#x#0.0#0.0\n" for c in captions))
    return root


def _files(folder: Path, skip: tuple[str, ...] = ()) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir()) if p.is_file() and p.name not in skip}


def _segment_command(root: Path, url: str, *extra: str) -> list[str]:
    return [sys.executable, "-m", "segmo", "segment-texts", "--data", str(root), "--backend", "openai",
            "--base-url", url, "--model", "tiny", "--concurrency", "1", "--batch-captions", "1",
            "--timeout", "10", "--quiet", *extra]


def _wait(proc: subprocess.Popen, timeout: float = 120) -> tuple[int, str, str]:
    out, err = proc.communicate(timeout=timeout)
    return proc.returncode, out, err


def _kill(proc: subprocess.Popen) -> None:
    os.kill(proc.pid, signal.SIGKILL)
    proc.communicate(timeout=30)
    assert proc.returncode == -signal.SIGKILL


# ---------------------------------------------------------------- segment-texts
@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory) -> dict[str, bytes]:
    """The files of an uninterrupted LLM run over TEXTS."""
    root = _dataset(tmp_path_factory.mktemp("whole") / "data")
    with FakeOpenAI() as server:
        done = subprocess.run(_segment_command(root, server.url), env=ENV, capture_output=True,
                              text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    folder = root / "text_segments" / "openai-tiny"
    assert len(list(folder.glob("0*.txt"))) == len(TEXTS)
    return _files(folder, skip=("summary.json",))


@pytest.mark.parametrize("kill_at", [3, 7])  # after 000001; inside 000004 (2 captions)
def test_kill_9_during_segment_texts_then_resume(tmp_path, uninterrupted, kill_at):
    root = _dataset(tmp_path / "data")
    folder = root / "text_segments" / "openai-tiny"
    with FakeOpenAI(block_at=kill_at) as server:
        proc = subprocess.Popen(_segment_command(root, server.url), env=ENV, stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True)
        assert server.blocked.wait(60), "the run never reached the blocked request"
        _kill(proc)  # mid-request: the files of the captions before it are written
        written = len(list(folder.glob("0*.txt")))
        assert 0 < written < len(TEXTS)
        server.block_at = None
        server.release.set()
        done = subprocess.run(_segment_command(root, server.url), env=ENV, capture_output=True,
                              text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert f"skipped {written}" in done.stdout
    assert _files(folder, skip=("summary.json",)) == uninterrupted
    assert not list(folder.glob(".*.tmp"))


def test_two_segment_texts_at_once_one_clear_error_nothing_lost(tmp_path, uninterrupted):
    root = _dataset(tmp_path / "data")
    with FakeOpenAI(block_at=3) as server:
        first = subprocess.Popen(_segment_command(root, server.url), env=ENV, stdout=subprocess.PIPE,
                                 stderr=subprocess.PIPE, text=True)
        assert server.blocked.wait(60)  # the first writer is mid-run, holding the lock
        for second in (_segment_command(root, server.url),
                       [sys.executable, "-m", "segmo", "encode-texts", "--data", str(root)]):
            done = subprocess.run(second, env=ENV, capture_output=True, text=True, timeout=120)
            assert done.returncode == 2
            lines = done.stderr.strip().splitlines()
            assert len(lines) == 1 and "Traceback" not in done.stderr
            assert f"is being written by PID {first.pid} (segmo segment-texts, since" in lines[0]
        server.block_at = None
        server.release.set()
        code, out, err = _wait(first)
    assert code == 0, err
    assert _files(root / "text_segments" / "openai-tiny", skip=("summary.json",)) == uninterrupted


def test_a_lock_left_by_a_killed_writer_is_recovered(tmp_path, uninterrupted):
    root = _dataset(tmp_path / "data")
    with FakeOpenAI(block_at=1) as server:
        proc = subprocess.Popen(_segment_command(root, server.url), env=ENV, stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True)
        assert server.blocked.wait(60)
        _kill(proc)
        assert f'"pid": {proc.pid}' in (root / ".segmo-writer.lock").read_text()  # its note stays
        server.block_at = None
        server.release.set()
        done = subprocess.run(_segment_command(root, server.url), env=ENV, capture_output=True,
                              text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert _files(root / "text_segments" / "openai-tiny", skip=("summary.json",)) == uninterrupted


# ---------------------------------------------------------------- encode-texts
DRIVER = """
import sys, time
sys.path.insert(0, {tests!r})
from conftest import hash_encoder
import segmo.text.cache as cache

stop = sys.argv[1]  # "encode:K" or "publish:K": block in the K-th shard's encoding / index write
kind, k = stop.split(":")[0], int(stop.split(":")[1] or 0)
encoder = hash_encoder("hash", 16)
calls = {{"encode": 0, "publish": 0}}
encode, write_json = encoder.encode, cache._write_json


def block(what):
    calls[what] += 1
    if kind == what and calls[what] == k:
        print("BLOCKED", flush=True)
        time.sleep(600)


def slow_encode(texts, batch_size=64):
    block("encode")
    return encode(texts, batch_size)


def publish(path, obj):
    if path.name == "index.json" and obj["shards"]:
        block("publish")
    write_json(path, obj)


encoder.encode, cache._write_json = slow_encode, publish
cache.get_text_encoder = lambda name, device="cpu": encoder
from segmo.cli import main
main(["encode-texts", "--data", sys.argv[2], "--encoder", "hash", "--shard-size", "4", "--quiet"])
"""


def _encode(driver: Path, root: Path, stop: str = "none:0", **kwargs) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, str(driver), stop, str(root)], env=ENV,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kwargs)


@pytest.fixture(scope="module")
def encode_setup(tmp_path_factory, uninterrupted):
    base = tmp_path_factory.mktemp("encode")
    driver = base / "driver.py"
    driver.write_text(DRIVER.format(tests=str(TESTS)))
    root = _dataset(base / "template")
    segments = root / "text_segments" / "openai-tiny"
    segments.mkdir(parents=True)
    for name, data in uninterrupted.items():
        (segments / name).write_bytes(data)
    whole = base / "whole"
    shutil.copytree(root, whole)
    code, out, err = _wait(_encode(driver, whole))
    assert code == 0, err
    files = _files(whole / "text_features" / "hash")
    assert len([f for f in files if f.endswith(".sentence.npy")]) >= 4  # several shards
    return driver, root, files


@pytest.mark.parametrize("stop", ["encode:3", "publish:2"])
def test_kill_9_during_encode_texts_then_resume(tmp_path, encode_setup, stop):
    driver, template, expected = encode_setup
    root = tmp_path / "data"
    shutil.copytree(template, root)
    proc = _encode(driver, root, stop)
    assert proc.stdout.readline().strip() == "BLOCKED"
    _kill(proc)
    cache = root / "text_features" / "hash"
    committed = json.loads((cache / "index.json").read_text())["shards"]
    assert len(committed) == int(stop[-1]) - 1  # the shards before the kill, and no more
    if stop.startswith("publish"):  # the killed shard's arrays were written, never published
        assert (cache / f"shard-{len(committed):05d}.sentence.npy").is_file()
    code, out, err = _wait(_encode(driver, root))
    assert code == 0, err
    assert _files(root / "text_features" / "hash") == expected  # byte for byte


def test_two_encode_texts_at_once_one_clear_error_nothing_lost(tmp_path, encode_setup):
    driver, template, expected = encode_setup
    root = tmp_path / "data"
    shutil.copytree(template, root)
    first = _encode(driver, root, "encode:2")
    assert first.stdout.readline().strip() == "BLOCKED"
    try:
        code, out, err = _wait(_encode(driver, root))
        assert code == 2 and "Traceback" not in err
        lines = err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith(
            f"segmo encode-texts: {root} is being written by PID {first.pid} (segmo encode-texts, since ")
    finally:
        _kill(first)
    start = time.perf_counter()
    code, out, err = _wait(_encode(driver, root))  # the killed writer's lock is gone with it
    assert code == 0 and time.perf_counter() - start < 60, err
    assert _files(root / "text_features" / "hash") == expected


def test_the_library_functions_take_the_lock_too(tmp_path):
    """Notebook users call segment_folder / update_cache directly: they must stop as well."""
    from conftest import hash_encoder

    from segmo.errors import FolderBusyError
    from segmo.text.cache import update_cache
    from segmo.text.extract import segment_folder
    from segmo.text.rules import RuleSegmenter

    root = _dataset(tmp_path / "data")
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys, time; from segmo.files import FolderLock; "
         "FolderLock(sys.argv[1], 'segmo synth').acquire(); print('HELD', flush=True); time.sleep(600)",
         str(root)], env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "HELD"
        for write in (lambda: segment_folder(root, RuleSegmenter(), progress=False),
                      lambda: update_cache(root, hash_encoder("hash", 8), progress=False)):
            with pytest.raises(FolderBusyError, match=rf"is being written by PID {holder.pid} \(segmo synth"):
                write()
        assert not (root / "text_segments").exists() and not (root / "text_features").exists()
    finally:
        _kill(holder)
    segment_folder(root, RuleSegmenter(), progress=False)  # free again once the holder is gone
