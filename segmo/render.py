"""Stick-figure rendering of motions: notebook figures and GIF/MP4 animations.

    >>> fig = plot_motion(joints, title="a person walks forward")        # key frames
    >>> save_animation(features, "walk.gif", title="a person walks forward")

A motion is either joints (t, j, 3) or features (t, d) (converted with
`features_to_joints`; pass `mean`/`std` for z-scored features). Data are y-up; the plot
maps (x, y, z) -> (x, -z, y) because matplotlib's 3-D axes are z-up (a rotation, so the
figure is not mirrored). Left limbs are blue, right limbs red.

CLI: `segmo render FILE.npy --out OUT.gif [--title T] [--skeleton t2m] [--fps N]
[--stride K] [--mean M.npy --std S.npy]`.
"""

from __future__ import annotations

import itertools
import math
import shutil
import subprocess
import textwrap
import warnings
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from segmo.errors import ArgumentParser, SegmoError, finite_float, positive_int
from segmo.files import atomic_open, atomic_path, file_above, npy_argument, remove_stale_temporaries
from segmo.motion.checks import joints_problem
from segmo.motion.features import features_to_joints
from segmo.motion.skeleton import SkeletonSpec, get_skeleton

__all__ = ["as_joints", "ffmpeg_executable", "plot_motion", "save_animation", "main"]

LEFT, RIGHT, CENTRE = "#1f5fbf", "#d62728", "#333333"
FLOOR_HALF_SIZE = 1.0  # metres of floor shown around the root (at least)
GRID_STEP = 0.5  # metres between floor grid lines
TITLE_LINES = 3  # a longer caption is cut: matplotlib lays out every line on every frame


def as_joints(
    motion: Any,
    skeleton: str | SkeletonSpec = "t2m",
    mean: Any = None,
    std: Any = None,
) -> np.ndarray:
    """Joints (t, j, 3) or features (t, d) (numpy or torch) -> joints (t, j, 3) float64,
    in metres (the skeleton's `unit` applied)."""
    spec = get_skeleton(skeleton)
    if hasattr(motion, "detach"):
        motion = motion.detach().cpu().numpy()
    motion = np.asarray(motion, dtype=np.float64)
    if motion.ndim == 3 and motion.shape[1:] == (spec.num_joints, 3):
        joints = motion
    elif motion.ndim == 2 and motion.shape[1] == spec.feature_dim:
        if (mean is None) != (std is None):
            raise ValueError("as_joints: pass both mean and std (z-scored features) or neither")
        if mean is not None:
            for name, stats in (("mean", mean), ("std", std)):  # else numpy broadcasts them
                if np.shape(stats) != (spec.feature_dim,):
                    raise ValueError(f"as_joints: {name} must have shape ({spec.feature_dim},) "
                                     f"for skeleton {spec.name!r}, got {np.shape(stats)}")
            motion = motion * np.asarray(std, dtype=np.float64) + np.asarray(mean, dtype=np.float64)
        joints = features_to_joints(motion, spec)
    else:
        raise SegmoError(
            f"expected joints (t, {spec.num_joints}, 3) or features (t, {spec.feature_dim}) for "
            f"skeleton {spec.name!r}, got shape {motion.shape}"
        )
    if len(joints) == 0:
        raise SegmoError("cannot render a motion with 0 frames")
    joints = joints * spec.unit
    problem = joints_problem(joints)
    if problem:
        raise SegmoError(problem)
    return joints


def _to_plot(points: np.ndarray) -> np.ndarray:
    """(..., 3) y-up data -> (..., 3) z-up plot coordinates (x, -z, y)."""
    return np.stack([points[..., 0], -points[..., 2], points[..., 1]], axis=-1)


def _chain_colours(spec: SkeletonSpec) -> list[str]:
    colours = []
    for chain in spec.kinematic_chains:
        names = " ".join(spec.joint_names[j] for j in chain[1:])
        colours.append(LEFT if "left" in names else RIGHT if "right" in names else CENTRE)
    return colours


class _StickFigure:
    """The artists of one 3-D axes, updated in place frame by frame (fast animation)."""

    def __init__(self, ax, joints: np.ndarray, spec: SkeletonSpec, trajectory: bool = True):
        self.ax, self.joints, self.spec = ax, joints, spec
        self.height = max(float(joints[..., 1].max()), 1.0)
        self.num_grid = int(2 * FLOOR_HALF_SIZE / GRID_STEP) + 2
        # one artist for the whole floor grid, its lines apart by NaN: a 3-D line costs its
        # projection on every frame, whatever its length
        self.grid = ax.plot([], [], [], color="#bbbbbb", lw=0.6)[0]
        self.trajectory = ax.plot([], [], [], color="#8c564b", lw=1.2)[0] if trajectory else None
        self.bones = [
            ax.plot([], [], [], color=colour, lw=2.5 if colour == CENTRE else 2.0,
                    solid_capstyle="round")[0]
            for colour in _chain_colours(spec)
        ]
        ax.set_box_aspect((1, 1, 1), zoom=1.25)
        ax.view_init(elev=15, azim=-60)
        ax.set_axis_off()

    def update(self, frame: int) -> None:
        pose = self.joints[frame]
        root_x, root_z = pose[0, 0], pose[0, 2]
        half = max(FLOOR_HALF_SIZE, 0.55 * self.height + 0.1)
        # Floor grid on world coordinates, windowed around the root: the figure walks
        # over the grid while the camera follows it.
        lines = []
        for centre, axis in ((root_x, 0), (root_z, 2)):
            first = np.floor((centre - half) / GRID_STEP) * GRID_STEP
            for k in range(self.num_grid):
                lines.append((axis, first + k * GRID_STEP))
        floor = []
        for axis, value in lines:
            if abs(value - (root_x if axis == 0 else root_z)) > half:
                continue  # outside the floor shown
            if axis == 0:
                floor += [[value, 0.0, root_z - half], [value, 0.0, root_z + half]]
            else:
                floor += [[root_x - half, 0.0, value], [root_x + half, 0.0, value]]
            floor.append([np.nan] * 3)
        floor = _to_plot(np.array(floor, dtype=float).reshape(-1, 3))
        self.grid.set_data_3d(floor[:, 0], floor[:, 1], floor[:, 2])
        if self.trajectory is not None:
            path = self.joints[: frame + 1, 0] * np.array([1.0, 0.0, 1.0])
            # 3-D lines are not clipped to the axes box: hide what lies off the floor.
            off = (np.abs(path[:, 0] - root_x) > half) | (np.abs(path[:, 2] - root_z) > half)
            path[off] = np.nan
            path = _to_plot(path)
            self.trajectory.set_data_3d(path[:, 0], path[:, 1], path[:, 2])
        for artist, chain in zip(self.bones, self.spec.kinematic_chains):
            points = _to_plot(pose[list(chain)])
            artist.set_data_3d(points[:, 0], points[:, 1], points[:, 2])
        self.ax.set_xlim(root_x - half, root_x + half)
        self.ax.set_ylim(-root_z - half, -root_z + half)
        self.ax.set_zlim(0.0, 2 * half)


def _figure(figsize: tuple[float, float], dpi: int):
    """A figure with its own Agg canvas: no pyplot state, so nothing is shown twice in a
    notebook and nothing leaks across calls (a notebook displays the returned figure)."""
    # matplotlib on use: `segmo render --help` and the pipeline's npy/bvh outputs skip it.
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize, dpi=dpi)
    FigureCanvasAgg(fig)
    return fig


def _wrap(title: str | None, width: int = 50) -> str | None:
    if title is None:
        return None
    return textwrap.fill(title, width, max_lines=TITLE_LINES, placeholder=" …")


def plot_motion(
    motion: Any,
    skeleton: str | SkeletonSpec = "t2m",
    title: str | None = None,
    frames: int | Sequence[int] = 4,
    mean: Any = None,
    std: Any = None,
    panel_size: float = 3.0,
):
    """Figure with one 3-D panel per key frame (`frames` evenly spaced key frames, or the
    listed frame indices), for notebooks. Returns a matplotlib Figure."""
    spec = get_skeleton(skeleton)
    joints = as_joints(motion, spec, mean, std)
    t = len(joints)
    if isinstance(frames, int):
        if frames < 1:
            raise ValueError(f"plot_motion: frames must be >= 1, got {frames}")
        indices = np.unique(np.linspace(0, t - 1, min(frames, t)).round().astype(int)).tolist()
    else:
        indices = [int(i) for i in frames]
        if not indices or any(not -t <= i < t for i in indices):
            raise ValueError(f"plot_motion: frame indices {indices} out of range for {t} frames")
    fig = _figure((panel_size * len(indices), panel_size + (0.6 if title else 0.2)), 100)
    fig.subplots_adjust(left=0, right=1, bottom=0, top=0.85 if title else 0.95, wspace=0)
    for k, index in enumerate(indices):
        ax = fig.add_subplot(1, len(indices), k + 1, projection="3d")
        _StickFigure(ax, joints, spec).update(index % t)
        ax.set_title(f"frame {index % t}", fontsize=9)
    if title:
        fig.suptitle(_wrap(title, int(18 * len(indices)) + 20), fontsize=10, parse_math=False)
    return fig


# The longest frame a GIF holds: its frame delay is a 16-bit count (of hundredths of a
# second; Pillow takes milliseconds), so one minute is well inside it.
GIF_LONGEST_FRAME_MS = 60_000
# The fastest a GIF plays: delays are whole hundredths, and browsers show a delay under
# two as ten (a 60 fps GIF played 6 times too slowly). Faster motions draw every k-th frame.
GIF_FASTEST_FPS = 50
# The most frames a GIF is drawn with: each is held in memory until the file is written
# (0.2 MB a frame; a 20-minute composition would take 4.5 GB). Longer motions draw every
# k-th frame; the npy and BVH files keep them all.
GIF_MAX_FRAMES = 3000


def save_animation(
    motion: Any,
    path: str | Path,
    skeleton: str | SkeletonSpec = "t2m",
    title: str | None = None,
    fps: float | None = None,
    mean: Any = None,
    std: Any = None,
    stride: int = 1,
    size: float = 4.0,
    dpi: int = 72,
    segments: Sequence[tuple[str, int, int]] | None = None,
    progress: bool = False,
) -> Path:
    """Write an animated stick figure to `path` (.gif with Pillow, .mp4 with ffmpeg:
    `ffmpeg_executable`), with a frame and time counter under it.

    stride: render every stride-th frame (fps is divided accordingly, so playback speed
    is unchanged). fps: playback rate of the source frames; default the skeleton's.
    segments: (text, start, end) frame spans; the frame's segment is written under the
    figure ("2/3 waves"). progress: a progress bar over the rendered frames.
    """
    spec = get_skeleton(skeleton)
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".gif", ".mp4"):
        raise SegmoError(f"save_animation: unsupported output {path.name!r}; use .gif or .mp4")
    ffmpeg = ffmpeg_executable() if suffix == ".mp4" else None
    if suffix == ".mp4" and ffmpeg is None:
        raise SegmoError("save_animation: writing .mp4 needs ffmpeg: install segmo's video "
                         "extra (pip install 'segmo[video]'), or put ffmpeg on PATH; or write "
                         "a .gif")
    if stride < 1:
        raise SegmoError(f"save_animation: stride must be >= 1, got {stride}")
    if fps is not None and not (np.isfinite(fps) and fps > 0):
        raise SegmoError(f"save_animation: fps must be a positive number, got {fps}")
    rate = (fps or spec.fps) / stride
    if suffix == ".gif" and not 1000 / rate <= GIF_LONGEST_FRAME_MS:
        raise SegmoError(f"save_animation: a frame would last {1000 / rate:.0f} ms (fps "
                         f"{fps or spec.fps:g} / stride {stride}); a GIF frame lasts at most "
                         f"{GIF_LONGEST_FRAME_MS} ms: lower the stride or raise the fps")
    joints = as_joints(motion, spec, mean, std)
    if suffix == ".gif":
        needed = max(stride, math.ceil((fps or spec.fps) / GIF_FASTEST_FPS),
                     math.ceil(len(joints) / GIF_MAX_FRAMES))
        if needed > stride:
            warnings.warn(f"save_animation: {path.name}: one frame in {needed} is drawn (a GIF "
                          f"plays at most {GIF_FASTEST_FPS} frames a second and is drawn with at "
                          f"most {GIF_MAX_FRAMES} frames)", stacklevel=2)
            stride = needed
            rate = (fps or spec.fps) / stride
    path.parent.mkdir(parents=True, exist_ok=True)

    footer = 0.45 if segments else 0.25  # inches under the figure for the counter (and segment)
    fig = _figure((size, size + (0.4 if title else 0.0) + footer), dpi)
    ax = fig.add_subplot(1, 1, 1, projection="3d")
    height = size + (0.4 if title else 0.0) + footer
    fig.subplots_adjust(left=0, right=1, bottom=footer / height,
                        top=1 - (0.4 / height if title else 0.0))
    if title:
        fig.suptitle(_wrap(title, int(10 * size)), fontsize=9, parse_math=False)
    counter = fig.text(0.02, 0.02 + (0.2 / height if segments else 0.0), "", fontsize=8,
                       family="monospace", color="#444444")
    # Captions are plain text: "$x^$" is no formula (matplotlib's mathtext failed on it).
    active = (fig.text(0.02, 0.02, "", fontsize=8, color="#1f4e9c", parse_math=False)
              if segments else None)
    spans = [(str(text), int(start), int(end)) for text, start, end in (segments or [])]
    source_fps = fps or spec.fps
    figure = _StickFigure(ax, joints, spec)
    frame_indices = range(0, len(joints), stride)

    def draw(frame: int) -> None:
        figure.update(frame)
        counter.set_text(f"frame {frame + 1:>3}/{len(joints)}  {frame / source_fps:5.2f} s")
        if active is not None:
            now = [k for k, (_, start, end) in enumerate(spans) if start <= frame < end]
            active.set_text(f"{now[0] + 1}/{len(spans)} {_wrap(spans[now[0]][0], int(12 * size))}"
                            if now else "")

    if progress:
        from tqdm import tqdm  # on use, like matplotlib

        frame_indices = tqdm(frame_indices, desc=f"render {path.name}", unit="frame", leave=False)
    frames = _drawn_frames(fig, ax, counter, active, draw, frame_indices)
    if suffix == ".gif":
        images = [Image.fromarray(rgb).quantize(colors=64, method=Image.Quantize.FASTOCTREE)
                  for rgb in frames]
        with atomic_open(path, "wb") as f:  # a killed render leaves no half GIF
            images[0].save(f, format="GIF", save_all=True, append_images=images[1:], loop=0,
                           duration=int(round(1000 / rate)), disposal=2)
    else:
        _write_mp4(frames, path, rate, ffmpeg)
    return path


def _drawn_frames(fig, ax, counter, active, draw, frame_indices) -> Iterator[np.ndarray]:
    """Each frame of the animation as (h, w, 3) uint8 RGB, after `draw(frame)` set it up.

    The title never changes and the segment seldom does: the figure is drawn once without
    what moves, the segment's line drawn on a copy of that when it changes, and each frame
    draws only the axes and the counter over the copy (half the time a frame). The axes'
    white patch goes (the figure is white beneath it): drawn after the title, it would cut
    off the title's descenders."""
    ax.patch.set_visible(False)
    for artist in (ax, counter, active):
        if artist is not None:
            artist.set_animated(True)
    fig.canvas.draw()
    background = blank = fig.canvas.copy_from_bbox(fig.bbox)
    shown = None
    for frame in frame_indices:
        draw(frame)
        if active is not None and active.get_text() != shown:  # the segment changed
            fig.canvas.restore_region(blank)
            fig.draw_artist(active)
            background, shown = fig.canvas.copy_from_bbox(fig.bbox), active.get_text()
        fig.canvas.restore_region(background)
        fig.draw_artist(ax)
        fig.draw_artist(counter)
        yield np.asarray(fig.canvas.buffer_rgba())[..., :3]


def ffmpeg_executable() -> str | None:
    """The ffmpeg that writes MP4s: the one imageio-ffmpeg ships (the `video` extra), else
    ffmpeg on PATH; None when there is neither."""
    try:
        import imageio_ffmpeg  # optional, and 70 MB: on use
    except ImportError:
        return shutil.which("ffmpeg")
    try:
        return imageio_ffmpeg.get_ffmpeg_exe()  # IMAGEIO_FFMPEG_EXE, its own, then PATH's
    except RuntimeError:  # no binary for this platform, and none on PATH
        return None


def _write_mp4(frames: Iterator[np.ndarray], path: Path, rate: float, ffmpeg: str) -> None:
    """Pipe RGB frames to `ffmpeg` for an H.264 MP4 that replaces `path` only once whole
    (a killed or failed render leaves an earlier file as it was). Players expect yuv420p,
    which needs even sides: a white row or column is added where one is odd."""
    first = next(frames)
    height, width = first.shape[:2]
    with atomic_path(path) as tmp:
        command = [ffmpeg, "-v", "error", "-y", "-f", "rawvideo", "-pix_fmt", "rgb24",
                   "-s", f"{width}x{height}", "-framerate", f"{rate:.6f}", "-i", "pipe:",
                   "-vf", "pad=ceil(iw/2)*2:ceil(ih/2)*2:color=white", "-vcodec", "h264",
                   "-pix_fmt", "yuv420p", "-f", "mp4", str(tmp)]
        process = subprocess.Popen(command, stdin=subprocess.PIPE, stdout=subprocess.DEVNULL,
                                   stderr=subprocess.PIPE)
        try:
            try:
                for rgb in itertools.chain([first], frames):
                    process.stdin.write(rgb.tobytes())
            except BrokenPipeError:  # ffmpeg stopped: its message says why
                pass
            _, error = process.communicate()
        except BaseException:
            process.kill()
            process.wait()
            raise
        if process.returncode != 0:
            lines = error.decode(errors="replace").strip().splitlines() or ["no message"]
            raise SegmoError(f"save_animation: {ffmpeg} could not write {path.name} (exit "
                             f"status {process.returncode}): {lines[-1]}")


def main(argv: list[str] | None = None) -> None:
    parser = ArgumentParser(
        prog="segmo render", description="Render a motion (.npy joints or features) to GIF/MP4."
    )
    parser.add_argument("file", type=Path, help="(t, j, 3) joints or (t, d) features, .npy")
    parser.add_argument("--out", type=Path, required=True, help="output .gif or .mp4")
    parser.add_argument("--title", default=None, help="caption shown above the figure")
    parser.add_argument("--skeleton", default="t2m", choices=["t2m", "kit"])
    parser.add_argument("--fps", type=finite_float, default=None,
                        help="default: the skeleton's fps")
    parser.add_argument("--stride", type=positive_int, default=1, help="render every k-th frame")
    parser.add_argument("--mean", type=Path, default=None, help="Mean.npy, for z-scored features")
    parser.add_argument("--std", type=Path, default=None, help="Std.npy, for z-scored features")
    args = parser.parse_args(argv)
    if (args.mean is None) != (args.std is None):
        parser.error("--mean and --std go together")
    if args.fps is not None and args.fps <= 0:
        parser.error(f"argument --fps: expected a positive number, got {args.fps:g}")
    if args.out.suffix.lower() not in (".gif", ".mp4"):
        parser.error(f"--out {args.out}: the name must end in .gif or .mp4")
    if args.out.is_dir():  # before the rendering, not when the file is moved into place
        parser.error(f"--out {args.out}: is a directory; name the file to write")
    above = file_above(args.out)
    if above is not None:
        parser.error(f"--out {args.out}: {above} is a file, not a directory")
    remove_stale_temporaries(args.out)  # of a render of this file that was killed
    motion = npy_argument(parser, "FILE", args.file)
    mean = None if args.mean is None else npy_argument(parser, "--mean", args.mean)
    std = None if args.std is None else npy_argument(parser, "--std", args.std)
    try:
        out = save_animation(motion, args.out, args.skeleton, args.title, args.fps, mean, std,
                             stride=args.stride)
    except (SegmoError, ValueError) as error:
        raise SegmoError(f"{args.file}: {error}") from None
    print(f"wrote {out}")

