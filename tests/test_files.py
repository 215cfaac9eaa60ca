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


def test_a_killed_writers_temporary_is_removed_by_the_next_writer_of_the_file(tmp_path):
    """`segmo render --out r/out.gif` killed while writing left r/.out.gif.<pid>.0.tmp for
    good; one of a live writer, and other files' temporaries, stay."""
    import os

    from segmo.files import remove_stale_temporaries

    dead, live = _dead_pid(), os.getpid()
    stale = tmp_path / f".out.gif.{dead}.0.tmp"
    busy = tmp_path / f".out.gif.{live}.3.tmp"
    other = tmp_path / f".other.gif.{dead}.0.tmp"
    for path in (stale, busy, other):
        path.write_bytes(b"GIF")
    remove_stale_temporaries(tmp_path / "out.gif")
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([busy.name, other.name])


def test_the_current_folder_and_those_above_it_are_never_replaced(tmp_path, monkeypatch):
    """`export(ckpt, "")` (an unset `$OUT`) replaced everything in the current folder by
    the model; a folder above it went the same way with `..`."""
    import pytest

    from segmo.errors import SegmoError
    from segmo.synth import build_corpus

    here = tmp_path / "work"
    here.mkdir()
    (here / "notes.txt").write_text("mine")
    monkeypatch.chdir(here)
    for folder, says in (("", "is the current folder"), (".", "is the current folder"),
                         ("..", "holds the current folder"), ("/", "holds the current folder")):
        with pytest.raises(SegmoError, match=says):
            with replacing_folder(folder):
                pass
    with pytest.raises(SegmoError, match="is the current folder"):
        build_corpus("", 3, overwrite=True, progress=False)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["work"]
    assert [p.name for p in here.iterdir()] == ["notes.txt"]
