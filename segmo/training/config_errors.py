"""One-line errors for `segmo fit|validate|test` arguments and YAML configs.

jsonargparse reports a bad key or value in a dozen lines of usage plus a nested union
report that names neither the YAML file nor the line. `check_config_files` refuses a
missing or unparsable ``--config`` file before LightningCLI reads it, and `config_error`
turns a parse error into a `SegmoError` that says where the key is and what is wrong::

    configs/rvq/mine.yaml:32: data.init_args.bach_size: segmo.data.MotionDataModule has no
    argument 'bach_size' (did you mean 'batch_size'?)

The key is looked up in the ``--config`` files (the last one that sets it wins, as in
jsonargparse) and on the command line; a message of a form not recognised here is still
folded into one line, with the config files named.
"""

from __future__ import annotations

import difflib
import importlib
import inspect
import re
from pathlib import Path

import yaml
from lightning.pytorch import Trainer

from segmo.errors import SegmoError

TOP_LEVEL = ("config", "seed_everything", "trainer", "model", "data", "optimizer",
             "lr_scheduler", "ckpt_path", "weights_only", "runs_dir", "run_name")


def config_files(argv: list[str]) -> list[str]:
    """The ``--config`` / ``-c`` files of an argument list, in order."""
    files = []
    for i, arg in enumerate(argv):
        if arg in ("--config", "-c") and i + 1 < len(argv):
            files.append(argv[i + 1])
        elif arg.startswith("--config="):
            files.append(arg.split("=", 1)[1])
    return files


def check_config_files(argv: list[str]) -> None:
    """Each ``--config`` file exists and is a YAML mapping that sets each key once, or one
    `SegmoError`."""
    for name in config_files(argv):
        path = Path(name)
        if not path.is_file():
            raise SegmoError(f"--config {name}: no such file")
        try:
            data = yaml.safe_load(path.read_text(encoding="utf-8"))
        except yaml.YAMLError as error:
            mark, start = getattr(error, "problem_mark", None), getattr(error, "context_mark", None)
            where = f"{name}:{mark.line + 1}" if mark is not None else name
            problem = getattr(error, "problem", None) or str(error)
            if start is not None and getattr(error, "context", None):
                problem += f" ({error.context} started at line {start.line + 1})"
            raise SegmoError(f"{where}: not valid YAML: {problem}") from None
        except UnicodeDecodeError as error:
            raise SegmoError(f"{name}: not a text file ({error.reason})") from None
        if data is None:  # empty, or only comments
            raise SegmoError(f"{name}: an empty config; expected a mapping of keys (trainer:, "
                             "model:, data:, ...)")
        if not isinstance(data, dict):
            raise SegmoError(f"{name}: expected a mapping of keys (trainer:, model:, data:, ...), "
                             f"got a YAML {type(data).__name__}")
        repeated = _repeated_key(yaml.compose(path.read_text(encoding="utf-8")))
        if repeated is not None:
            key, line, first = repeated
            # YAML parsers keep the last value silently: a pasted section or an edited
            # copy of a line would replace the setting above it without a word.
            raise SegmoError(f"{name}:{line}: key {key!r} set twice (also line {first})")


def _repeated_key(node: yaml.Node, prefix: str = "") -> tuple[str, int, int] | None:
    """The first key that a mapping of a YAML node tree sets twice, as (dotted key, its
    second line, its first line), or None."""
    items = node.value if isinstance(node, (yaml.MappingNode, yaml.SequenceNode)) else []
    if isinstance(node, yaml.MappingNode):
        first: dict[str, int] = {}
        for key, _ in items:
            line = key.start_mark.line + 1
            if isinstance(key, yaml.ScalarNode) and key.value in first:
                return f"{prefix}{key.value}", line, first[key.value]
            first.setdefault(str(key.value), line)
    for item in items:
        key, value = item if isinstance(node, yaml.MappingNode) else (None, item)
        found = _repeated_key(value, f"{prefix}{key.value}." if key is not None else prefix)
        if found is not None:
            return found
    return None


def _key_lines(node: yaml.Node, prefix: tuple[str, ...] = ()
               ) -> list[tuple[tuple[str, ...], int, str | None]]:
    """Every key path of a YAML node tree with its 1-based line and its value when that is
    a scalar; list items add no level."""
    out = []
    if isinstance(node, yaml.MappingNode):
        for key, value in node.value:
            path = (*prefix, str(key.value))
            scalar = value.value if isinstance(value, yaml.ScalarNode) else None
            out.append((path, key.start_mark.line + 1, scalar))
            out += _key_lines(value, path)
    elif isinstance(node, yaml.SequenceNode):
        for item in node.value:
            out += _key_lines(item, prefix)
    return out


def _plain(path: tuple[str, ...] | list[str]) -> tuple[str, ...]:
    """A key path without its ``init_args`` levels (jsonargparse accepts both spellings)."""
    return tuple(p for p in path if p != "init_args")


def where_set(key: str, argv: list[str]) -> list[tuple[str, str | None]]:
    """Every place that sets ``key`` (dotted), as ``("FILE:LINE" or "argument --ARG", the
    value there when it is a scalar)``, the one in effect first: command-line arguments from
    the last one, then the config files from the last one."""
    wanted = _plain(key.split("."))
    places: list[tuple[str, str | None]] = []
    for i, arg in enumerate(argv):
        if arg.startswith("--") and _plain(arg[2:].split("=", 1)[0].split(".")) == wanted:
            given = arg.split("=", 1)[1] if "=" in arg else (argv[i + 1] if i + 1 < len(argv) else None)
            places.insert(0, (f"argument {arg}", given))
    for name in reversed(config_files(argv)):
        try:
            root = yaml.compose(Path(name).read_text(encoding="utf-8"))
        except (OSError, yaml.YAMLError):
            continue
        found = [(line, scalar) for path, line, scalar in _key_lines(root) if _plain(path) == wanted]
        places += [(f"{name}:{line}", scalar) for line, scalar in reversed(found)]
    return places


def locate(key: str, argv: list[str], value: str | None = None) -> str | None:
    """Where ``key`` (dotted) is set: ``"FILE:LINE"`` or ``"argument --ARG"``, or None.

    With ``value`` (the offending value), a place that sets the key to it is preferred:
    a bad value in a YAML file is reported before a command-line override replaces it."""
    found = where_set(key, argv)
    matching = [where for where, given in found if value is not None and given == value]
    return (matching or [where for where, _ in found] or [None])[0]


def _argument_names(class_path: str) -> list[str]:
    """The constructor arguments of a class, those of the base classes that its ``**kwargs``
    pass on included (as jsonargparse resolves them)."""
    try:
        module, _, name = class_path.rpartition(".")
        cls = getattr(importlib.import_module(module), name)
        names: list[str] = []
        for klass in cls.__mro__:
            if "__init__" not in vars(klass):
                continue
            parameters = list(inspect.signature(klass.__init__).parameters.values())[1:]
            names += [p.name for p in parameters if p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)]
            if not any(p.kind is p.VAR_KEYWORD for p in parameters):
                break
        return list(dict.fromkeys(names))
    except (ImportError, AttributeError, ValueError, TypeError):
        return []


def _suggest(name: str, candidates: list[str]) -> str:
    close = difflib.get_close_matches(name, candidates, n=1)
    return f" (did you mean {close[0]!r}?)" if close else ""


def _expected(text: str) -> str:
    """jsonargparse's type text as a reader would say it: "<class 'int'>" → "int"."""
    text = re.sub(r"<class '(?:[\w.]+\.)?(\w+)'>", r"\1", text.strip())
    literal = re.fullmatch(r"typing\.Literal\[(.*)\]", text)
    return f"one of {literal.group(1)}" if literal else text


def _problem(message: str, subcommand: str) -> tuple[str | None, str, str | None]:
    """(dotted key or None, what is wrong, the offending value or None) of a jsonargparse
    message."""
    m = re.search(r"Subcommand '(\w+)' does not accept option '([^']+)'", message)
    if m:
        key = m.group(2)
        head, _, rest = key.partition(".")
        if head == "trainer" and rest:
            hint = _suggest(rest, list(inspect.signature(Trainer).parameters))
            return key, f"the Trainer has no argument {rest!r}{hint}", None
        return key, f"segmo {subcommand} has no key {head!r}{_suggest(head, list(TOP_LEVEL))}", None
    m = re.search(r"unrecognized arguments: (.*)", message)
    if m:
        return (None, f"unrecognized arguments: {m.group(1).strip()} (see `segmo {subcommand} "
                      "--help`)", None)
    outer = re.match(r'Parser key "([^"]+)":', message)
    group = outer.group(1) if outer else None
    m = re.search(r"Problem with given class_path '([^']+)':\s*(.*?)\n\s*- ", message + "\n  - ",
                  re.S)
    if group and m:
        class_path, detail = m.group(1), m.group(2)
        accepted = re.search(r"Option '([^']+)' is not accepted", detail)
        if accepted:
            name = accepted.group(1)
            hint = _suggest(name, _argument_names(class_path))
            return f"{group}.init_args.{name}", f"{class_path} has no argument {name!r}{hint}", None
        typed = re.search(r'Parser key "([^"]+)":\s*Expected (?:a )?(.*?)\. Got value: (.*)', detail)
        if typed:
            value = typed.group(3).strip()
            return (f"{group}.init_args.{typed.group(1)}",
                    f"expected {_expected(typed.group(2))}, got {value!r}", value)
        return f"{group}.class_path", f"{class_path}: {' '.join(detail.split())}", class_path
    typed = re.search(r"Expected (?:a )?(.*?)\. Got value: (.*)", message)
    if group and typed:
        value = typed.group(2).strip()
        return group, f"expected {_expected(typed.group(1))}, got {value!r}", value
    return group, " ".join(message.split()), None


def config_error(message: str, argv: list[str]) -> SegmoError:
    """A `SegmoError` for jsonargparse's ``message`` about ``segmo ARGV``."""
    subcommand = argv[0] if argv else "fit"
    key, problem, value = _problem(message, subcommand)
    where = locate(key, argv, value) if key else None
    if where is not None:
        return SegmoError(f"{where}: {key}: {problem}")
    files = config_files(argv)
    context = f" (config: {', '.join(files)})" if files else ""
    return SegmoError(f"{key}: {problem}{context}" if key else f"{problem}{context}")
