"""LLM backends: prompt, parsing, validation, retries and rule fallback.

The OpenAI backend talks to a local HTTP server; the transformers backend runs a tiny
randomly initialised chat model built offline, whose garbage answers prove the fallback.
"""

from __future__ import annotations

import time
from pathlib import Path

import pytest
from fake_openai import RETRY_AFTER, FakeOpenAI

from segmo.errors import SegmoError
from segmo.text.captions import has_words
from segmo.text.llm import (
    LLMSegmenter,
    LLMUnavailableError,
    OpenAISegmenter,
    Prompt,
    load_prompt,
    parse_answer,
    validate_segments,
)
from segmo.text.llm import (
    get_text_segmenter as get_segmenter,
)
from segmo.text.rules import RuleSegmenter, TextSegmenter
from segmo.text.validate import MAX_ANSWER_CHARS

KIT = Path(__file__).resolve().parents[1].parent / "shared" / "fixtures" / "kitml" / "annotations.json"

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
    with pytest.raises(SegmoError, match="segment_system.md"):
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


@pytest.mark.parametrize("caption, segments, reason", [
    ("a person walks forward, then waves twice", ["it is it"], "names no action"),
    ("a person walks forward, then waves twice", ["a person walks forward"] * 5, "repeated 5 times"),
    ("a person walks forward, then waves twice", ["a person walks forward"], "lose the caption's action(s) ['wave']"),
    ("a person walks forward, then waves twice", ["a person waves twice", "a person walks forward"],
     "out of execution order"),
    ("a man runs after walking", ["a man runs", "a man walks"], "out of execution order"),
    ("before sitting down, a man waves", ["a man sits down", "a man waves"], "out of execution order"),
    ("the person walks forward, turns around and walks back",
     ["the person walks back", "the person turns around", "the person walks forward"], "out of execution order"),
])
def test_degenerate_answers_are_rejected(caption, segments, reason):
    assert reason in validate_segments(caption, segments)


@pytest.mark.parametrize("caption, segments", [
    ("a man runs after walking", ["a man walks", "a man runs"]),  # execution order, not mention
    ("before sitting down, a man waves", ["a man waves", "a man sits down"]),
    ("a person jumps, jumps and jumps", ["a person jumps"] * 3),  # the caption repeats it
    ("a person stands and waves", ["a person stands", "a person waves"]),  # split, order kept
    ("a person walks forward, turns around and walks back",
     ["a person walks forward and turns around", "a person walks back"]),  # merged
    ("A person walks forwards, then a few steps backwards and then forwards again.",
     ["A person walks forwards", "A person walks a few steps backwards", "A person walks forwards again"]),
    ("a person proceeds to walk forward", ["a person walks forward"]),  # light verb dropped
])
def test_legitimate_answers_are_accepted(caption, segments):
    assert validate_segments(caption, segments) is None


def test_rule_outputs_pass_the_validator_on_real_captions():
    """The validator must not reject faithful splits: the rules' own on all KIT captions."""
    if not KIT.is_file():
        pytest.skip(f"KIT-ML captions not found at {KIT} (../shared/fixtures)")
    import json

    captions = [a["text"] for motion in json.loads(KIT.read_text()).values() for a in motion["annotations"]]
    rules = RuleSegmenter()
    rejected = [(c, r) for c in captions[::4] if has_words(c)
                and (r := validate_segments(c, rules.segment_one(c))) is not None]
    assert rejected == []


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


def test_an_answer_over_the_limit_falls_back_as_too_long():
    """An answer past MAX_ANSWER_CHARS is not read; its reason said 'no JSON object found',
    though a reasoning model's long <think> block may hold a good answer at its end."""
    caption = "a man waves then jumps"
    long_answer = "<think>" + "hmm " * 15_000 + '</think>{"segments": ["a man waves", "a man jumps"]}'
    assert len(long_answer) > MAX_ANSWER_CHARS
    seg = _Scripted({caption: [long_answer]}, max_retries=0)
    out, fell_back = seg.segment_with_fallbacks([caption])
    assert out == [RuleSegmenter().segment_one(caption)]
    assert fell_back[0] == f"answer of {len(long_answer):,} characters, longer than the {MAX_ANSWER_CHARS:,} read"


def test_get_segmenter():
    assert isinstance(get_segmenter("rule"), RuleSegmenter)
    seg = get_segmenter("openai", base_url="http://127.0.0.1:9/v1", model="Qwen/Qwen3-8B", concurrency=None)
    assert isinstance(seg, TextSegmenter) and seg.name == "openai-qwen3-8b" and seg.concurrency == 8
    with pytest.raises(ValueError, match="unknown backend"):
        get_segmenter("gpt")
    with pytest.raises(ValueError, match="no option"):
        get_segmenter("rule", model="x")
    with pytest.raises(SegmoError, match="base URL 'localhost:8000' must look like http://HOST"):
        OpenAISegmenter("localhost:8000", "m")
    with pytest.raises(SegmoError, match="not a valid URL"):
        OpenAISegmenter("http://host:port/v1", "m")


# ---------------------------------------------------------------- OpenAI-compatible server
def _client(url, **kwargs):
    options = dict(timeout=0.5, max_retries=1, concurrency=4)
    options.update(kwargs)
    return OpenAISegmenter(url, "tiny", **options)


def test_openai_good_answers_keep_order(monkeypatch):
    monkeypatch.setenv("SEGMO_TEST_KEY", "sk-test")
    captions = ["a person walks forward and waves"] + [f"a person jumps {i} times" for i in range(6)]
    with FakeOpenAI() as server:
        seg = _client(server.url, api_key_env="SEGMO_TEST_KEY")
        out, fell_back = seg.segment_with_fallbacks(captions)
    assert out == RuleSegmenter().segment(captions) and fell_back == {}
    assert seg.fallbacks == 0 and all(server.calls[c] == 1 for c in captions)


def test_structured_output_is_asked_for_and_connections_are_kept_alive():
    captions = [f"a person jumps {i} times then waves" for i in range(5)]
    with FakeOpenAI() as server:
        seg = _client(server.url, concurrency=1)
        assert seg.segment_with_fallbacks(captions)[1] == {}
    formats = [b.get("response_format") for b in server.bodies]
    assert len(formats) == 5 and all(f["type"] == "json_schema" and f["json_schema"]["strict"]
                                     for f in formats)
    schema = formats[0]["json_schema"]["schema"]
    assert schema["required"] == ["segments"] and schema["properties"]["segments"]["maxItems"] == 5
    assert len(server.connections) == 1  # five requests, one connection


def test_progress_moves_with_each_first_answer():
    counts: list[int] = []
    captions = [f"a person bows {i} times then runs" for i in range(6)]
    with FakeOpenAI({captions[0]: "prose-once"}) as server:
        seg = _client(server.url)
        seg.progress = counts.append
        seg.segment(captions)
    assert counts == [1] * 6  # the re-ask of the first caption does not count twice


def test_a_server_without_structured_output_is_asked_without_it():
    captions = [f"a person hops {i} times then bows" for i in range(4)]
    with FakeOpenAI(structured=False) as server:
        seg = _client(server.url, concurrency=1)
        out, fell_back = seg.segment_with_fallbacks(captions)
    assert fell_back == {} and out == RuleSegmenter().segment(captions)
    sent = ["response_format" in b for b in server.bodies]
    assert sent == [True, False, False, False, False]  # refused once, then never sent again
    with FakeOpenAI() as server:
        _client(server.url, structured_output="off").segment(captions[:1])
    assert "response_format" not in server.bodies[0]
    with pytest.raises(SegmoError, match="structured_output"):
        _client("http://127.0.0.1:1/v1", structured_output="yes")


def test_openai_base_url_from_the_environment(monkeypatch):
    with FakeOpenAI() as server:
        monkeypatch.setenv("OPENAI_BASE_URL", server.url)
        seg = OpenAISegmenter(None, "tiny", timeout=0.5)
        assert seg.segment(["a man runs after walking"]) == [["a man walks", "a man runs"]]
    assert server.total == 1


def test_retry_after_is_honoured():
    caption = "a man jumps then sits down"
    with FakeOpenAI({caption: "429-once"}) as server:
        seg = _client(server.url)
        assert seg.segment_with_fallbacks([caption]) == ([["a man jumps", "a man sits down"]], {})
    first, second = server.times[caption]
    assert second - first >= RETRY_AFTER  # the client's own first back-off is at most 0.5 s


# caption -> (fault, what the fallback reason says)
FAULTS = {
    "a person waves then bows": ("500", "HTTP 500"),
    "a person jumps then sits down": ("429", "HTTP 429"),
    "a person crawls then stands up": ("hang", "no answer within 0.5 s"),
    "a person claps then kicks": ("badjson", "unreadable response"),
    "a person spins then falls down": ("invalidjson", "no JSON object"),
    "a person kneels then prays": ("prose", "no JSON object"),
    "a person walks then turns around": ("itisit", "names no action"),
    "a person hops then runs": ("copies", "repeated 5 times"),
    "a person sits down then waves": ("dropped", "lose the caption's action(s) ['wave']"),
    "a person runs after walking": ("reversed", "out of execution order"),
}


def test_openai_faults_are_retried_then_fall_back_with_their_reason(caplog):
    captions = [*FAULTS, "a person walks forward, then waves twice"]
    with FakeOpenAI({c: fault for c, (fault, _) in FAULTS.items()}) as server, caplog.at_level("WARNING"):
        seg = _client(server.url)
        t0 = time.perf_counter()
        out, fell_back = seg.segment_with_fallbacks(captions)
        elapsed = time.perf_counter() - t0
    assert out == RuleSegmenter().segment(captions)  # the run survives every fault
    assert {captions[i]: reason for i, reason in fell_back.items()}.keys() == FAULTS.keys()
    for i, reason in fell_back.items():
        assert FAULTS[captions[i]][1] in reason, (captions[i], reason)
        assert server.calls[captions[i]] == 2  # one retry (transport) or one re-ask (answer)
    assert server.calls[captions[-1]] == 1 and seg.fallbacks == len(FAULTS)
    assert elapsed < 15
    assert "falling back" in caplog.text


HOSTILE_ANSWERS = {  # each was a traceback (exit 1), or text written that is not the caption's
    "deepbody": "unreadable response (RecursionError",
    "number": "the message's content is a int, not text",
    "deep": "answer of 500,000 characters, longer than the 50,000 read",
    "braces": "answer of 300,000 characters, longer than the 50,000 read",
    "foreign": "uses words not in the caption: ['火箭发射到月球']",
    "nul": "holds control characters",
    "surrogate": "holds control characters",
}


@pytest.mark.parametrize("fault", HOSTILE_ANSWERS)
def test_hostile_answers_fall_back_with_a_reason(fault):
    caption = "a person walks forward, then waves twice"
    with FakeOpenAI({caption: fault}) as server:
        t0 = time.perf_counter()
        out, fell_back = _client(server.url, timeout=5.0).segment_with_fallbacks([caption])
    assert out == [RuleSegmenter().segment_one(caption)]
    assert HOSTILE_ANSWERS[fault] in fell_back[0] and len(fell_back[0]) < 400, fell_back
    assert time.perf_counter() - t0 < 10  # "{" * 300,000 took 22 s of parsing per answer


def test_content_parts_are_read_as_the_answer():
    """Some servers send the message's content as a list of parts."""
    caption = "a person walks forward, then waves twice"
    with FakeOpenAI({caption: "parts"}) as server:
        out, fell_back = _client(server.url).segment_with_fallbacks([caption])
    assert out == [RuleSegmenter().segment_one(caption)] and not fell_back


def test_an_api_key_no_http_header_can_carry_is_one_line(monkeypatch):
    """A key with a stray line end failed every request, and the error quoted the key into
    the manifest."""
    monkeypatch.setenv("OPENAI_API_KEY", "sk-SECRET123\r")
    with pytest.raises(SegmoError) as caught:
        OpenAISegmenter("http://127.0.0.1:9/v1", "tiny")
    assert "SECRET" not in str(caught.value) and "$OPENAI_API_KEY" in str(caught.value)


def test_a_caption_the_server_refuses_falls_back_without_retries():
    caption = " ".join(["a person walks forward then waves"] * 1700)  # 10,000 words
    with FakeOpenAI({caption: "400"}) as server:
        # (60 kB to send and parse: a generous timeout, or a busy machine times it out)
        seg = _client(server.url, max_retries=3, timeout=10.0)
        out, fell_back = seg.segment_with_fallbacks([caption])
    assert out == [RuleSegmenter().segment_one(caption)] and server.calls[caption] == 1
    assert fell_back == {0: "request failed: HTTP 400 (Error code: 400 - maximum context length exceeded)"}


def test_rejected_answers_are_re_asked_with_the_reason():
    caption = "a person runs after walking"
    with FakeOpenAI({caption: "reversed-once"}) as server:
        seg = _client(server.url)
        assert seg.segment_with_fallbacks([caption]) == ([["a person walks", "a person runs"]], {})
    assert server.calls[caption] == 2 and seg.stats.retries == 1


def test_openai_configuration_errors_raise():
    with FakeOpenAI({"a person is denied": "401"}) as server:
        with pytest.raises(SegmoError, match=r"HTTP 401 .*--base-url, --model and the API key"):
            _client(server.url).segment(["a person is denied"])
        with pytest.raises(SegmoError, match="HTTP 404"):
            OpenAISegmenter(server.url.replace("/v1", "/v2"), "tiny", timeout=0.5).segment(["a man runs"])


def test_a_dead_server_stops_the_run():
    with FakeOpenAI() as server:
        url = server.url  # closed at the end of the block: nothing listens there any more
    seg = _client(url, max_retries=0, max_failures_in_a_row=3, concurrency=2)
    captions = [f"a person jumps {i} times" for i in range(20)]
    t0 = time.perf_counter()
    with pytest.raises(LLMUnavailableError, match=r"requests in a row failed .*cannot reach"):
        seg.segment(captions)
    assert time.perf_counter() - t0 < 10


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


# Long enough that a loaded machine (the fake server gzips 64 MB before its first byte)
# still answers in time; the trickle and the flood last far longer.
ANSWER_TIMEOUT = 3.0
SLOW_OR_HUGE_ANSWERS = {  # each held a request for ever, or its bytes in memory
    "trickle": f"still arriving {ANSWER_TIMEOUT:g} s after it began",
    "flood": "ran past 1 MiB",
    "gzip": "came compressed (gzip)",
}


@pytest.mark.parametrize("fault", SLOW_OR_HUGE_ANSWERS)
def test_an_answer_is_read_within_the_timeout_and_a_size(fault):
    """httpx's timeout bounds each wait for bytes, not their sum: a server sending a byte
    every 50 ms held a request for 20 s with --timeout 1, and an endless body was read into
    memory (1.3 GB in 3 s). A gzip of 64 MB is 64 KB on the wire. (With a 1 s timeout the
    gzip and flood cases failed now and then on a loaded machine, before the first byte.)"""
    caption = "a person walks forward, then waves twice"
    with FakeOpenAI({caption: fault}) as server:
        t0 = time.perf_counter()
        out, fell_back = _client(server.url, timeout=ANSWER_TIMEOUT, max_retries=0).segment_with_fallbacks(
            [caption])
        elapsed = time.perf_counter() - t0
    assert out == [RuleSegmenter().segment_one(caption)]
    assert SLOW_OR_HUGE_ANSWERS[fault] in fell_back[0], fell_back
    assert server.calls[caption] == 1  # not asked again
    assert elapsed < 2 * ANSWER_TIMEOUT + 4  # the trickle alone lasts about 20 s


def test_requests_ask_for_uncompressed_answers():
    """So that the bytes read are the bytes held (see the "gzip" fault above)."""
    with FakeOpenAI() as server:
        _client(server.url).segment(["a person walks forward, then waves twice"])
    assert server.headers[0]["accept-encoding"] == "identity"


@pytest.mark.parametrize("options, expected", [
    ({"max_retries": 21}, "max_retries must be in [0, 20], got 21"),
    ({"concurrency": 1025}, "concurrency must be in [1, 1024], got 1025"),
])
def test_retries_and_concurrency_are_bounded(options, expected):
    with pytest.raises(SegmoError) as caught:
        OpenAISegmenter("http://127.0.0.1:9/v1", "tiny", **options)
    assert expected in str(caught.value)
