"""LLM text-segment extraction: prompt, answer parsing/validation, and two backends.

Both backends ask a chat model for ``{"segments": [...]}`` with the prompt in
``prompts/`` (system rules from spec §7 + few-shot examples), check every answer with
`validate_segments`, re-ask up to ``max_retries`` times with the reason of the rejection,
and otherwise fall back to `RuleSegmenter` with a logged warning; `fallbacks` counts
those captions.

- `OpenAISegmenter`: any OpenAI-compatible ``/v1/chat/completions`` server (vLLM,
  llama.cpp, Ollama, OpenAI), stdlib HTTP only, requests in a thread pool, exponential
  back-off on timeouts, 429 and 5xx.
- `TransformersSegmenter`: a local causal LM through `AutoModelForCausalLM`, greedy.

Example (a vLLM server with Qwen3-8B)::

    seg = OpenAISegmenter("http://localhost:8000/v1", "Qwen/Qwen3-8B",
                          extra_body={"chat_template_kwargs": {"enable_thinking": False}})
    seg.segment(["a man runs after walking"])  # [["a man walks", "a man runs"]]
"""

from __future__ import annotations

import hashlib
import http.client
import json
import logging
import os
import re
import time
import urllib.error
import urllib.request
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from segmo.text.rules import MAX_SEGMENTS, RuleSegmenter, TextSegmenter, lemma

log = logging.getLogger(__name__)

PROMPT_DIR = Path(__file__).resolve().parents[2] / "prompts"
# Words an answer may add to the caption's own: a restored subject and light glue.
_ALLOWED_EXTRA = set("""a an the person man woman human someone somebody he she they it his her
their is are and then subject figure""".split())
_THINK_RE = re.compile(r"<think>.*?(</think>|$)", re.DOTALL | re.IGNORECASE)
_WORD_RE = re.compile(r"[A-Za-z]+|[0-9]+")


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
    """Read ``segment_system.md`` and ``segment_examples.json`` from `directory` (default prompts/)."""
    directory = Path(directory) if directory is not None else PROMPT_DIR
    system_path, examples_path = directory / "segment_system.md", directory / "segment_examples.json"
    for path in (system_path, examples_path):
        if not path.is_file():
            raise FileNotFoundError(f"load_prompt: missing prompt file {path}")
    try:
        raw = json.loads(examples_path.read_text(encoding="utf-8"))
        examples = tuple((e["caption"], tuple(e["segments"])) for e in raw)
    except (json.JSONDecodeError, KeyError, TypeError) as err:
        raise ValueError(f"load_prompt: {examples_path} must be a JSON list of "
                         f"{{'caption', 'segments'}} objects ({err})") from err
    return Prompt(system_path.read_text(encoding="utf-8").strip(), examples)


# ---------------------------------------------------------------- answers
def parse_answer(text: str) -> list[str] | None:
    """Segments from a model answer, or None if there is no ``{"segments": [str, ...]}`` in it.

    Tolerates ``<think>...</think>`` blocks (Qwen3), code fences and text around the JSON.
    """
    text = _THINK_RE.sub("", text)
    text = re.sub(r"```(?:json)?", "", text)
    decoder = json.JSONDecoder()
    for match in re.finditer(r"\{", text):
        try:
            obj, _ = decoder.raw_decode(text, match.start())
        except json.JSONDecodeError:
            continue
        if isinstance(obj, dict) and isinstance(obj.get("segments"), list):
            segments = obj["segments"]
            if all(isinstance(s, str) for s in segments):
                return [s.replace("#", " ").strip().rstrip(".!?;,").strip() for s in segments]
    return None


def validate_segments(caption: str, segments: list[str] | None, max_segments: int = MAX_SEGMENTS,
                      length_margin: int = 40) -> str | None:
    """Why `segments` is not an acceptable answer for `caption`, or None if it is.

    Accepted: 1..max_segments non-empty segments, each at most ``len(caption) +
    length_margin`` characters and made only of the caption's words up to inflection
    (see `segmo.text.rules.lemma`), plus a restored subject.
    """
    if segments is None:
        return 'no JSON object {"segments": [...]} found'
    if not 1 <= len(segments) <= max_segments:
        return f"expected 1 to {max_segments} segments, got {len(segments)}"
    allowed = {lemma(w) for w in _WORD_RE.findall(caption)} | _ALLOWED_EXTRA
    for s in segments:
        if not s.strip():
            return "empty segment"
        if len(s) > len(caption) + length_margin:
            return f"segment longer than the caption: {s!r}"
        foreign = [w for w in _WORD_RE.findall(s) if lemma(w) not in allowed and w.lower() not in allowed]
        if foreign:
            return f"segment {s!r} uses words not in the caption: {foreign}"
    return None


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
        if max_retries < 0:
            raise ValueError(f"{type(self).__name__}: max_retries must be >= 0, got {max_retries}")
        self.prompt = prompt if prompt is not None else load_prompt()
        self.max_retries = max_retries
        self.max_segments = max_segments
        self.length_margin = length_margin
        self.fallback = RuleSegmenter(max_segments)
        self.stats = LLMStats()

    @property
    def fallbacks(self) -> int:
        return self.stats.fallbacks

    def _complete_many(self, conversations: list[list[dict[str, str]]]) -> list[str | Exception]:
        """One answer (or the exception that prevented it) per conversation."""
        raise NotImplementedError

    def segment(self, texts: list[str]) -> list[list[str]]:
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
            answers = self._complete_many([conversations[i] for i in pending])
            still = []
            for i, answer in zip(pending, answers):
                if isinstance(answer, Exception):
                    reasons[i] = f"request failed: {answer}"
                    continue  # transport errors were already retried with back-off
                segments = parse_answer(answer)
                reason = validate_segments(texts[i], segments, self.max_segments, self.length_margin)
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
        for i, segments in enumerate(results):
            if segments is None:
                self.stats.fallbacks += 1
                self.stats.reasons = (self.stats.reasons + [reasons.get(i, "")])[-20:]
                log.warning("%s: falling back to rules for %r (%s)", self.name, texts[i], reasons.get(i))
                results[i] = self.fallback.segment_one(texts[i])
        self.stats.captions += len(texts)
        return results  # type: ignore[return-value]


# ---------------------------------------------------------------- OpenAI-compatible HTTP
class OpenAISegmenter(LLMSegmenter):
    """Chat-completions client for any OpenAI-compatible server.

    `base_url` includes the API version (``http://host:8000/v1``); the key is read from
    the environment variable `api_key_env` and may be absent for local servers.
    Timeouts, connection errors, 429 and 5xx are retried `max_retries` times after
    ``backoff * 2**attempt`` seconds; other HTTP errors (401, 404, ...) raise at once,
    since they mean a wrong configuration rather than a bad caption.
    """

    def __init__(self, base_url: str, model: str, api_key_env: str = "OPENAI_API_KEY",
                 concurrency: int = 8, timeout: float = 60.0, max_retries: int = 3,
                 backoff: float = 1.0, temperature: float = 0.0, max_tokens: int = 512,
                 extra_body: dict[str, Any] | None = None, prompt: Prompt | None = None,
                 max_segments: int = MAX_SEGMENTS) -> None:
        super().__init__(prompt, max_retries, max_segments)
        if not base_url.startswith(("http://", "https://")):
            raise ValueError(f"OpenAISegmenter: base_url must start with http:// or https://, got {base_url!r}")
        if concurrency < 1:
            raise ValueError(f"OpenAISegmenter: concurrency must be >= 1, got {concurrency}")
        self.url = base_url.rstrip("/") + "/chat/completions"
        self.model = model
        self.api_key = os.environ.get(api_key_env, "")
        self.concurrency, self.timeout, self.backoff = concurrency, timeout, backoff
        self.body = {"model": model, "temperature": temperature, "max_tokens": max_tokens, **(extra_body or {})}
        self.name = f"openai-{_slug(model)}"

    def _request(self, messages: list[dict[str, str]]) -> str | Exception:
        """The answer text, or the last transport error once the retries are spent."""
        data = json.dumps({**self.body, "messages": messages}).encode("utf-8")
        headers = {"Content-Type": "application/json"}
        if self.api_key:
            headers["Authorization"] = f"Bearer {self.api_key}"
        error: Exception = RuntimeError("no request made")
        for attempt in range(self.max_retries + 1):
            try:
                req = urllib.request.Request(self.url, data=data, headers=headers, method="POST")
                with urllib.request.urlopen(req, timeout=self.timeout) as response:
                    payload = json.loads(response.read().decode("utf-8"))
                return payload["choices"][0]["message"]["content"] or ""
            except urllib.error.HTTPError as err:
                if err.code != 429 and err.code < 500:
                    raise RuntimeError(f"OpenAISegmenter: {self.url} answered HTTP {err.code}: "
                                       f"{err.read()[:200]!r}") from err
                error = err
            except (urllib.error.URLError, TimeoutError, ConnectionError, http.client.HTTPException) as err:
                error = err
            except (json.JSONDecodeError, KeyError, IndexError, TypeError) as err:
                return f"<unreadable response: {err}>"  # validated (and re-asked) upstream
            if attempt < self.max_retries:
                time.sleep(self.backoff * 2**attempt)
        return error  # handed to the rule fallback by the caller

    def _complete_many(self, conversations: list[list[dict[str, str]]]) -> list[str | Exception]:
        if len(conversations) == 1:
            return [self._request(conversations[0])]
        with ThreadPoolExecutor(max_workers=self.concurrency) as pool:
            return list(pool.map(self._request, conversations))


# ---------------------------------------------------------------- local transformers model
class TransformersSegmenter(LLMSegmenter):
    """A local chat model (`AutoModelForCausalLM`), greedy decoding, batched."""

    def __init__(self, model_name_or_path: str, device: str = "cpu", max_new_tokens: int = 256,
                 batch_size: int = 8, max_retries: int = 1, enable_thinking: bool = False,
                 prompt: Prompt | None = None, max_segments: int = MAX_SEGMENTS) -> None:
        super().__init__(prompt, max_retries, max_segments)
        from transformers import AutoModelForCausalLM, AutoTokenizer  # heavy, import on use

        if batch_size < 1:
            raise ValueError(f"TransformersSegmenter: batch_size must be >= 1, got {batch_size}")
        self.tokenizer = AutoTokenizer.from_pretrained(model_name_or_path)
        self.tokenizer.padding_side = "left"  # generation continues the right end
        if self.tokenizer.pad_token is None:
            self.tokenizer.pad_token = self.tokenizer.eos_token
        if getattr(self.tokenizer, "chat_template", None) is None:
            raise ValueError(f"TransformersSegmenter: {model_name_or_path} has no chat template")
        self.model = AutoModelForCausalLM.from_pretrained(model_name_or_path).to(device).eval()
        self.device, self.max_new_tokens, self.batch_size = device, max_new_tokens, batch_size
        self.enable_thinking = enable_thinking
        self.model_name = str(model_name_or_path)
        self.name = f"transformers-{_slug(str(model_name_or_path))}"

    def _complete_many(self, conversations: list[list[dict[str, str]]]) -> list[str | Exception]:
        import torch

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
        return answers


def get_segmenter(backend: str, **options: Any) -> TextSegmenter:
    """Build a segmenter by backend name: "rule", "openai" or "transformers".

    Options are the backend's constructor arguments; None values are dropped so that
    unset CLI flags keep the defaults.
    """
    options = {k: v for k, v in options.items() if v is not None}
    if backend == "rule":
        extra = set(options) - {"max_segments"}
        if extra:
            raise ValueError(f"get_segmenter: the rule backend takes no option(s) {sorted(extra)}")
        return RuleSegmenter(**options)
    if backend == "openai":
        return OpenAISegmenter(**options)
    if backend == "transformers":
        return TransformersSegmenter(**options)
    raise ValueError(f"get_segmenter: unknown backend {backend!r} (choose rule, openai, transformers)")
