"""The README's main job, `segmo demo`: every step end to end on a tiny corpus, with a
wall-clock budget whose step caps end each stage first, then resumed with the smoke budget."""

from __future__ import annotations

import argparse
import json

import pytest

from segmo.demo import QUICK, Budget, main, parse_budget, run
from segmo.errors import SegmoError

pytestmark = pytest.mark.slow


def test_demo_runs_every_step_on_a_time_budget_and_resumes(tmp_path, capsys):
    out = tmp_path / "demo"
    run(out, Budget(num_motions=24, rvq_steps=2, mask_steps=2, residual_steps=2, length_epochs=1,
                    seconds=900))
    printed = capsys.readouterr().out
    for step in range(1, 9):
        assert f"==> {step}/8" in printed
    # every stage got its share of the time left (the tokenizer 30 % of 15 minutes less the
    # reserves), stopped at its step cap first, and left the unused time to the next stages
    limits = [int(line.split()[-2]) for line in printed.splitlines() if "training for at most" in line]
    assert len(limits) == 4 and abs(limits[0] - 0.30 * (900 - 45 - 4 * 15)) < 10
    assert limits == sorted(limits) and limits[-1] < 900
    assert printed.count("trained 2 steps") == 3
    assert (out / "model" / "segmo.json").is_file()
    bundle = json.loads((out / "model" / "segmo.json").read_text())
    # the measured defaults of the built-in corpus
    assert (bundle["steps"], bundle["residual_guided_layers"], bundle["guidance_scale"]) == (4, 2, 2.0)
    assert len(list((out / "samples").glob("*.gif"))) == 4
    assert (out / "grounding.png").stat().st_size > 0
    # A second run resumes: nothing is trained again.
    main(["--out", str(out), "--budget", "quick"])
    assert capsys.readouterr().out.count("exists, skipped") == 4
    # Another seed or size would be ignored (stages skipped) or rebuild the corpus under
    # the trained models: refused, and nothing changes.
    before = (out / "corpus" / "corpus.json").read_bytes()
    for seed, budget in ((1, QUICK), (0, Budget(num_motions=30, rvq_steps=2, mask_steps=2,
                                                 residual_steps=2, length_epochs=1))):
        with pytest.raises(SegmoError, match="seed 0, 24 motions; this one asks for"):
            run(out, budget, seed)
    assert (out / "corpus" / "corpus.json").read_bytes() == before


def test_parse_budget():
    assert parse_budget("quick") is QUICK
    assert parse_budget("20m").seconds == 1200 and parse_budget("1h30m").seconds == 5400
    assert parse_budget("150").seconds == 150 and parse_budget("2m30s").seconds == 150
    for bad in ("huge", "", "20 minutes", "-5m", "30s"):
        with pytest.raises(argparse.ArgumentTypeError):
            parse_budget(bad)
