"""`segmo.files`: what a writer killed half-way leaves, and how the next one clears it."""

from __future__ import annotations

import subprocess
import sys

from segmo.files import pid_alive, replacing_folder


def _dead_pid() -> int:
    process = subprocess.Popen([sys.executable, "-c", "pass"])
    process.wait()
    assert not pid_alive(process.pid)
    return process.pid


def test_a_folder_replacement_killed_between_its_renames_is_put_back(tmp_path):
    """`segmo export`/`bundle` killed between the two renames left OUT missing and the
    user's model in OUT.old-<pid>-<n>; killed earlier, a half-written OUT.tmp-<pid>-<n>
    (6 MB) stayed for good."""
    pid = _dead_pid()
    out = tmp_path / "model"
    (tmp_path / f"model.old-{pid}-0").mkdir()  # the user's model, renamed away
    (tmp_path / f"model.old-{pid}-0" / "weights").write_text("theirs")
    (tmp_path / f"model.tmp-{pid}-1").mkdir()  # a killed writer's half-written folder
    (tmp_path / "model.old-photos").mkdir()  # the user's, named alike
    with replacing_folder(out) as tmp:
        assert (out / "weights").read_text() == "theirs"  # put back before the new write
        (tmp / "weights").write_text("new")
    assert (out / "weights").read_text() == "new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model", "model.old-photos"]


def test_a_leftover_of_a_writer_still_running_is_left_alone(tmp_path):
    import os

    busy = tmp_path / f"model.tmp-{os.getpid()}-99"
    busy.mkdir()
    with replacing_folder(tmp_path / "model") as tmp:
        (tmp / "weights").write_text("new")
    assert busy.is_dir()
