"""The README's main job, `segmo demo`, on its smoke budget: every step runs end to end."""

from __future__ import annotations

import pytest

from segmo.demo import main

pytestmark = pytest.mark.slow


def test_demo_quick_runs_every_step(tmp_path, capsys):
    out = tmp_path / "demo"
    main(["--out", str(out), "--budget", "quick"])
    printed = capsys.readouterr().out
    for step in range(1, 9):
        assert f"==> {step}/8" in printed
    assert (out / "model" / "segmo.json").is_file()
    assert len(list((out / "samples").glob("*.gif"))) == 4
    assert (out / "grounding.png").stat().st_size > 0
    # A second run resumes: nothing is trained again.
    main(["--out", str(out), "--budget", "quick"])
    assert capsys.readouterr().out.count("exists, skipped") == 4
