"""`segmo segment-texts --backend openai` against a faulty server: the run survives, each
fallback is recorded on disk, the exit status follows --max-fallback-share, and a rerun
asks again exactly the captions that fell back."""

from __future__ import annotations

import json

import pytest
from fake_openai import RETRY_AFTER, FakeOpenAI

from segmo.cli import main as segmo_main
from segmo.text.manifest import SegmentManifest
from segmo.text.rules import RuleSegmenter

# caption -> fault (see fake_openai.FakeOpenAI); one file per fault, plus clean files
FAULTS = {
    "a person waves then bows": "500",
    "a person jumps then sits down": "429-once",  # succeeds after the Retry-After wait
    "a person crawls then stands up": "hang",
    "a person claps then kicks": "badjson",
    "a person spins then falls down": "invalidjson",
    "a person kneels then prays": "prose",
    "a person walks then turns around": "itisit",
    "a person hops then runs": "copies",
    "a person sits down then waves": "dropped",
    "a person runs after walking": "reversed",
}
CLEAN = ["a man walks forward, then waves twice", "a woman kicks then punches", "a man claps"]
FELL_BACK = {c for c, f in FAULTS.items() if not f.endswith("-once")}


@pytest.fixture
def root(tmp_path):
    root = tmp_path / "data"
    (root / "texts").mkdir(parents=True)
    for k, caption in enumerate([*FAULTS, *CLEAN]):
        # every fault file has a clean caption too, so a retry must ask only the faulty line
        (root / "texts" / f"{k:06d}.txt").write_text(f"{caption}#x#0#0\na man claps {k} times#x#0#0\n")
    return root


def _run(root, url, *extra):
    argv = ["segment-texts", "--data", str(root), "--backend", "openai", "--base-url", url,
            "--model", "tiny", "--timeout", "1", "--max-retries", "1", "--concurrency", "4", "--quiet"]
    try:
        segmo_main([*argv, *extra])
    except SystemExit as exit_:
        return exit_.code
    return 0


def test_faults_are_recorded_and_the_run_fails_after_writing_everything(root, capsys):
    with FakeOpenAI(FAULTS) as server:
        assert _run(root, server.url) == 2
    out, err = capsys.readouterr()
    assert "Traceback" not in err
    folder = root / "text_segments" / "openai-tiny"
    manifest = SegmentManifest(folder)
    assert err.strip().splitlines()[-1] == (
        f"segmo segment-texts: {len(FELL_BACK)} of 26 captions (34.6%) hold rule fallbacks because "
        "the LLM failed (allowed: 0%, --max-fallback-share 0); each is recorded with its reason "
        f'under "fallbacks" in {manifest.path}; re-run to retry them')
    assert f"fallbacks {len(FELL_BACK)} this run, {len(FELL_BACK)} in the folder" in out  # summary printed
    assert len(list(folder.glob("0*.txt"))) == len(FAULTS) + len(CLEAN)  # everything written
    for k, caption in enumerate([*FAULTS, *CLEAN]):
        record = manifest.get(f"{k:06d}")
        lines = (folder / f"{k:06d}.txt").read_text().splitlines()
        assert lines[0] == "#".join(RuleSegmenter().segment_one(caption))
        if caption in FELL_BACK:
            [fallback] = record["fallbacks"]
            assert (fallback["line"], fallback["index"]) == (1, 0) and fallback["reason"]
        else:
            assert record["fallbacks"] == []
    reasons = {c: manifest.get(f"{k:06d}")["fallbacks"][0]["reason"]
               for k, c in enumerate(FAULTS) if c in FELL_BACK}
    assert "HTTP 500" in reasons["a person waves then bows"]
    assert "no answer within 1 s" in reasons["a person crawls then stands up"]
    assert "unreadable response" in reasons["a person claps then kicks"]
    assert "out of execution order" in reasons["a person runs after walking"]
    assert "repeated 5 times" in reasons["a person hops then runs"]
    first, second = server.times["a person jumps then sits down"][:2]
    assert second - first >= RETRY_AFTER
    summary = json.loads((folder / "summary.json").read_text())
    assert summary["fallback_captions"] == len(FELL_BACK) and summary["captions"] == 26


def test_a_share_within_the_limit_exits_0(root):
    with FakeOpenAI(FAULTS) as server:
        assert _run(root, server.url, "--max-fallback-share", "0.4") == 0


def test_a_rerun_retries_only_the_captions_that_fell_back(root, capsys):
    with FakeOpenAI(FAULTS) as server:
        assert _run(root, server.url) == 2
    capsys.readouterr()
    folder = root / "text_segments" / "openai-tiny"
    before = {p.name: p.read_text() for p in folder.glob("0*.txt")}
    with FakeOpenAI() as healed:  # the server is fixed
        assert _run(root, healed.url) == 0
    out, _ = capsys.readouterr()
    assert set(healed.calls) == FELL_BACK and all(n == 1 for n in healed.calls.values())
    assert f"processed {len(FELL_BACK)} files, skipped {len(FAULTS) + len(CLEAN) - len(FELL_BACK)}" in out
    assert "fallbacks 0 this run, 0 in the folder" in out
    manifest = SegmentManifest(folder)
    assert all(not r["fallbacks"] for r in manifest.records.values())
    assert {p.name: p.read_text() for p in folder.glob("0*.txt")} == before  # same split, now the LLM's
    with FakeOpenAI() as idle:
        assert _run(root, idle.url) == 0
    assert idle.total == 0  # nothing left to ask


def test_a_dead_server_stops_the_run_with_one_line(root, capsys):
    with FakeOpenAI() as server:
        url = server.url  # nothing listens there after the block
    assert _run(root, url, "--max-retries", "0") == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert err.strip().splitlines()[-1].startswith(f"segmo segment-texts: {url}: ")
    assert "requests in a row failed (last: cannot reach" in err and "re-run when the server answers" in err


def test_ctrl_c_ends_a_run_whose_requests_are_in_flight(root):
    """An interrupted run waited for every request in flight (42 s with --timeout 10 and
    three retries; for ever with a server that trickles its answer), as Python joins the
    request threads at exit."""
    import os
    import signal
    import subprocess
    import sys
    import time

    captions = [line.split("#")[0] for f in sorted((root / "texts").iterdir())
                for line in f.read_text().splitlines()]
    with FakeOpenAI({c: "stall" for c in captions}) as server:
        process = subprocess.Popen(
            [sys.executable, "-m", "segmo", "segment-texts", "--data", str(root), "--backend",
             "openai", "--base-url", server.url, "--model", "tiny", "--timeout", "30", "--quiet"],
            stderr=subprocess.PIPE, text=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
        deadline = time.monotonic() + 60
        while server.total < 2 and time.monotonic() < deadline:  # requests in flight
            time.sleep(0.1)
        process.send_signal(signal.SIGINT)
        sent = time.monotonic()
        try:
            err = process.communicate(timeout=20)[1]
        finally:
            process.kill()
    assert process.returncode == 130 and "interrupted" in err, err
    assert time.monotonic() - sent < 15
