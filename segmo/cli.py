"""The `segmo` command.

Every sub-command lives next to the code it drives and exposes `main(argv: list[str])`;
this module only maps names to those functions, importing them lazily so that
`segmo --help` stays fast. Training sub-commands (`fit`, `validate`, `test`) go to the
LightningCLI wrapper in `segmo.training.cli`.
"""

from __future__ import annotations

import importlib
import os
import sys
import threading
import warnings

from segmo.errors import SegmoError

# name -> (module, function, one-line help)
COMMANDS: dict[str, tuple[str, str, str]] = {
    "demo": ("segmo.demo", "main", "run the whole flow on the built-in corpus"),
    "synth": ("segmo.synth.corpus", "main", "build the built-in synthetic corpus"),
    "render": ("segmo.render", "main", "render a motion (.npy features or joints) to GIF/MP4"),
    "segment-texts": ("segmo.text.extract", "main", "extract text segments offline"),
    "encode-texts": ("segmo.text.cache", "main", "cache text-encoder features"),
    "fit": ("segmo.training.cli", "main", "train a stage from a YAML config (LightningCLI)"),
    "validate": ("segmo.training.cli", "main", "validate a stage (LightningCLI)"),
    "test": ("segmo.training.cli", "main", "test a stage (LightningCLI)"),
    "export": ("segmo.export", "main", "export a checkpoint to a self-describing model directory"),
    "bundle": ("segmo.pipeline.cli", "bundle_main", "assemble exported stages into one SegMo model"),
    "generate": ("segmo.pipeline.cli", "generate_main", "generate motions from text"),
    "edit": ("segmo.pipeline.cli", "edit_main", "edit a generated motion by its attention"),
    "compose": ("segmo.pipeline.cli", "compose_main",
                "one long motion from a list of prompts, joined by transitions"),
    "ground": ("segmo.pipeline.cli", "ground_main", "ground a text in a motion"),
    "evaluate": ("segmo.evaluation.cli", "main", "evaluate a model and write a report"),
    "serve": ("segmo.serve", "main", "a web page around a model: caption in, motion and BVH out"),
}


def _usage() -> str:
    width = max(map(len, COMMANDS))
    lines = ["usage: segmo COMMAND [ARGS...]", "", "commands:"]
    lines += [f"  {name:<{width}}  {help_}" for name, (_, _, help_) in COMMANDS.items()]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    """Run ``segmo [--debug] COMMAND [ARGS...]``.

    Expected failures (`SegmoError`, and OS errors, which name their file) end as one line
    ``segmo COMMAND: message`` on stderr with exit status 2; ``--debug`` (anywhere on the
    line) shows the traceback instead. Ctrl-C ends with status 130.
    """
    argv = sys.argv[1:] if argv is None else list(argv)
    debug = "--debug" in argv
    argv = [a for a in argv if a != "--debug"]
    if not argv or argv[0] in ("-h", "--help"):
        print(_usage())
        return
    name, rest = argv[0], argv[1:]
    if name not in COMMANDS:
        print(f"segmo: unknown command {name!r} (see `segmo --help`)", file=sys.stderr)
        sys.exit(2)
    module, function, _ = COMMANDS[name]

    def command(argv: list[str]) -> None:  # imported inside `run`: Ctrl-C while torch loads
        getattr(importlib.import_module(module), function)(argv)  # is one line, not 58

    # LightningCLI needs the sub-command itself.
    args = [name, *rest] if module == "segmo.training.cli" else rest
    run(f"segmo {name}", command, args, debug=debug)


def run(prog: str, command, argv: list[str], debug: bool = False) -> None:
    """Call ``command(argv)``, turning expected failures into one line and exit status 2."""
    def one_line(message, category, filename, lineno, file=None, line=None) -> None:
        # A warning is news for the user, not a pointer into segmo's source.
        text = " ".join(str(message).split())
        print(f"{prog}: {category.__name__}: {text}", file=file or sys.stderr)

    shown = warnings.showwarning
    if not debug:
        warnings.showwarning = one_line
    try:
        command(argv)
    except (SegmoError, OSError) as error:
        if debug:
            raise
        message = str(error) if isinstance(error, SegmoError) else _os_message(error)
        print(f"{prog}: {message}", file=sys.stderr)
        sys.exit(2)
    except KeyboardInterrupt:
        if debug:
            raise
        print(f"{prog}: interrupted", file=sys.stderr)
        if any(t.is_alive() and not t.daemon for t in threading.enumerate()
               if t is not threading.main_thread()):
            # Python would wait for them at exit: a request in flight to a server that does
            # not answer (segment-texts) kept an interrupted run alive for minutes. What the
            # commands write is atomic and resumable, so nothing is lost by not waiting.
            sys.stderr.flush()
            sys.stdout.flush()
            os._exit(130)
        sys.exit(130)
    finally:
        warnings.showwarning = shown


def _os_message(error: OSError) -> str:
    """An OS error as one line that names its file(s): 'PATH: No space left on device'."""
    files = [f for f in (error.filename, error.filename2) if f is not None]
    reason = error.strerror or str(error)
    message = f"{' -> '.join(map(str, files))}: {reason}" if files else reason
    return " ".join(message.split())


if __name__ == "__main__":
    main()
