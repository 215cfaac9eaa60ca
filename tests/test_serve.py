"""`segmo serve` driven through its HTTP API (gradio_client) on a tiny random bundle:
a caption in, the segments, a GIF, a BVH, the joints and a grounding map out."""

from __future__ import annotations

import re
import socket
from pathlib import Path

import numpy as np
import pytest
from conftest import hash_encoder
from test_pipeline import TEXT_DIM, build_stages

from segmo.errors import SegmoError
from segmo.pipeline import SegMo

gr = pytest.importorskip("gradio", reason="gradio (the serve extra) is not installed")
gradio_client = pytest.importorskip("gradio_client")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def served(tmp_path_factory, tokenizer_dir):
    from segmo.serve import build_app

    root = tmp_path_factory.mktemp("serve")
    dirs = build_stages(root / "stages", tokenizer_dir["t2m"])
    model = SegMo.from_stages(dirs["tokenizer"], dirs["mask"], dirs["residual"], dirs["length"],
                              text_encoder=hash_encoder("hash", TEXT_DIM))
    app = build_app(model, root / "out")
    port = _free_port()
    app.launch(server_name="127.0.0.1", server_port=port, prevent_thread_lock=True, quiet=True)
    yield f"http://127.0.0.1:{port}/", model
    app.close()


def test_a_caption_in_a_motion_file_out(served, capfd):
    url, model = served
    client = gradio_client.Client(url, verbose=False)
    summary, gif, files, grounding = client.predict("a person walks forward, then waves", 2.4, 3,
                                                    4.0, "attention", api_name="/generate")
    assert "48 frames (2.4 s), 2 segment(s)" in summary and "walks forward" in summary
    paths = {Path(f if isinstance(f, str) else f["path"]).name: Path(f if isinstance(f, str) else f["path"])
             for f in files}
    bvh = paths["sample_00.bvh"].read_text()
    assert bvh.startswith("HIERARCHY") and "Frames: 142" in bvh  # 48 frames at 60 fps
    assert np.load(paths["sample_00_joints.npy"]).shape == (48, 22, 3)
    assert Path(gif).read_bytes()[:3] == b"GIF" and Path(grounding).read_bytes()[:4] == b"\x89PNG"
    # the same request gives the same motion; an empty caption is refused with its reason
    again = client.predict("a person walks forward, then waves", 2.4, 3, 4.0, "attention",
                           api_name="/generate")
    again_joints = [f if isinstance(f, str) else f["path"] for f in again[2] if str(f).endswith(".npy") or
                    (isinstance(f, dict) and f["path"].endswith(".npy"))][0]
    assert np.array_equal(np.load(again_joints), np.load(paths["sample_00_joints.npy"]))
    capfd.readouterr()
    with pytest.raises(Exception, match="type a caption first"):
        client.predict("   ", 2.4, 0, 4.0, "similarity", api_name="/generate")
    # the server's log says why in one line, without Gradio's 30-line traceback
    err = capfd.readouterr().err
    assert "segmo serve: refused a request: type a caption first" in err and "Traceback" not in err
    # The seed widget rounded 2.7 to 3 before generate_files could refuse it.
    with pytest.raises(Exception, match="seed must be a whole number"):
        client.predict("a person walks forward, then waves", 2.4, 2.7, 4.0, "attention",
                       api_name="/generate")


def test_segment_durations_through_the_api(served, tmp_path, tokenizer_dir):
    """The page's durations reach a segment-timing bundle ("1,4" = "2, 8": shares); on a
    bundle without timing, or written wrong, they are refused with the reason; a call that
    leaves them out (the former five inputs) still works."""
    from segmo.serve import generate_files

    url, _ = served
    client = gradio_client.Client(url, verbose=False)
    caption = "a person walks forward, then waves"
    with pytest.raises(Exception, match="durations need a mask transformer trained with segment timing"):
        client.predict(caption, 2.4, 3, 4.0, "attention", "1,4", api_name="/generate")
    with pytest.raises(Exception, match="segment durations '1,x': expected numbers >= 0"):
        client.predict(caption, 2.4, 3, 4.0, "attention", "1,x", api_name="/generate")
    assert "48 frames" in client.predict(caption, 2.4, 3, 4.0, "attention", "",
                                         api_name="/generate")[0]

    dirs = build_stages(tmp_path / "stages", tokenizer_dir["t2m"], segment_timing=True)
    timed = SegMo.from_stages(dirs["tokenizer"], dirs["mask"], dirs["residual"],
                              text_encoder=hash_encoder("hash", TEXT_DIM))

    def joints(durations: str, name: str) -> np.ndarray:
        found = generate_files(timed, caption, 2.4, 3, 4.0, "similarity", tmp_path / name, durations)
        return np.load(found["joints"])

    short_first = joints("1,4", "a")
    assert np.array_equal(short_first, joints(" 2, 8", "b"))
    assert not np.array_equal(short_first, joints("4,1", "c"))
    with pytest.raises(SegmoError, match=r"durations\[0\] has 3 values, text 0 has 2 segments"):
        joints("1,1,1", "d")


def test_a_request_out_of_range_names_its_field(served, tmp_path):
    """What a client may send besides the page's widgets: each refused with the field it
    names (the page shows it), before any generation."""
    from segmo.serve import MAX_CAPTION_CHARACTERS, generate_files

    _, model = served
    caption = "a person walks forward"
    for args, message in (
            ((["a"], 2.4, 0, 4.0), "caption must be text, got list"),
            ((caption, float("nan"), 0, 4.0), "length must be a finite number, got nan"),
            ((caption, 2.4, 1e30, 4.0), r"seed must be a whole number from 0 to 2\^63 - 1"),
            ((caption, 2.4, 2.5, 4.0), r"seed must be a whole number"),
            ((caption, 2.4, 0, float("inf")), "guidance must be a finite number, got inf"),
            ((caption, 12.0, 0, 4.0), r"a length of 12 s is longer than the model's 9.8 s \(196 "
                                      r"frames at 20 fps\)"),  # was cut to 9.8 s
            (("walk " * MAX_CAPTION_CHARACTERS, 2.4, 0, 4.0), "characters; at most 2,000"),
            # it failed after the generation: "3 segments in order need 6 tokens"
            (("a person walks, then jumps, then sits, then waves, then kicks", 0.6, 0, 4.0),
             r"a length of 0.6 s is too short for the caption's 3 segments; give at least 1.2 s")):
        with pytest.raises(SegmoError, match=message):
            generate_files(model, *args, "similarity", tmp_path / "out")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("fps, max_frames, longest", [(20.0, 196, "9.8"), (12.5, 196, "15.68"),
                                                     (20.0, 120, "6")])
def test_the_longest_request_is_the_models(fps, max_frames, longest, tmp_path):
    """The page's limit was 9.8 s whatever the model (196 frames at 20 fps): a KIT bundle
    (12.5 fps, 15.68 s) was cut to 9.8 s, and a request beyond the limit was clamped to it
    without a word. The slider now ends at the model's longest motion; a longer request is
    refused."""
    from types import SimpleNamespace

    from segmo.serve import build_app, generate_files

    asked = []

    class Model:  # what generate_files and build_app read of a SegMo
        config = SimpleNamespace(guidance_scale=4.0)

        def segment_texts(self, texts):
            return [["a person walks"]]

        def generate(self, texts, lengths, **kwargs):
            asked.append(lengths)
            raise SegmoError("stop here")

    model = Model()
    model.fps, model.max_frames = fps, max_frames
    with pytest.raises(SegmoError, match="stop here"):  # the longest is taken as it is
        generate_files(model, "a person walks", float(longest), 0, 4.0, "similarity", tmp_path)
    assert asked == [[max_frames]]
    with pytest.raises(SegmoError, match=re.escape(
            f"a length of {float(longest) + 0.2:g} s is longer than the model's {longest} s "
            f"({max_frames} frames at {fps:g} fps)")):
        generate_files(model, "a person walks", float(longest) + 0.2, 0, 4.0, "similarity", tmp_path)
    assert len(asked) == 1
    [slider] = [block for block in build_app(model, tmp_path / "work").blocks.values()
                if isinstance(block, gr.Slider) and block.label.startswith("length (s)")]
    assert slider.maximum == pytest.approx(max_frames / fps)


def test_serve_refuses_a_port_beyond_65535_before_loading(tmp_path, capsys):
    from conftest import cli_failure

    line = cli_failure(["serve", "--model", str(tmp_path / "nope"), "--port", "70000"], capsys)
    assert line == ("segmo serve: argument --port: expected a TCP port from 1 to 65535, got "
                    "'70000' (see `segmo serve --help`)")


def test_old_request_folders_are_pruned_and_other_entries_stay(tmp_path):
    from segmo.serve import prune_requests

    for i in range(6):
        (tmp_path / f"{i:06d}").mkdir()
        (tmp_path / f"{i:06d}" / "sample_00.gif").write_bytes(b"GIF")
    (tmp_path / "notes").mkdir()
    (tmp_path / "²").mkdir()  # a digit to str.isdigit(), not a request folder
    prune_requests(tmp_path, 2)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["000004", "000005", "notes", "²"]
    prune_requests(tmp_path / "missing", 2)  # nothing served yet: nothing to do


def test_a_work_folder_of_the_users_loses_nothing_to_pruning(tmp_path, monkeypatch):
    """`build_app(model, workdir)` pruned every all-digit folder of the work folder, sorted as
    text: a user's own folders 001..006 were deleted; and a reused work folder restarted
    at 000000, writing into an earlier server's request folders. Requests now go to a
    folder of the app's own, and only its folders are pruned, oldest first."""
    from types import SimpleNamespace

    from segmo import serve

    work = tmp_path / "work"
    mine = [work / f"{i:03d}" for i in range(1, 7)] + [work / "000000"]  # 000000: an earlier
    for folder in mine:                                                    # server's request
        folder.mkdir(parents=True)
        (folder / "notes.txt").write_text("mine")
    made = []

    def generate_files(model, caption, seconds, seed, guidance, method, out, durations=""):
        out.mkdir(parents=True, exist_ok=True)
        made.append(out)
        return {"segments": ["walk"], "spans": [(0, 40)], "frames": 40,
                **{key: out / key for key in ("gif", "bvh", "joints", "map")}}

    monkeypatch.setattr(serve, "generate_files", generate_files)
    monkeypatch.setattr(serve, "KEEP_REQUESTS", 2)
    model = SimpleNamespace(fps=20.0, max_frames=196, config=SimpleNamespace(guidance_scale=4.0))
    for _ in range(2):  # a second app in the same work folder: a server restarted
        app = serve.build_app(model, work)
        [run] = [f.fn for f in app.fns.values() if f.api_name == "generate"]
        for _ in range(4):
            run("a person walks", 2.0, 0, 4.0, "attention", "")
    assert all((folder / "notes.txt").read_text() == "mine" for folder in mine)
    assert len(set(made)) == 8 and not set(made) & set(mine) and all(p.parent != work for p in made)
    # each app keeps its newest requests: pruned before each new one, down to 2
    assert [p.exists() for p in made] == [False, True, True, True] * 2


def test_sigterm_stops_the_server_and_removes_its_work_folder(tmp_path, monkeypatch):
    """`docker stop` sends SIGTERM, which ended Python on the spot: the server's /tmp work
    folder, with every request's GIF and BVH, stayed behind (Ctrl-C removed it)."""
    import os
    import signal
    import time

    from segmo import serve

    folders, closed = [], []

    class App:  # stands in for the Gradio app: launch blocks until a signal
        def launch(self, **kwargs):
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(10)  # the handler runs here

        def close(self):
            closed.append(True)

    monkeypatch.setattr(serve, "build_app", lambda model, workdir: folders.append(Path(workdir)) or App())
    monkeypatch.setattr(SegMo, "from_pretrained", classmethod(lambda cls, name: object()))

    def unhandled(signum, frame):  # what would end the test run, were serve not to catch it
        raise AssertionError("SIGTERM reached the handler serve found")

    previous = signal.signal(signal.SIGTERM, unhandled)
    try:
        with pytest.raises(SystemExit) as stopped:
            serve.main(["--model", str(tmp_path)])
        assert signal.getsignal(signal.SIGTERM) is unhandled  # serve's handler is not left behind
    finally:
        signal.signal(signal.SIGTERM, previous)
    assert stopped.value.code == 128 + signal.SIGTERM
    assert folders and not folders[0].exists() and closed
