"""LLM text-segment extraction: prompt, the retry/fallback loop, and two backends.

Both backends ask a chat model for ``{"segments": [...]}`` with the prompt in
``prompts/`` (system rules from spec §7 + few-shot examples), check every answer against
its caption with `segmo.text.validate.validate_segments` (content words from the caption,
no empty or duplicated segment, no action lost, execution order), re-ask up to
``max_retries`` times with the reason of the rejection, and otherwise fall back to
`RuleSegmenter`. `segment_with_fallbacks` says which captions fell back and why, so that
`segment-texts` records them on disk and retries them on the next run.

- `OpenAISegmenter`: any OpenAI-compatible ``/v1/chat/completions`` server (vLLM,
  llama.cpp, Ollama, OpenAI) through the official `openai` client: kept-alive
  connections, a timeout per request, retries of timeouts, 408/409/429 and 5xx with
  exponential back-off that honours ``Retry-After``. A 401/403/404 (wrong key, URL or
  model) raises `SegmoError` at once; when ``max_failures_in_a_row`` requests fail one
  after another the server is taken to be down and `LLMUnavailableError` stops the run.
- `TransformersSegmenter`: a local causal LM through `AutoModelForCausalLM`, greedy.

Example (a vLLM server with Qwen3-8B)::

    seg = OpenAISegmenter("http://localhost:8000/v1", "Qwen/Qwen3-8B",
                          extra_body={"chat_template_kwargs": {"enable_thinking": False}})
    seg.segment(["a man runs after walking"])  # [["a man walks", "a man runs"]]
"""

from __future__ import annotations

import functools
import hashlib
import importlib
import json
import logging
import math
import os
import re
import threading
import time
import urllib.parse
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from importlib.resources import files
from pathlib import Path
from typing import Any

from segmo.errors import SegmoError
from segmo.text.rules import MAX_SEGMENTS, RuleSegmenter, TextSegmenter
from segmo.text.validate import MAX_ANSWER_CHARS, answer_schema, parse_answer, validate_segments

__all__ = ["LLMSegmenter", "LLMUnavailableError", "OpenAISegmenter", "Prompt", "TransformersSegmenter",
           "get_text_segmenter", "load_prompt", "parse_answer", "validate_segments"]

log = logging.getLogger(__name__)

# The top-level prompts/ folder, shipped inside the package (pyproject.toml maps it to
# segmo._prompts), so that an installed segmo finds it as well as a source checkout.
PROMPT_DIR = files("segmo._prompts")
# Words of a 400 that refuses response_format (not, say, a caption over the context length).
_FORMAT_WORDS = ("response_format", "json_schema", "schema", "structured", "guided")
UNREADABLE = "<unreadable response"  # how a backend hands a broken answer to the re-ask loop
# A server's response is read up to this size: an answer is read up to MAX_ANSWER_CHARS
# (50,000) characters, which JSON-escaped take at most 300 KB.
MAX_RESPONSE_BYTES = 1 << 20
# Bounds of the options: each retry of a failed request waits up to 8 s (or a server's
# Retry-After, up to two minutes), so more retries only wait on a broken server; and the
# server is taken to be down after max(16, 2 * concurrency) failures in a row.
MAX_RETRIES = 20
MAX_CONCURRENCY = 1024


class LLMUnavailableError(SegmoError):
    """The server failed so many requests in a row that asking on would only fall back."""


# ---------------------------------------------------------------- prompt
@dataclass(frozen=True)
class Prompt:
    """System rules and few-shot (caption, segments) pairs."""

    system: str
    examples: tuple[tuple[str, tuple[str, ...]], ...]

    @property
    def hash(self) -> str:
        """Short content hash, stored in ``meta.json`` so that outputs name their prompt."""
        payload = json.dumps([self.system, self.examples], ensure_ascii=False)
        return hashlib.sha256(payload.encode("utf-8")).hexdigest()[:16]

    def messages(self, caption: str) -> list[dict[str, str]]:
        """Chat messages: system, the examples as user/assistant turns, then the caption."""
        out = [{"role": "system", "content": self.system}]
        for text, segments in self.examples:
            out.append({"role": "user", "content": text})
            out.append({"role": "assistant", "content": json.dumps({"segments": list(segments)})})
        out.append({"role": "user", "content": caption})
        return out


def load_prompt(directory: str | Path | None = None) -> Prompt:
    """Read ``segment_system.md`` and ``segment_examples.json`` from `directory` (default:
    the prompts shipped with segmo, the repository's prompts/ folder)."""
    directory = Path(directory) if directory is not None else PROMPT_DIR
    system_path, examples_path = directory / "segment_system.md", directory / "segment_examples.json"
    for path in (system_path, examples_path):
        if not path.is_file():
            raise SegmoError(f"missing prompt file {path}")
    try:
        raw = json.loads(examples_path.read_text(encoding="utf-8"))
        examples = tuple((e["caption"], tuple(e["segments"])) for e in raw)
    except (json.JSONDecodeError, KeyError, TypeError) as err:
        raise SegmoError(f"{examples_path} must be a JSON list of {{'caption', 'segments'}} "
                         f"objects ({err})") from err
    return Prompt(system_path.read_text(encoding="utf-8").strip(), examples)


def _slug(model: str) -> str:
    return re.sub(r"[^a-z0-9.]+", "-", model.rstrip("/").split("/")[-1].lower()).strip("-")


# ---------------------------------------------------------------- shared loop
@dataclass
class LLMStats:
    """Counters of one segmenter's lifetime."""

    captions: int = 0
    requests: int = 0
    retries: int = 0  # re-asks after an invalid answer
    fallbacks: int = 0  # captions answered by RuleSegmenter
    reasons: list[str] = field(default_factory=list)  # last few rejection reasons


class LLMSegmenter:
    """Validation, retry and fallback around `_complete_many` (implemented by backends)."""

    name = "llm"

    def __init__(self, prompt: Prompt | None = None, max_retries: int = 3,
                 max_segments: int = MAX_SEGMENTS, length_margin: int = 40) -> None:
        if not 0 <= max_retries <= MAX_RETRIES:
            raise SegmoError(f"{type(self).__name__}: max_retries must be in [0, {MAX_RETRIES}], "
                             f"got {max_retries}")
        self.prompt = prompt if prompt is not None else load_prompt()
        self.max_retries = max_retries
        self.max_segments = max_segments
        self.length_margin = length_margin
        self.fallback = RuleSegmenter(max_segments)
        self.stats = LLMStats()
        # Called with a count as first answers arrive (a progress bar per caption);
        # `segment-texts` sets it.
        self.progress: Any = None

    @property
    def fallbacks(self) -> int:
        return self.stats.fallbacks

    def _complete_many(self, conversations: list[list[dict[str, str]]],
                       progress: Any = None) -> list[str | Exception]:
        """One answer (or the exception that prevented it) per conversation; `progress`,
        when given, is called with the number of answers as they arrive."""
        raise NotImplementedError

    def segment(self, texts: list[str]) -> list[list[str]]:
        return self.segment_with_fallbacks(texts)[0]

    def segment_with_fallbacks(self, texts: list[str]) -> tuple[list[list[str]], dict[int, str]]:
        """Segments of every text, and {index: reason} of the texts that fell back to rules.

        A text without content is answered by the rules without asking (not a fallback).
        """
        results: list[list[str] | None] = [None] * len(texts)
        conversations = {i: self.prompt.messages(t) for i, t in enumerate(texts) if t.strip()}
        for i, t in enumerate(texts):
            if not t.strip():
                results[i] = self.fallback.segment_one(t)  # nothing to ask about
        pending, reasons = sorted(conversations), {}
        for attempt in range(self.max_retries + 1):
            if not pending:
                break
            if attempt:
                self.stats.retries += len(pending)
            self.stats.requests += len(pending)
            asked = [conversations[i] for i in pending]
            if attempt == 0 and self.progress is not None:
                answers = self._complete_many(asked, progress=self.progress)
            else:
                answers = self._complete_many(asked)
            still = []
            for i, answer in zip(pending, answers):
                if isinstance(answer, Exception):
                    reasons[i] = f"request failed: {answer}"
                    continue  # transport errors were already retried with back-off
                segments = parse_answer(answer)
                reason = validate_segments(texts[i], segments, self.max_segments, self.length_margin)
                if segments is None and answer.startswith(UNREADABLE):
                    reason = answer[1:-1]
                elif segments is None and len(answer) > MAX_ANSWER_CHARS:  # not read, not "no JSON"
                    reason = f"answer of {len(answer):,} characters, longer than the {MAX_ANSWER_CHARS:,} read"
                if reason is None:
                    results[i] = segments
                    continue
                reasons[i] = reason
                still.append(i)
                conversations[i] = conversations[i] + [
                    {"role": "assistant", "content": answer},
                    {"role": "user", "content": f"Invalid answer: {reason}. Follow the rules and "
                                                'answer with JSON only: {"segments": [...]}'},
                ]
            pending = still
        fell_back = {}
        for i, segments in enumerate(results):
            if segments is None:
                fell_back[i] = reasons.get(i, "no answer")
                self.stats.fallbacks += 1
                self.stats.reasons = (self.stats.reasons + [fell_back[i]])[-20:]
                log.warning("%s: falling back to rules for %r (%s)", self.name, texts[i], fell_back[i])
                results[i] = self.fallback.segment_one(texts[i])
        self.stats.captions += len(texts)
        return results, fell_back  # type: ignore[return-value]


# ---------------------------------------------------------------- OpenAI-compatible server
class ResponseLimitError(RuntimeError):
    """A response ran past its size or time bound, or came compressed; reading stopped."""


@functools.cache
def _bounded_stream_class(library: Any) -> type:
    """A body stream of `library` (httpx or httpx2) that stops at MAX_RESPONSE_BYTES or a deadline."""

    class BoundedStream(library.SyncByteStream):
        def __init__(self, stream: Any, seconds: float) -> None:
            self.stream, self.seconds = stream, seconds
            self.deadline = time.monotonic() + seconds

        def __iter__(self) -> Any:
            size = 0
            for chunk in self.stream:
                size += len(chunk)
                if size > MAX_RESPONSE_BYTES:
                    raise ResponseLimitError(f"the answer ran past {MAX_RESPONSE_BYTES >> 20} MiB; "
                                             "stopped reading it")
                if time.monotonic() > self.deadline:
                    raise ResponseLimitError(f"the answer was still arriving {self.seconds:g} s "
                                             "after it began; stopped reading it")
                yield chunk

        def close(self) -> None:
            self.stream.close()

    return BoundedStream


def bounded_http_client(openai: Any, timeout: float) -> Any:
    """openai's default HTTP client, reading every response body within `timeout` seconds
    of its headers and up to MAX_RESPONSE_BYTES.

    The client's own timeout bounds each wait for bytes, not their sum: a server sending
    one byte a second, or bytes without end, would otherwise hold a request, and memory,
    for ever. Answers are asked for uncompressed (``Accept-Encoding: identity``), so that
    the size read is the size held; a compressed answer is refused.
    """
    client_class = openai.DefaultHttpxClient  # openai's defaults (limits, redirects)
    # the library the installed openai is built on: httpx2, or httpx for older releases
    base = next(c for c in client_class.__mro__ if c.__name__ == "Client")
    stream_class = _bounded_stream_class(importlib.import_module(base.__module__.split(".")[0]))

    def bound(response: Any) -> None:
        encoding = response.headers.get("content-encoding", "identity").strip().lower()
        if encoding not in ("", "identity"):
            raise ResponseLimitError(f"the answer came compressed ({encoding}) although none was "
                                     "asked for")
        response.stream = stream_class(response.stream, timeout)

    return client_class(timeout=timeout, headers={"Accept-Encoding": "identity"},
                        event_hooks={"response": [bound]})


def check_base_url(url: str) -> str:
    """`url` if it is an http(s) URL with a host (and a valid port); SegmoError otherwise."""
    try:
        parts = urllib.parse.urlsplit(url)
        parts.port  # noqa: B018 -- raises ValueError for a port that is not a number
    except ValueError as err:
        raise SegmoError(f"base URL {url!r} is not a valid URL ({err})") from err
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise SegmoError(f"base URL {url!r} must look like http://HOST:PORT/v1")
    return url


class OpenAISegmenter(LLMSegmenter):
    """Chat-completions client for any OpenAI-compatible server (the `openai` package).

    `base_url` includes the API version (``http://host:8000/v1``); None reads
    ``OPENAI_BASE_URL``. The key is read from the environment variable `api_key_env`
    and may be absent for local servers. `timeout` (seconds) is the longest wait for the
    server (to connect, or for the next bytes of an answer), and the longest an answer may
    take to arrive once it begins; an answer is read up to 1 MiB. Timeouts, connection errors,
    408/409/429 and 5xx are retried `max_retries` times by the client, after the server's
    ``Retry-After`` when it sends one (up to two minutes) and otherwise with exponential
    back-off from 0.5 s. A request still failing then makes its caption fall back to the
    rules; 401/403/404 raise `SegmoError`, since they mean a wrong configuration rather
    than a bad caption. After `max_failures_in_a_row` failed requests (default
    ``max(16, 2 * concurrency)``) with no success in between, the rest is not asked and
    `LLMUnavailableError` is raised.

    structured_output: "auto" (default) sends a strict JSON-schema ``response_format``
    (`segmo.text.validate.answer_schema`), so that servers that constrain decoding (vLLM,
    llama.cpp, Ollama, OpenAI) can only answer ``{"segments": [...]}``; a server that
    refuses the field (an HTTP 400 that names it) is asked again without it, and not sent
    it again.
    "json_schema" always sends it, "off" never does. The answer is checked either way.
    """

    def __init__(self, base_url: str | None, model: str, api_key_env: str = "OPENAI_API_KEY",
                 concurrency: int = 8, timeout: float = 60.0, max_retries: int = 3,
                 temperature: float = 0.0, max_tokens: int = 512,
                 extra_body: dict[str, Any] | None = None, prompt: Prompt | None = None,
                 max_segments: int = MAX_SEGMENTS, max_failures_in_a_row: int | None = None,
                 structured_output: str = "auto") -> None:
        super().__init__(prompt, max_retries, max_segments)
        import openai  # import on use: `segmo --help` and the rule backend stay fast

        if structured_output not in ("auto", "json_schema", "off"):
            raise SegmoError(f"OpenAISegmenter: structured_output must be auto, json_schema or off, "
                             f"got {structured_output!r}")

        base_url = base_url or os.environ.get("OPENAI_BASE_URL")
        if not base_url:
            raise SegmoError("OpenAISegmenter: no base URL (pass base_url / --base-url, or set "
                             "OPENAI_BASE_URL)")
        if not 1 <= concurrency <= MAX_CONCURRENCY:
            raise SegmoError(f"OpenAISegmenter: concurrency must be in [1, {MAX_CONCURRENCY}], "
                             f"got {concurrency}")
        if not (timeout > 0 and math.isfinite(timeout)):
            raise SegmoError(f"OpenAISegmenter: timeout must be a positive number of seconds, got {timeout}")
        self.base_url = check_base_url(base_url).rstrip("/")
        self.model = model
        self.api_key_env = api_key_env
        self.concurrency, self.timeout = concurrency, timeout
        key = os.environ.get(api_key_env) or "none"
        if not (key.isascii() and key.isprintable()) or any(c.isspace() for c in key):
            # httpx would refuse it for every caption, and quote it in the manifest
            raise SegmoError(f"${api_key_env}: the API key holds a character an HTTP header "
                             "cannot carry (a line end, a space, a non-ASCII letter); fix the "
                             "variable")
        self.client = openai.OpenAI(base_url=self.base_url, api_key=key, timeout=timeout,
                                    max_retries=max_retries,
                                    http_client=bounded_http_client(openai, timeout))
        self.options = {"temperature": temperature, "max_tokens": max_tokens}
        self.extra_body = extra_body
        self.name = f"openai-{_slug(model)}"
        self.max_failures_in_a_row = max_failures_in_a_row or max(16, 2 * concurrency)
        self._lock = threading.Lock()
        self._failures_in_a_row = 0
        self._last_failure = ""
        self.structured_output = structured_output
        self._schema_refused = False  # "auto": the server answered 400 to response_format
        self.response_format = {"type": "json_schema", "json_schema": {
            "name": "text_segments", "strict": True, "schema": answer_schema(max_segments)}}

    def _failed(self, reason: str) -> RuntimeError:
        with self._lock:
            self._failures_in_a_row += 1
            self._last_failure = reason
        return RuntimeError(reason)

    def _request(self, messages: list[dict[str, str]]) -> str | Exception:
        """The answer text, or the error that remained once the client's retries were spent."""
        import openai  # on use, as in __init__

        if self._failures_in_a_row >= self.max_failures_in_a_row:
            return RuntimeError("not asked: the server is down")
        structured = self.structured_output == "json_schema" or (
            self.structured_output == "auto" and not self._schema_refused)
        try:
            try:
                completion = self.client.chat.completions.create(
                    model=self.model, messages=messages, extra_body=self.extra_body, **self.options,
                    **({"response_format": self.response_format} if structured else {}))
            except openai.BadRequestError as err:
                about_format = any(w in str(err.message).lower() for w in _FORMAT_WORDS)
                if not structured or self.structured_output != "auto" or not about_format:
                    raise
                # A server without structured output refuses the field: ask again without it.
                completion = self.client.chat.completions.create(
                    model=self.model, messages=messages, extra_body=self.extra_body, **self.options)
                with self._lock:
                    if not self._schema_refused:
                        log.info("%s refused response_format (json_schema); asking without it",
                                 self.base_url)
                    self._schema_refused = True
        except (openai.AuthenticationError, openai.PermissionDeniedError, openai.NotFoundError) as err:
            raise SegmoError(f"{self.base_url} answered HTTP {err.status_code} for model "
                             f"{self.model!r} ({str(err.message)[:200]}); check --base-url, --model "
                             f"and the API key in ${self.api_key_env}") from err
        except openai.APIStatusError as err:
            retried = err.status_code in (408, 409, 429) or err.status_code >= 500
            return self._failed(f"HTTP {err.status_code} ({' '.join(str(err.message).split())[:120]})"
                                + (f" after {self.max_retries} retries" if retried else ""))
        except openai.APITimeoutError:
            return self._failed(f"no answer within {self.timeout:g} s, {self.max_retries} retries")
        except ResponseLimitError as err:  # a hostile or broken server: not asked again
            return self._failed(str(err))
        except openai.APIConnectionError as err:
            if isinstance(err.__cause__, ResponseLimitError):  # older openai releases wrap it
                return self._failed(str(err.__cause__))
            return self._failed(f"cannot reach {self.base_url} ({err.__cause__ or err}), "
                                f"{self.max_retries} retries")
        except (openai.APIResponseValidationError, ValueError, TypeError, KeyError,
                RecursionError) as err:
            # a broken body (invalid JSON) from a live server: validated, so re-asked, upstream
            return f"{UNREADABLE} ({type(err).__name__}: {str(err)[:120]})>"
        with self._lock:
            self._failures_in_a_row = 0
        choices = getattr(completion, "choices", None) or []
        message = getattr(choices[0], "message", None) if choices else None
        content = getattr(message, "content", None) or ""  # an empty answer is re-asked upstream
        if isinstance(content, list):  # content parts, as some servers send them
            content = "".join(part.get("text") or "" for part in content if isinstance(part, dict)
                              and isinstance(part.get("text"), str))
        if not isinstance(content, str):
            return f"{UNREADABLE} (the message's content is a {type(content).__name__}, not text)>"
        return content

    def _complete_many(self, conversations: list[list[dict[str, str]]],
                       progress: Any = None) -> list[str | Exception]:
        def ask(conversation: list[dict[str, str]]) -> str | Exception:
            answer = self._request(conversation)
            if progress is not None:
                progress(1)
            return answer

        if len(conversations) == 1:
            answers = [ask(conversations[0])]
        else:
            pool = ThreadPoolExecutor(max_workers=self.concurrency)
            try:
                answers = list(pool.map(ask, conversations))
            except BaseException:  # Ctrl-C: the requests not yet sent are not sent
                pool.shutdown(wait=False, cancel_futures=True)
                raise
            pool.shutdown()
        if self._failures_in_a_row >= self.max_failures_in_a_row:
            raise LLMUnavailableError(
                f"{self.base_url}: {self._failures_in_a_row} requests in a row failed (last: "
                f"{self._last_failure}); stopped asking. The files written so far are kept: re-run "
                "when the server answers")
        return answers


# ---------------------------------------------------------------- local transformers model
class TransformersSegmenter(LLMSegmenter):
    """A local chat model (`AutoModelForCausalLM`), greedy decoding, batched."""

    def __init__(self, model_name_or_path: str, device: str = "cpu", max_new_tokens: int = 256,
                 batch_size: int = 8, max_retries: int = 1, enable_thinking: bool = False,
                 prompt: Prompt | None = None, max_segments: int = MAX_SEGMENTS) -> None:
        super().__init__(prompt, max_retries, max_segments)
        from transformers import AutoModelForCausalLM, AutoTokenizer  # heavy, import on use

        if batch_size < 1:
            raise SegmoError(f"TransformersSegmenter: batch_size must be >= 1, got {batch_size}")
        try:
            self.tokenizer = AutoTokenizer.from_pretrained(model_name_or_path)
        except (OSError, ValueError) as err:  # not a model directory / hub model here
            raise SegmoError(f"--model {model_name_or_path}: cannot load a tokenizer "
                             f"({' '.join(str(err).split())[:200]})") from err
        self.tokenizer.padding_side = "left"  # generation continues the right end
        if self.tokenizer.pad_token is None:
            self.tokenizer.pad_token = self.tokenizer.eos_token
        if getattr(self.tokenizer, "chat_template", None) is None:
            raise SegmoError(f"TransformersSegmenter: {model_name_or_path} has no chat template")
        self.model = AutoModelForCausalLM.from_pretrained(model_name_or_path).to(device).eval()
        self.device, self.max_new_tokens, self.batch_size = device, max_new_tokens, batch_size
        self.enable_thinking = enable_thinking
        self.model_name = str(model_name_or_path)
        self.name = f"transformers-{_slug(str(model_name_or_path))}"

    def _complete_many(self, conversations: list[list[dict[str, str]]],
                       progress: Any = None) -> list[str | Exception]:
        import torch  # with transformers, on use: the rule and server backends run without it

        answers: list[str | Exception] = []
        for start in range(0, len(conversations), self.batch_size):
            chunk = conversations[start : start + self.batch_size]
            texts = [
                self.tokenizer.apply_chat_template(c, tokenize=False, add_generation_prompt=True,
                                                   enable_thinking=self.enable_thinking)
                for c in chunk
            ]
            batch = self.tokenizer(texts, return_tensors="pt", padding=True, add_special_tokens=False)
            batch = batch.to(self.device)
            with torch.no_grad():
                out = self.model.generate(**batch, do_sample=False, max_new_tokens=self.max_new_tokens,
                                          pad_token_id=self.tokenizer.pad_token_id)
            new = out[:, batch["input_ids"].shape[1] :]  # (b, new tokens)
            answers += self.tokenizer.batch_decode(new, skip_special_tokens=True)
            if progress is not None:
                progress(len(chunk))
        return answers


def get_text_segmenter(backend: str, **options: Any) -> TextSegmenter:
    """Build a segmenter by backend name: "rule", "openai" or "transformers".

    Options are the backend's constructor arguments; None values are dropped so that
    unset CLI flags keep the defaults.
    """
    options = {k: v for k, v in options.items() if v is not None}
    if backend == "rule":
        extra = set(options) - {"max_segments"}
        if extra:
            raise SegmoError(f"get_text_segmenter: the rule backend takes no option(s) {sorted(extra)}")
        return RuleSegmenter(**options)
    if backend == "openai":
        return OpenAISegmenter(**options)
    if backend == "transformers":
        return TransformersSegmenter(**options)
    raise SegmoError(f"get_text_segmenter: unknown backend {backend!r} (choose rule, openai, transformers)")
