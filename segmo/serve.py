"""`segmo serve`: a web page (Gradio) around a bundle: type a caption, get a motion.

    segmo serve --model runs/demo/model [--host 127.0.0.1] [--port 7860]

The page shows the caption's text segments, the generated motion as a GIF (each frame
labelled with its segment), the BVH and joints files to download, and where each segment
happens in the motion (the similarity map of `SegMo.ground`, by the learned space or by
attention). Everything the page does is also an HTTP API endpoint, ``/generate``
(caption, seconds, seed, guidance, grounding method, segment durations -> segments, GIF,
BVH, joints, map), callable with `gradio_client`:

    from gradio_client import Client
    Client("http://127.0.0.1:7860").predict("a person walks, then waves", 4.0, 0, 4.0,
                                            "attention", "3,1", api_name="/generate")

The durations ("3,1": the walk three times as long as the wave; empty: the model's own
timing head) steer a bundle trained with segment timing; they may be left out.
"""

from __future__ import annotations

import argparse
import math
import os
import shutil
import signal
import sys
import tempfile
from pathlib import Path
from typing import Any

import torch

from segmo.errors import (
    LARGEST_WHOLE_NUMBER,
    ArgumentParser,
    SegmoError,
    parse_durations,
    positive_int,
)

GROUNDING_METHODS = ("attention", "similarity")
# A caption a person types: longer ones are cut by the text encoder anyway, and a page of
# text tied up the queue for half a minute.
MAX_CAPTION_CHARACTERS = 2_000
# Request folders a server keeps in its work folder (`prune_requests`).
KEEP_REQUESTS = 20
# The page takes no files, but Gradio's upload route stays open: bound what it stores.
MAX_UPLOAD = "1mb"


def generate_files(model: Any, caption: str, seconds: float, seed: int, guidance: float,
                   method: str, out: Path, durations: str = "") -> dict[str, Any]:
    """One generation written under `out`: {"segments", "gif", "bvh", "joints", "map"}.
    seconds <= 0 lets the length estimator choose, and more than the model's longest motion
    (`longest_seconds`) is refused; durations ("1,4", one per text segment) are given to a
    segment-timing model, empty lets it predict them."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from segmo.models.tokenizer import FRAMES_PER_TOKEN
    from segmo.pipeline.grounding import MIN_TOKENS, plot_similarity_map

    if not isinstance(caption, str):
        raise SegmoError(f"caption must be text, got {type(caption).__name__}")
    caption = " ".join(caption.split())
    if not caption:
        raise SegmoError("type a caption first")
    if len(caption) > MAX_CAPTION_CHARACTERS:  # the text encoder reads its start only
        raise SegmoError(f"caption of {len(caption):,} characters; at most "
                         f"{MAX_CAPTION_CHARACTERS:,}")
    numbers = {"length": seconds, "seed": seed, "guidance": guidance}
    for name, value in numbers.items():
        if isinstance(value, bool) or not isinstance(value, (int, float)) \
                or not math.isfinite(value):
            raise SegmoError(f"{name} must be a finite number, got {value!r}")
    if not (0 <= seed <= LARGEST_WHOLE_NUMBER and float(seed).is_integer()):
        raise SegmoError(f"seed must be a whole number from 0 to 2^63 - 1, got {seed!r}")
    if method not in GROUNDING_METHODS:
        raise SegmoError(f"grounding method must be one of {GROUNDING_METHODS}, got {method!r}")
    timing = None
    if durations and str(durations).strip():
        try:
            timing = [parse_durations(durations)]
        except ValueError as error:
            raise SegmoError(f"segment durations {error}") from None
    longest = longest_seconds(model)
    if seconds > longest:  # it was cut to the longest without a word
        raise SegmoError(f"a length of {seconds:g} s is longer than the model's {longest:g} s "
                         f"({model.max_frames} frames at {model.fps:g} fps)")
    segmented = model.segment_texts([caption])  # once: a bundle may name an LLM segmenter
    lengths = None
    if seconds and seconds > 0:
        frames = max(int(round(float(seconds) * model.fps / 4)) * 4, 4)
        count = len(segmented[0])
        needed = count * MIN_TOKENS * FRAMES_PER_TOKEN  # what grounding each segment takes
        if frames < needed:  # it failed after the generation, naming tokens
            raise SegmoError(f"a length of {seconds:g} s is too short for the caption's {count} "
                             f"segments; give at least {needed / model.fps:.1f} s")
        lengths = [frames]
    result = model.generate([caption], lengths, segments=segmented, guidance_scale=float(guidance),
                            generator=torch.Generator().manual_seed(int(seed)), durations=timing)
    segments = result.segments[0]
    grounding = model.ground(caption, result.motion(0), segments=segments, method=method)
    out.mkdir(parents=True, exist_ok=True)
    paths = result.save(out, formats=("npy", "gif", "bvh"), spans=[grounding.best_spans_frames])
    ax = plot_similarity_map(grounding, title=caption)
    map_path = out / "grounding.png"
    ax.figure.savefig(map_path, dpi=100, bbox_inches="tight")
    plt.close(ax.figure)
    by_suffix = {p.name: p for p in paths}
    return {"segments": segments, "spans": grounding.best_spans_frames,
            "gif": by_suffix["sample_00.gif"], "bvh": by_suffix["sample_00.bvh"],
            "joints": by_suffix["sample_00_joints.npy"], "map": map_path,
            "frames": int(result.lengths[0])}


def longest_seconds(model: Any) -> float:
    """The longest motion `model` makes, in seconds: its frames over its frame rate (9.8 s
    for 196 frames at 20 fps, 15.68 s at KIT's 12.5)."""
    return model.max_frames / model.fps


def _port(text: str) -> int:
    """argparse type of --port: a TCP port, 1 to 65535 (checked before the model loads)."""
    value = positive_int(text)
    if value > 65535:
        raise argparse.ArgumentTypeError(f"expected a TCP port from 1 to 65535, got {text!r}")
    return value


def prune_requests(root: Path, keep: int) -> None:
    """Delete all but the newest `keep` request folders (``000123/``, numbered in the order
    they were made) under `root`, the app's own requests folder: a server that runs for
    days must not fill its disk. Gradio has served its own copies of their files by then;
    other entries of `root` are left alone."""
    if not root.is_dir():
        return
    folders = sorted((p for p in root.iterdir()
                      if p.is_dir() and p.name.isascii() and p.name.isdigit()),
                     key=lambda p: int(p.name))
    for old in folders[:max(len(folders) - keep, 0)]:
        shutil.rmtree(old, ignore_errors=True)


def build_app(model: Any, workdir: str | os.PathLike | None = None):
    """The Gradio Blocks app of `model` (a `SegMo`); outputs go to a ``segmo-requests-*``
    folder the app makes for itself in `workdir` (in the system's temporary folder by
    default), one subfolder per request. Nothing else in `workdir` is touched, the
    folders of an earlier app there included."""
    os.environ.setdefault("GRADIO_ANALYTICS_ENABLED", "False")  # no telemetry calls
    try:
        import gradio as gr
    except ImportError:
        raise SegmoError("segmo serve needs Gradio: pip install 'segmo[serve]' (or gradio)") from None
    if workdir:
        Path(workdir).mkdir(parents=True, exist_ok=True)
    # A folder of its own: pruning must never reach the user's folders, nor reuse the
    # numbers of an earlier app's requests.
    root = Path(tempfile.mkdtemp(prefix="segmo-requests-", dir=workdir or None))
    counter = iter(range(10**9))

    def run(caption: str, seconds: float, seed: float, guidance: float, method: str,
            durations: str = ""):
        prune_requests(root, KEEP_REQUESTS)
        try:
            found = generate_files(model, caption, seconds, seed, guidance, method,
                                   root / f"{next(counter):06d}", durations)
        except SegmoError as error:  # one line in the server's log, the reason on the page
            print(f"segmo serve: refused a request: {error}", file=sys.stderr, flush=True)
            raise gr.Error(str(error), print_exception=False) from None
        lines = [f"{k + 1}. {text} — frames {s}–{e} ({s / model.fps:.1f}–{e / model.fps:.1f} s)"
                 for k, (text, (s, e)) in enumerate(zip(found["segments"], found["spans"]))]
        summary = (f"**{found['frames']} frames ({found['frames'] / model.fps:.1f} s), "
                   f"{len(lines)} segment(s)**\n\n" + "\n".join(lines))
        return summary, str(found["gif"]), [str(found["bvh"]), str(found["joints"])], str(found["map"])

    # Gradio's copies of the files it served: deleted an hour after they were made, checked
    # every hour, and when the server stops.
    with gr.Blocks(title="segmo", analytics_enabled=False, delete_cache=(3600, 3600)) as app:
        gr.Markdown("# segmo: text to 3-D human motion\nType a caption; its text segments, "
                    "in order, condition the motion. Download the BVH for Blender or a game engine.")
        with gr.Row():
            with gr.Column():
                caption = gr.Textbox(label="caption", value="a person walks forward, then waves",
                                     lines=2)
                seconds = gr.Slider(0, longest_seconds(model), value=0, step=0.2,
                                    label="length (s); 0: the model's estimate")
                # precision None: Gradio would round 2.7 to 3 before generate_files sees it
                seed = gr.Number(value=0, precision=None, label="seed (a whole number)")
                guidance = gr.Slider(1, 8, value=model.config.guidance_scale, step=0.5,
                                     label="guidance scale")
                method = gr.Radio(list(GROUNDING_METHODS), value="attention",
                                  label="ground the segments by")
                durations = gr.Textbox(value="", label="segment durations, e.g. 3,1 (models "
                                       "trained with segment timing; empty: predicted)")
                button = gr.Button("Generate", variant="primary")
            with gr.Column():
                segments = gr.Markdown(label="text segments")
                animation = gr.Image(label="motion", type="filepath")
                files = gr.File(label="BVH and joints", file_count="multiple")
        grounding = gr.Image(label="where each segment happens", type="filepath")
        button.click(run, [caption, seconds, seed, guidance, method, durations],
                     [segments, animation, files, grounding], api_name="generate")
    return app


def main(argv: list[str] | None = None) -> None:
    parser = ArgumentParser(prog="segmo serve", description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", required=True, help="bundle folder or hub id")
    parser.add_argument("--host", default="127.0.0.1", help="address to listen on (0.0.0.0: all)")
    parser.add_argument("--port", type=_port, default=7860)
    args = parser.parse_args(argv)
    from segmo.models.hub import is_hub_id
    from segmo.pipeline import SegMo

    if not Path(args.model).is_dir() and not is_hub_id(args.model):
        parser.error(f"--model {args.model}: no such directory (a bundle made by `segmo bundle`, "
                     "or a hub id like owner/name)")
    model = SegMo.from_pretrained(args.model)
    # The requests' files live in a folder that goes when the server stops: on Ctrl-C, and
    # on SIGTERM (`docker stop`, systemd, `kill`), which would otherwise end Python on the spot.
    previous = signal.signal(signal.SIGTERM, _exit_on_sigterm)
    try:
        with tempfile.TemporaryDirectory(prefix="segmo-serve-") as workdir:
            app = build_app(model, workdir)
            print(f"segmo serve: http://{args.host}:{args.port}  (Ctrl-C stops)")
            try:
                app.launch(server_name=args.host, server_port=args.port, show_error=True,
                           max_file_size=MAX_UPLOAD)
            finally:
                app.close()
    finally:
        signal.signal(signal.SIGTERM, previous)


def _exit_on_sigterm(signum: int, frame: object) -> None:
    raise SystemExit(128 + signum)  # the status a shell gives a process ended by the signal


if __name__ == "__main__":
    main()
