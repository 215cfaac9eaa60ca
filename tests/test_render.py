"""Tests of segmo.render: GIF animation, key-frame figures and the `segmo render` CLI."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import numpy as np
import pytest
from conftest import cli_failure
from PIL import Image

from segmo.errors import SegmoError
from segmo.motion import T2M
from segmo.render import as_joints, ffmpeg_executable, main, plot_motion, save_animation

FIXTURES = Path(__file__).resolve().parents[1].parent / "shared" / "fixtures" / "humanml3d"


def _fixture(name: str) -> np.ndarray:
    path = FIXTURES / name
    if not path.exists():
        pytest.skip(f"HumanML3D fixture {path} not found (needs the shared fixtures folder)")
    return np.load(path)


def _frames(path: Path) -> int:
    with Image.open(path) as image:
        assert image.format == "GIF"
        return image.n_frames


def test_gif_from_fixture_joints(tmp_path):
    joints = _fixture("012314_joints.npy")
    out = save_animation(joints, tmp_path / "walk.gif", title="a person walks " * 8, stride=10)
    assert out.exists() and _frames(out) > 5
    with Image.open(out) as image:
        assert image.info["duration"] == 500  # 20 fps / stride 10 -> 2 fps


def test_a_gif_faster_than_50_fps_or_longer_than_its_frame_limit_draws_every_kth_frame(
        tmp_path, monkeypatch):
    """A 60 fps GIF got 1-hundredth delays, which browsers play as 10 (6 times too slowly);
    1e9 fps wrote a delay of 0; every frame of any length was held in memory."""
    import segmo.render as render

    joints = as_joints(np.zeros((24, 263)))
    with pytest.warns(UserWarning, match="one frame in 2 is drawn"):
        out = save_animation(joints, tmp_path / "fast.gif", fps=60)
    with Image.open(out) as image:
        assert image.info["duration"] == 30 and image.n_frames == 12  # 30 fps, on time
    monkeypatch.setattr(render, "GIF_MAX_FRAMES", 5)
    with pytest.warns(UserWarning, match="one frame in 5 is drawn"):
        out = save_animation(joints, tmp_path / "long.gif")
    with Image.open(out) as image:
        assert image.info["duration"] == 250 and image.n_frames == 5  # 20 fps / 5, on time


def test_gif_from_random_zscored_features(tmp_path):
    g = np.random.default_rng(0)
    mean, std = g.normal(size=263), np.abs(g.normal(size=263)) * 0.1 + 0.01
    features = g.normal(size=(12, 263)).astype(np.float32)
    out = save_animation(features, tmp_path / "random.gif", mean=mean, std=std)
    assert _frames(out) > 1
    joints = as_joints(features, "t2m", mean, std)
    assert joints.shape == (12, 22, 3) and np.isfinite(joints).all()


def test_plot_motion_key_frames():
    joints = as_joints(np.zeros((5, 263)))  # a still pose at the origin
    fig = plot_motion(joints, title="still", frames=3)
    assert len(fig.axes) == 3 and fig.axes[1].get_title() == "frame 2"
    assert len(plot_motion(joints, frames=[4]).axes) == 1
    with pytest.raises(ValueError, match="out of range"):
        plot_motion(joints, frames=[7])


def test_input_errors(tmp_path, monkeypatch):
    with pytest.raises(ValueError, match=r"expected joints \(t, 22, 3\) or features \(t, 263\)"):
        as_joints(np.zeros((10, 100)))
    with pytest.raises(ValueError, match="unsupported output"):
        save_animation(np.zeros((3, 22, 3)), tmp_path / "x.avi")
    monkeypatch.setattr("segmo.render.ffmpeg_executable", lambda: None)
    with pytest.raises(ValueError, match="ffmpeg"):
        save_animation(np.zeros((3, 22, 3)), tmp_path / "x.mp4")


def test_cli(tmp_path, capsys):
    features = np.zeros((6, T2M.feature_dim), dtype=np.float32)
    features[:, 3] = 0.9  # root height
    np.save(tmp_path / "m.npy", features)
    main([str(tmp_path / "m.npy"), "--out", str(tmp_path / "m.gif"), "--title", "still", "--fps", "10"])
    assert _frames(tmp_path / "m.gif") >= 1 and "wrote" in capsys.readouterr().out
    line = cli_failure(["render", str(tmp_path / "missing.npy"), "--out", str(tmp_path / "x.gif")],
                       capsys)
    assert "missing.npy" in line and "no such file" in line
    np.save(tmp_path / "bad.npy", np.zeros((6, 7)))
    line = cli_failure(["render", str(tmp_path / "bad.npy"), "--out", str(tmp_path / "x.gif")],
                       capsys)
    assert "bad.npy" in line and "got shape (6, 7)" in line
    assert not (tmp_path / "x.gif").exists() and not list(tmp_path.glob(".*.tmp"))


def test_long_titles_are_cut_to_three_lines():
    from segmo.render import _wrap

    assert _wrap("walk " * 10_000, 40).count("\n") == 2


def test_gif_counts_frames_and_names_the_segment_of_each_frame(tmp_path):
    """A figure standing still: only the footer (frame/time counter, active segment) may
    change between frames, and it must change where the segment does."""
    still = np.repeat(as_joints(np.zeros((1, 263), np.float32)), 8, axis=0)
    out = save_animation(still, tmp_path / "still.gif", segments=[("walks", 0, 4), ("waves", 4, 8)])
    with Image.open(out) as image:
        frames = []
        for k in range(image.n_frames):
            image.seek(k)
            frames.append(np.asarray(image.convert("L"), dtype=np.int16))
    footer = int(0.45 / (4.0 + 0.45) * frames[0].shape[0]) + 2  # the strip under the figure
    top = slice(0, frames[0].shape[0] - footer)
    assert all(np.abs(f[top] - frames[0][top]).max() < 40 for f in frames)  # the figure stands still
    changed = [np.abs(frames[k][-footer:] - frames[k - 1][-footer:]).sum() for k in range(1, 8)]
    assert all(c > 0 for c in changed)  # the counter moves every frame
    assert changed[3] == max(changed)  # frame 4 -> 5: "1/2 walks" becomes "2/2 waves"


def test_each_gif_frame_redraws_what_moves_and_keeps_the_title(tmp_path):
    """Frames are drawn over a copy of the first full drawing (the title is drawn once): a
    walking figure must move from frame to frame, and the title stay in every frame."""
    pose = np.random.default_rng(0).normal(size=(1, 22, 3)) * 0.3 + np.array([0.0, 1.0, 0.0])
    walk = np.repeat(pose, 6, axis=0) + np.arange(6)[:, None, None] * np.array([0.25, 0.0, 0.0])
    out = save_animation(walk, tmp_path / "walk.gif", title="a person walks to the right")
    with Image.open(out) as image:
        frames = []
        for k in range(image.n_frames):
            image.seek(k)
            frames.append(np.asarray(image.convert("L"), dtype=np.int16))
    title = slice(0, int(0.4 / (4.0 + 0.4 + 0.25) * frames[0].shape[0]))  # the strip above the axes
    assert (frames[0][title] < 128).sum() > 50  # the title is drawn...
    assert all(np.abs(f[title] - frames[0][title]).max() <= 8 for f in frames)  # ...in every frame
    figure = slice(title.stop, frames[0].shape[0] - 20)
    assert all((f[figure] < 128).sum() > 500 for f in frames)  # the stick figure, in every frame
    # the floor moves under the figure the camera follows
    assert all(np.abs(frames[k][figure] - frames[k - 1][figure]).max() > 30 for k in range(1, 6))


def _ffmpeg() -> str:
    exe = ffmpeg_executable()
    if exe is None:
        pytest.skip("no ffmpeg: neither imageio-ffmpeg (the video extra) nor ffmpeg on PATH")
    return exe


def _mp4_frames(path: Path) -> np.ndarray:
    """The frames of an MP4 as (n, h, w, 3) uint8, decoded by ffmpeg."""
    probe = subprocess.run([_ffmpeg(), "-v", "error", "-i", str(path), "-f", "rawvideo",
                            "-pix_fmt", "rgb24", "-"], capture_output=True, check=True)
    header = subprocess.run([_ffmpeg(), "-i", str(path)], capture_output=True, text=True).stderr
    width, height = map(int, re.search(r"Video: h264.*?, (\d+)x(\d+)", header).groups())
    assert re.search(r"(\d+(\.\d+)?) fps", header).group(1) == "20"
    return np.frombuffer(probe.stdout, np.uint8).reshape(-1, height, width, 3)


def test_an_mp4_has_every_frame_at_the_motions_rate(tmp_path):
    _ffmpeg()
    joints = as_joints(np.zeros((23, 263)))
    joints[:, :, 0] += np.linspace(0, 1, 23)[:, None]  # walks along x: frames differ
    out = save_animation(joints, tmp_path / "walk.mp4", title="a person walks",
                         segments=[("walks", 0, 12), ("stops", 12, 23)])
    frames = _mp4_frames(out)
    assert len(frames) == 23 and frames.shape[1] % 2 == 0 and frames.shape[2] % 2 == 0
    assert np.abs(frames[0].astype(int) - frames[-1]).max() > 100  # the figure moved
    assert not list(tmp_path.glob(".*.tmp"))


def test_an_mp4_that_fails_midway_leaves_the_earlier_file(tmp_path, monkeypatch):
    _ffmpeg()
    out = tmp_path / "walk.mp4"
    out.write_bytes(b"yesterday's render")
    calls = []

    def fail_on_the_fifth(self, frame):
        calls.append(frame)
        if len(calls) == 5:
            raise KeyboardInterrupt
    monkeypatch.setattr("segmo.render._StickFigure.update", fail_on_the_fifth)
    with pytest.raises(KeyboardInterrupt):
        save_animation(np.zeros((30, 22, 3)), out)
    assert out.read_bytes() == b"yesterday's render"
    assert not list(tmp_path.glob(".*.tmp"))


def test_an_ffmpeg_that_fails_is_named_with_its_message(tmp_path, monkeypatch):
    broken = tmp_path / "ffmpeg"
    broken.write_text("#!/bin/sh\necho 'Unknown encoder h264' >&2\nexit 1\n")
    broken.chmod(0o755)
    monkeypatch.setattr("segmo.render.ffmpeg_executable", lambda: str(broken))
    with pytest.raises(SegmoError, match=r"ffmpeg could not write x.mp4 \(exit status 1\): "
                                         "Unknown encoder h264"):
        save_animation(np.zeros((40, 22, 3)), tmp_path / "x.mp4")
    assert not list(tmp_path.glob("*.mp4")) and not list(tmp_path.glob(".*.tmp"))
