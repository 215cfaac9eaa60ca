"""LLM backends: prompt, parsing, validation, retries and rule fallback.

The OpenAI backend talks to a local HTTP server; the transformers backend runs a tiny
randomly initialised chat model built offline, whose garbage answers prove the fallback.
"""

from __future__ import annotations

import json
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import pytest

from segmo.text.llm import (
    LLMSegmenter,
    OpenAISegmenter,
    Prompt,
    get_segmenter,
    load_prompt,
    parse_answer,
    validate_segments,
)
from segmo.text.rules import RuleSegmenter, TextSegmenter

# ---------------------------------------------------------------- prompt, parsing, validation


def test_prompt_files_load_and_examples_obey_the_validator():
    prompt = load_prompt()
    assert "order" in prompt.system.lower() and '{"segments"' in prompt.system
    assert len(prompt.examples) >= 5 and len(prompt.hash) == 16
    for caption, segments in prompt.examples:
        assert validate_segments(caption, list(segments)) is None, caption
    messages = prompt.messages("a man jumps")
    assert messages[0]["role"] == "system" and messages[-1] == {"role": "user", "content": "a man jumps"}
    assert len(messages) == 2 + 2 * len(prompt.examples)


def test_load_prompt_names_the_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="segment_system.md"):
        load_prompt(tmp_path)


@pytest.mark.parametrize(
    "answer",
    [
        '{"segments": ["a man walks", "a man runs"]}',
        '<think>\nthe walk comes first {"segments": ["x"]}\n</think>\n{"segments": ["a man walks", "a man runs"]}',
        '```json\n{"segments": ["a man walks.", "a man runs"]}\n```',
        'Sure! Here it is: {"segments": ["a man walks", "a man runs"]} Hope that helps.',
    ],
)
def test_parse_answer_tolerates_wrappers(answer):
    assert parse_answer(answer) == ["a man walks", "a man runs"]


@pytest.mark.parametrize("answer", ["", "a man walks", '{"segs": ["a"]}', '{"segments": [1, 2]}', "<think>{\"segments\": [\"a\"]}"])
def test_parse_answer_rejects_non_answers(answer):
    assert parse_answer(answer) is None


def test_parse_answer_strips_hash():
    assert parse_answer('{"segments": ["a man #walks"]}') == ["a man  walks"]


def test_validate_segments():
    caption = "a man runs after walking"
    assert validate_segments(caption, ["a man walks", "a man runs"]) is None
    assert validate_segments(caption, ["the person walked", "he ran"]) is None  # subject, inflection
    assert "JSON" in validate_segments(caption, None)
    assert "1 to 5" in validate_segments(caption, [])
    assert "1 to 5" in validate_segments(caption, ["a man runs"] * 6)
    assert "empty" in validate_segments(caption, ["a man walks", " "])
    assert "not in the caption" in validate_segments(caption, ["a man dances"])
    assert "longer" in validate_segments(caption, ["a man runs " * 10])


# ---------------------------------------------------------------- shared retry / fallback loop
class _Scripted(LLMSegmenter):
    """Answers from a script: caption -> list of answers, one per attempt."""

    name = "scripted"

    def __init__(self, script, **kwargs):
        super().__init__(**kwargs)
        self.script = script
        self.asked: list[int] = []

    def _complete_many(self, conversations):
        self.asked.append(len(conversations))
        out = []
        for conv in conversations:
            caption = conv[len(self.prompt.messages("")) - 1]["content"]
            attempt = (len(conv) - len(self.prompt.messages(""))) // 2
            out.append(self.script[caption][min(attempt, len(self.script[caption]) - 1)])
        return out


def test_retry_then_success_and_fallback_counts(caplog):
    script = {
        "a man runs after walking": ['{"segments": ["a man walks", "a man runs"]}'],
        "a man waves then jumps": ["nonsense", '{"segments": ["a man waves", "a man jumps"]}'],
        "a man sits then stands up": ['{"segments": ["a dragon flies"]}'],
        "a man crawls": [RuntimeError("boom")],
    }
    seg = _Scripted(script, max_retries=2)
    with caplog.at_level("WARNING"):
        out = seg.segment(list(script) + [""])
    assert out[0] == ["a man walks", "a man runs"]
    assert out[1] == ["a man waves", "a man jumps"]
    assert out[2] == RuleSegmenter().segment_one("a man sits then stands up")  # fallback
    assert out[3] == ["a man crawls"]  # transport failure: fallback, no re-ask
    assert out[4] == [""]
    assert seg.fallbacks == 2 and seg.stats.retries == 3
    assert seg.asked == [4, 2, 1]
    assert "falling back" in caplog.text


def test_get_segmenter():
    assert isinstance(get_segmenter("rule"), RuleSegmenter)
    seg = get_segmenter("openai", base_url="http://127.0.0.1:9/v1", model="Qwen/Qwen3-8B", concurrency=None)
    assert isinstance(seg, TextSegmenter) and seg.name == "openai-qwen3-8b" and seg.concurrency == 8
    with pytest.raises(ValueError, match="unknown backend"):
        get_segmenter("gpt")
    with pytest.raises(ValueError, match="no option"):
        get_segmenter("rule", model="x")
    with pytest.raises(ValueError, match="base_url"):
        OpenAISegmenter("localhost:8000", "m")


# ---------------------------------------------------------------- OpenAI-compatible server
GOOD = {"a person walks forward and waves": ["a person walks forward and waves"]}


class _Handler(BaseHTTPRequestHandler):
    calls: dict[str, int] = {}
    auth: list[str] = []

    def log_message(self, *args):  # keep pytest output clean
        pass

    def _send(self, code: int, body: str) -> None:
        try:
            self.send_response(code)
            self.send_header("Content-Type", "application/json")
            self.end_headers()
            self.wfile.write(body.encode())
        except OSError:
            pass  # the client gave up (timeout test)

    def do_POST(self):
        body = json.loads(self.rfile.read(int(self.headers["Content-Length"])))
        assert self.path == "/v1/chat/completions" and body["model"] == "tiny"
        caption = next(m["content"] for m in reversed(body["messages"]) if m["role"] == "user"
                       and not m["content"].startswith("Invalid answer"))
        n = self.calls[caption] = self.calls.get(caption, 0) + 1
        self.auth.append(self.headers.get("Authorization", ""))

        def answer(content: str) -> str:
            return json.dumps({"choices": [{"message": {"role": "assistant", "content": content}}]})

        if "slow" in caption:
            time.sleep(1.0)
            self._send(200, answer('{"segments": ["a person walks slowly"]}'))
        elif "crash" in caption or ("flaky" in caption and n == 1):
            self._send(500, "{}")
        elif "denied" in caption:
            self._send(401, '{"error": "bad key"}')
        elif "malformed" in caption:
            self._send(200, answer("I would rather not."))
        elif "flaky" in caption:
            self._send(200, answer('<think>ok</think>{"segments": ["a person jumps flaky"]}'))
        else:
            self._send(200, answer("```json\n" + json.dumps({"segments": GOOD.get(caption, [caption])}) + "\n```"))


@pytest.fixture()
def server():
    _Handler.calls, _Handler.auth = {}, []
    httpd = ThreadingHTTPServer(("127.0.0.1", 0), _Handler)
    httpd.daemon_threads = True
    thread = threading.Thread(target=httpd.serve_forever, kwargs={"poll_interval": 0.02}, daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{httpd.server_address[1]}/v1"
    httpd.shutdown()
    httpd.server_close()


def _client(url, **kwargs):
    options = dict(timeout=0.3, max_retries=1, backoff=0.01, concurrency=4)
    options.update(kwargs)
    return OpenAISegmenter(url, "tiny", **options)


def test_openai_good_answers_keep_order(server, monkeypatch):
    monkeypatch.setenv("SEGMO_TEST_KEY", "sk-test")
    seg = _client(server, api_key_env="SEGMO_TEST_KEY")
    captions = ["a person walks forward and waves"] + [f"a person jumps {i} times" for i in range(6)]
    out = seg.segment(captions)
    assert out[0] == ["a person walks forward and waves"]  # the server's answer, not the rules'
    assert out[1:] == [[c] for c in captions[1:]]
    assert seg.fallbacks == 0 and set(_Handler.auth) == {"Bearer sk-test"}


def test_openai_timeout_malformed_and_500_fall_back(server):
    seg = _client(server)
    captions = ["a person walks slow then sits", "a person malformed then waves", "a person crash then jumps"]
    t0 = time.perf_counter()
    out = seg.segment(captions)
    assert time.perf_counter() - t0 < 5
    assert out == RuleSegmenter().segment(captions)
    assert seg.fallbacks == 3
    assert _Handler.calls[captions[0]] == 2  # timeout: 1 + 1 retry
    assert _Handler.calls[captions[1]] == 2  # malformed: asked again once
    assert _Handler.calls[captions[2]] == 2  # HTTP 500: 1 + 1 retry


def test_openai_retries_a_flaky_server(server):
    seg = _client(server)
    assert seg.segment(["a person jumps flaky"]) == [["a person jumps flaky"]]
    assert seg.fallbacks == 0 and _Handler.calls["a person jumps flaky"] == 2


def test_openai_configuration_errors_raise(server):
    with pytest.raises(RuntimeError, match="HTTP 401"):
        _client(server).segment(["a person is denied"])


# ---------------------------------------------------------------- transformers backend
def _tiny_chat_model(path):
    from tokenizers import Tokenizer, models, pre_tokenizers, trainers
    from transformers import LlamaConfig, LlamaForCausalLM, PreTrainedTokenizerFast

    tok = Tokenizer(models.WordLevel(unk_token="[UNK]"))
    tok.pre_tokenizer = pre_tokenizers.Whitespace()
    corpus = ["a person walks forward then waves", "segments system user assistant { } [ ] : \" ,"]
    tok.train_from_iterator(corpus, trainers.WordLevelTrainer(special_tokens=["[PAD]", "[UNK]", "[EOS]"]))
    tokenizer = PreTrainedTokenizerFast(tokenizer_object=tok, unk_token="[UNK]", pad_token="[PAD]", eos_token="[EOS]")
    tokenizer.chat_template = (
        "{% for m in messages %}{{ m['role'] }} : {{ m['content'] }} [EOS] {% endfor %}"
        "{% if add_generation_prompt %}assistant : {% endif %}"
    )
    config = LlamaConfig(vocab_size=len(tokenizer), hidden_size=16, intermediate_size=32, num_hidden_layers=1,
                         num_attention_heads=2, num_key_value_heads=2, max_position_embeddings=4096,
                         pad_token_id=0, eos_token_id=2, bos_token_id=2)
    import torch

    torch.manual_seed(0)
    LlamaForCausalLM(config).save_pretrained(path)
    tokenizer.save_pretrained(path)


@pytest.mark.slow
def test_transformers_backend_falls_back_on_garbage(tmp_path, caplog):
    _tiny_chat_model(tmp_path / "tiny-chat")
    short = Prompt("Split the motion description.", (("a man waves", ("a man waves",)),))
    seg = get_segmenter("transformers", model_name_or_path=str(tmp_path / "tiny-chat"),
                        max_new_tokens=8, batch_size=2, max_retries=1, prompt=short)
    assert seg.name == "transformers-tiny-chat"
    captions = ["a person walks forward then waves", "a person waves", "someone jumps after walking"]
    with caplog.at_level("WARNING"):
        out = seg.segment(captions)
    assert out == RuleSegmenter().segment(captions)
    assert seg.fallbacks == 3 and seg.stats.requests == 6  # asked, re-asked, fell back
    assert "falling back" in caplog.text
