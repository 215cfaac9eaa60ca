"""Hostile input to `segmo segment-texts` and `segmo encode-texts`: every expected failure
ends as one line ``segmo COMMAND: message`` naming the file (and line) or the argument,
exit status 2, no traceback. Each case builds what it needs in a tiny folder."""

from __future__ import annotations

import json

import numpy as np
import pytest
from fake_openai import FakeOpenAI

from segmo.cli import main as segmo_main
from segmo.text.cache import update_cache
from segmo.text.extract import segment_folder
from segmo.text.rules import RULES_VERSION, RuleSegmenter


def _data(tmp_path, texts=None):
    root = tmp_path / "data"
    (root / "texts").mkdir(parents=True)
    for name, text in (texts or {"000001": "a man walks then waves#x#0#0\n"}).items():
        data = text if isinstance(text, bytes) else text.encode()
        (root / "texts" / f"{name}.txt").write_bytes(data)
    return root


def _fails(argv, capsys, *expected):
    """Run `segmo ARGV`; it must exit 2 with one line holding every `expected` piece."""
    with pytest.raises(SystemExit) as exit_:
        segmo_main(argv)
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    # (transformers may draw its "Loading weights" bar on stderr before a late failure)
    lines = [x for x in err.strip().splitlines() if not x.startswith("Loading weights")]
    assert len(lines) == 1, err
    assert lines[0].startswith(f"segmo {argv[0]}: ")
    for piece in expected:
        assert piece in lines[0], (piece, lines[0])
    return lines[0]


def _hash_cache(root, name="hash", dim=8):
    from conftest import hash_encoder

    return update_cache(root, hash_encoder(name, dim), progress=False)


# ---------------------------------------------------------------- both commands, --data
@pytest.mark.parametrize("command", ["segment-texts", "encode-texts"])
def test_data_does_not_exist(tmp_path, capsys, command):
    _fails([command, "--data", str(tmp_path / "nowhere")], capsys, f"--data {tmp_path / 'nowhere'}: no such folder")


@pytest.mark.parametrize("command", ["segment-texts", "encode-texts"])
def test_data_is_a_file(tmp_path, capsys, command):
    (tmp_path / "file.txt").write_text("x")
    _fails([command, "--data", str(tmp_path / "file.txt")], capsys, "file.txt: is a file, not a dataset folder")


@pytest.mark.parametrize("command", ["segment-texts", "encode-texts"])
def test_no_texts_folder(tmp_path, capsys, command):
    _fails([command, "--data", str(tmp_path)], capsys, f"--data {tmp_path}: no texts/ folder in it")
    assert not (tmp_path / ".segmo-writer.lock").exists()  # refused before taking the lock


@pytest.mark.parametrize("command", ["segment-texts", "encode-texts"])
def test_empty_texts_folder(tmp_path, capsys, command):
    (tmp_path / "texts").mkdir()
    _fails([command, "--data", str(tmp_path)], capsys, f"{tmp_path / 'texts'} holds no <id>.txt caption files")


def test_a_byte_order_mark_is_not_part_of_the_first_caption(tmp_path):
    root = _data(tmp_path, {"000001": "\ufeffa man walks, then jumps#x#0#0\n".encode()})
    segment_folder(root, RuleSegmenter(), "rule", progress=False)
    line = (root / "text_segments" / "rule" / "000001.txt").read_text(encoding="utf-8")
    assert line.splitlines() == ["a man walks#a man jumps"]


@pytest.mark.parametrize("command", ["segment-texts", "encode-texts"])
@pytest.mark.parametrize("kind", ["broken link", "folder", "pipe"])
def test_a_texts_entry_that_is_not_a_file_is_named(tmp_path, capsys, command, kind):
    """They were skipped without a word: their motions had no captions, hence no segments."""
    import os

    root = _data(tmp_path)
    entry = root / "texts" / "000002.txt"
    if kind == "broken link":
        entry.symlink_to(tmp_path / "moved" / "000002.txt")
    elif kind == "folder":
        entry.mkdir()
    else:
        os.mkfifo(entry)
    _fails([command, "--data", str(root)], capsys,
           f"{root / 'texts'}: 1 of its *.txt entries are not caption files", "'000002.txt'")


@pytest.mark.parametrize("command", ["segment-texts", "encode-texts"])
def test_texts_not_utf8(tmp_path, capsys, command):
    root = _data(tmp_path, {"000001": "a man walks#x#0#0\n", "000002": b"a man walks#x#0#0\na \xe9t\xe9#x#0#0\n"})
    _fails([command, "--data", str(root)], capsys, "000002.txt:2: not UTF-8 text")


@pytest.mark.parametrize("command", ["segment-texts", "encode-texts"])
def test_unknown_option(tmp_path, capsys, command):
    _fails([command, "--data", str(_data(tmp_path)), "--frobnicate"], capsys, "unrecognized arguments: --frobnicate")


@pytest.mark.parametrize("command", ["segment-texts", "encode-texts"])
def test_missing_data_argument(capsys, command):
    _fails([command], capsys, "the following arguments are required: --data")


@pytest.mark.parametrize("argv, expected", [
    (["--batch-captions", "0"], "argument --batch-captions: expected a whole number >= 1, got '0'"),
    (["--batch-captions", "many"], "argument --batch-captions: expected a whole number, got 'many'"),
    (["--backend", "openai", "--model", "m", "--base-url", "http://h/v1", "--concurrency", "-1"],
     "argument --concurrency: expected a whole number >= 1, got '-1'"),
    (["--backend", "openai", "--model", "m", "--base-url", "http://h/v1", "--concurrency", "0"],
     "argument --concurrency: expected a whole number >= 1, got '0'"),
    (["--backend", "openai", "--model", "m", "--base-url", "http://h/v1", "--timeout", "-1"],
     "argument --timeout: expected a number of seconds in (0, 86400], got '-1'"),
    (["--backend", "openai", "--model", "m", "--base-url", "http://h/v1", "--timeout", "1e300"],
     "argument --timeout: expected a number of seconds in (0, 86400], got '1e300'"),
    (["--backend", "openai", "--model", "m", "--base-url", "http://h/v1", "--timeout", "nan"],
     "argument --timeout: expected a finite number, got 'nan'"),
    (["--backend", "openai", "--model", "m", "--base-url", "http://h/v1", "--max-retries", "-2"],
     "argument --max-retries: expected a whole number >= 0, got '-2'"),
    # a million retries of 8 s each waited for ever on a dead server
    (["--backend", "openai", "--model", "m", "--base-url", "http://h/v1", "--max-retries", "1000000"],
     "argument --max-retries: expected at most 20 retries, got '1000000'"),
    # and 10^6 parallel requests took 2 million failures to call the server down
    (["--backend", "openai", "--model", "m", "--base-url", "http://h/v1", "--concurrency", "1000000"],
     "argument --concurrency: expected at most 1024 parallel requests, got '1000000'"),
    (["--max-fallback-share", "1.5"], "argument --max-fallback-share: expected a share between 0 and 1, got '1.5'"),
    (["--max-fallback-share", "nan"], "argument --max-fallback-share: expected a finite number, got 'nan'"),
    (["--backend", "transformers", "--model", "m", "--batch-size", "0"], "argument --batch-size: expected a whole number >= 1, got '0'"),
    (["--backend", "gpt"], "argument --backend: invalid choice: 'gpt'"),
    (["--backend", "openai", "--model", "m"], "--backend openai needs --base-url (or OPENAI_BASE_URL"),
    (["--backend", "openai", "--base-url", "http://h/v1"], "--backend openai needs --model"),
    (["--backend", "openai", "--model", "m", "--base-url", "localhost:8000"],
     "argument --base-url: base URL 'localhost:8000' must look like http://HOST:PORT/v1"),
    (["--backend", "openai", "--model", "m", "--base-url", "http://host:port/v1"],
     "argument --base-url: base URL 'http://host:port/v1' is not a valid URL"),
    (["--backend", "openai", "--model", "m", "--base-url", "ftp://host/v1"],
     "argument --base-url: base URL 'ftp://host/v1' must look like"),
    (["--backend", "transformers"], "--backend transformers needs --model"),
    (["--model", "m", "--timeout", "3"], "--backend rule takes none of ['--model', '--timeout']"),
])
def test_segment_texts_bad_arguments(tmp_path, capsys, monkeypatch, argv, expected):
    monkeypatch.delenv("OPENAI_BASE_URL", raising=False)
    _fails(["segment-texts", "--data", str(_data(tmp_path)), *argv], capsys, expected)


def test_segment_texts_unloadable_transformers_model(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    missing = tmp_path / "no-such-model"
    _fails(["segment-texts", "--data", str(_data(tmp_path)), "--backend", "transformers", "--model",
            str(missing)], capsys, f"--model {missing}: cannot load a tokenizer")


def test_segment_texts_corrupt_meta(tmp_path, capsys):
    root = _data(tmp_path)
    (root / "text_segments" / "rule").mkdir(parents=True)
    (root / "text_segments" / "rule" / "meta.json").write_text("{not json")
    _fails(["segment-texts", "--data", str(root)], capsys, "text_segments/rule/meta.json: not valid JSON")


def test_segment_texts_meta_of_another_prompt(tmp_path, capsys):
    root = _data(tmp_path)
    segment_folder(root, RuleSegmenter(), progress=False)
    meta = root / "text_segments" / "rule" / "meta.json"
    meta.write_text(json.dumps({**json.loads(meta.read_text()), "backend": "openai"}))
    _fails(["segment-texts", "--data", str(root)], capsys, "text_segments/rule was made with other backend",
           "use --overwrite or another folder")


def test_segment_texts_folder_of_older_rules(tmp_path, capsys):
    """A rule folder written before a rule change is refused, not mixed with newer segments."""
    root = _data(tmp_path)
    segment_folder(root, RuleSegmenter(), progress=False)
    meta = root / "text_segments" / "rule" / "meta.json"
    record = json.loads(meta.read_text())
    assert record["rules_version"] == RULES_VERSION
    meta.write_text(json.dumps({k: v for k, v in record.items() if k != "rules_version"}))
    before = {p.name: p.read_bytes() for p in meta.parent.glob("*.txt")}
    _fails(["segment-texts", "--data", str(root)], capsys, "text_segments/rule was made with other rules_version",
           "use --overwrite or another folder")
    assert {p.name: p.read_bytes() for p in meta.parent.glob("*.txt")} == before


def test_segment_texts_hand_made_folder_is_refused(tmp_path, capsys):
    """A segment folder segment-texts did not write (no meta.json, no manifest.jsonl: made by
    hand, or by the reference code) was silently rewritten, and the user's segments lost."""
    root = _data(tmp_path)
    folder = root / "text_segments" / "rule"
    folder.mkdir(parents=True)
    (folder / "000001.txt").write_text("my own hand-made segment A#B\n")
    _fails(["segment-texts", "--data", str(root), "--quiet"], capsys, f"{folder}: holds segment files",
           "not written by segment-texts", "--overwrite")
    assert (folder / "000001.txt").read_text() == "my own hand-made segment A#B\n"
    assert sorted(p.name for p in folder.iterdir()) == ["000001.txt"]
    segmo_main(["segment-texts", "--data", str(root), "--quiet", "--overwrite"])
    assert (folder / "000001.txt").read_text() == "a man walks#a man waves\n"


def test_segment_texts_corrupt_manifest(tmp_path, capsys):
    root = _data(tmp_path)
    segment_folder(root, RuleSegmenter(), progress=False)
    manifest = root / "text_segments" / "rule" / "manifest.jsonl"
    manifest.write_text('{"id": "000001"}\n' + manifest.read_text())
    _fails(["segment-texts", "--data", str(root)], capsys, "manifest.jsonl:1: not a segment record")


def test_segment_texts_server_refuses_the_key(tmp_path, capsys):
    root = _data(tmp_path, {"000001": "a person is denied#x#0#0\n"})
    with FakeOpenAI({"a person is denied": "401"}) as server:
        _fails(["segment-texts", "--data", str(root), "--backend", "openai", "--model", "tiny",
                "--base-url", server.url, "--quiet"], capsys,
               f"{server.url} answered HTTP 401 for model 'tiny'", "API key in $OPENAI_API_KEY")


def test_segment_texts_malformed_line_is_reported_not_fatal(tmp_path, capsys, caplog):
    """The dataset reader skips such a line (and counts it), so segment-texts segments it,
    keeps the lines aligned, and names it."""
    root = _data(tmp_path, {"000001": "a man walks then waves#x#0#0\na man jumps without tags\n"})
    segmo_main(["segment-texts", "--data", str(root), "--quiet"])
    out = capsys.readouterr().out
    assert ("1 malformed caption line(s), segmented but skipped by the dataset reader: "
            "texts/000001.txt:2: expected 'caption#tokens#from#to', got 1 '#'-separated fields") in out
    assert "000001.txt:2: expected 'caption#tokens#from#to'" in caplog.text
    assert (root / "text_segments" / "rule" / "000001.txt").read_text() == \
        "a man walks#a man waves\na man jumps without tags\n"


# ---------------------------------------------------------------- encode-texts
@pytest.mark.parametrize("argv, expected", [
    (["--batch-size", "0"], "argument --batch-size: expected a whole number >= 1, got '0'"),
    (["--batch-size", "x"], "argument --batch-size: expected a whole number, got 'x'"),
    (["--shard-size", "0"], "argument --shard-size: expected a whole number >= 1, got '0'"),
    (["--segments", "llm"], "--segments llm: no text-segment folder"),
    (["--device", "banana"], "--device 'banana': not a torch device"),
    (["--device", "cuda:0"], "--device 'cuda:0': this torch build sees no CUDA device"),
])
def test_encode_texts_bad_arguments(tmp_path, capsys, argv, expected):
    if "cuda:0" in argv:
        import torch

        if torch.cuda.is_available():
            pytest.skip("this machine has a CUDA device")
    root = _data(tmp_path)
    _fails(["encode-texts", "--data", str(root), *argv], capsys, expected)
    assert not (root / "text_features").exists()  # no empty feature folder left behind


def test_encode_texts_unknown_encoder(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    root = _data(tmp_path)
    _fails(["encode-texts", "--data", str(root), "--encoder", "no-such-encoder"], capsys,
           "--encoder 'no-such-encoder': text-encoder weights 'no-such-encoder' are not available")
    assert not (root / "text_features").exists()


def test_encode_texts_encoder_directory_without_config(tmp_path, capsys):
    (tmp_path / "enc").mkdir()
    _fails(["encode-texts", "--data", str(_data(tmp_path)), "--encoder", str(tmp_path / "enc")], capsys,
           f"--encoder '{tmp_path / 'enc'}': text-encoder directory {tmp_path / 'enc'} has no config.json")


def test_encode_texts_no_caption_with_words(tmp_path, capsys):
    root = _data(tmp_path, {"000001": ".#x#0#0\n!!!#x#0#0\n"})
    _fails(["encode-texts", "--data", str(root)], capsys, f"no caption with words in {root / 'texts'}")


def test_a_pipe_among_the_segment_files_is_one_line_not_a_hang(tmp_path, capsys):
    """A FIFO named *.txt in a segment folder blocked encode-texts for ever, and one named
    manifest.jsonl blocked segment-texts after its first file."""
    import os

    root = _data(tmp_path)
    folder = root / "text_segments" / "rule"
    folder.mkdir(parents=True)
    os.mkfifo(folder / "manifest.jsonl")
    _fails(["segment-texts", "--data", str(root), "--quiet"], capsys,
           f"{folder / 'manifest.jsonl'}: not a regular file")
    (folder / "manifest.jsonl").unlink()
    os.mkfifo(folder / "000002.txt")
    _fails(["encode-texts", "--data", str(root)], capsys, f"{folder / '000002.txt'}: not a regular file")


def test_encode_texts_segment_file_not_utf8(tmp_path, capsys):
    root = _data(tmp_path)
    (root / "text_segments" / "rule").mkdir(parents=True)
    (root / "text_segments" / "rule" / "000001.txt").write_bytes(b"a man walks#a man \xff waves\n")
    _fails(["encode-texts", "--data", str(root)], capsys, "text_segments/rule/000001.txt:1: not UTF-8 text")


@pytest.mark.parametrize("name, content, expected", [
    ("index.json", "{truncated", "index.json: corrupt text-feature index"),
    ("index.json", "[1, 2]", "index.json: corrupt text-feature index (not a JSON object)"),
    ("index.json", '{"format": 7, "shards": []}', "index.json: not a format-1 text-feature index"),
    ("meta.json", "", "meta.json: corrupt text-feature metadata"),
])
def test_encode_texts_corrupt_cache_files(tmp_path, capsys, name, content, expected):
    root = _data(tmp_path)
    _hash_cache(root, name="minilm", dim=384)
    (root / "texts" / "000002.txt").write_text("a woman jumps#x#0#0\n")  # something to encode
    (root / "text_features" / "minilm" / name).write_text(content)
    _fails(["encode-texts", "--data", str(root)], capsys, str(root / "text_features" / "minilm" / name), expected)


def test_encode_texts_other_dim_in_the_folder(tmp_path, capsys):
    root = _data(tmp_path)
    _hash_cache(root, name="minilm", dim=16)
    (root / "texts" / "000002.txt").write_text("a woman jumps#x#0#0\n")
    _fails(["encode-texts", "--data", str(root)], capsys, "text_features/minilm holds HashEncoder features of dim 16",
           "delete the folder or use another encoder name")


def test_opening_a_cache_with_a_corrupt_shard_names_it(tmp_path):
    from segmo.errors import SegmoError
    from segmo.text.cache import TextFeatureCache

    root = _data(tmp_path)
    _hash_cache(root)
    shard = root / "text_features" / "hash" / "shard-00000.sentence.npy"
    shard.write_bytes(b"\x93NUMPY garbage")
    with pytest.raises(SegmoError, match=rf"{shard}: unreadable shard of the text-feature cache"):
        TextFeatureCache.open(root, "hash")
    np.save(shard, np.zeros((1, 8), dtype=np.float16))  # a readable shard opens again
    assert TextFeatureCache.open(root, "hash").dim == 8


def _damage(folder, what):
    import json as json_

    stem = folder / "shard-00000"
    index = json_.loads((folder / "index.json").read_text())
    if what == "sentence rows":
        np.save(f"{stem}.sentence.npy", np.load(f"{stem}.sentence.npy")[:0])
    elif what == "sentence ints":
        np.save(f"{stem}.sentence.npy", np.load(f"{stem}.sentence.npy").astype(np.int8))
    elif what == "token width":
        np.save(f"{stem}.tokens.npy", np.load(f"{stem}.tokens.npy")[:, :3])
    elif what == "offsets floats":
        np.save(f"{stem}.offsets.npy", np.load(f"{stem}.offsets.npy").astype(np.float32))
    elif what == "offsets past the end":
        np.save(f"{stem}.offsets.npy", np.load(f"{stem}.offsets.npy") + 5)
    elif what in ("name outside", "name a number"):
        index["shards"][0]["name"] = "../../elsewhere" if what == "name outside" else 7
        (folder / "index.json").write_text(json_.dumps(index))
    elif what == "huge dim":
        meta = json_.loads((folder / "meta.json").read_text())
        (folder / "meta.json").write_text(json_.dumps({**meta, "dim": 10**12}))


@pytest.mark.parametrize("what, expected", [
    ("sentence rows", "shard-00000.sentence.npy: float16 of shape (0, 8), expected floats of shape (1, 8)"),
    ("sentence ints", "shard-00000.sentence.npy: int8 of shape (1, 8)"),
    ("token width", "shard-00000.tokens.npy: float16 of shape"),
    ("offsets floats", "shard-00000.offsets.npy: float32 of shape (2,), expected 2 whole numbers"),
    ("offsets past the end", "shard-00000.offsets.npy: offsets must run from 0 up to the"),
    ("name outside", "shard '../../elsewhere' is not a shard entry of segmo's"),
    ("name a number", "shard '7' is not a shard entry of segmo's"),
    ("huge dim", "meta.json: no valid 'dim'"),
])
def test_a_damaged_cache_is_one_line_naming_the_file(tmp_path, what, expected):
    """Each was read as valid (a shard of int8, token lookups past the end came back empty,
    a name outside the folder was read), or failed later in training with an IndexError,
    a TypeError or a MemoryError."""
    from segmo.errors import SegmoError
    from segmo.text.cache import TextFeatureCache

    root = _data(tmp_path)
    _hash_cache(root)
    _damage(root / "text_features" / "hash", what)
    with pytest.raises(SegmoError) as caught:
        TextFeatureCache.open(root, "hash")
    assert expected in str(caught.value) and "re-run `segmo encode-texts`" in str(caught.value)
