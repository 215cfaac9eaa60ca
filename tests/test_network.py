"""Without a network, a hub name fails at once with the reason, instead of after
huggingface_hub's five retries of the name lookup (about 25 s and five warnings)."""

from __future__ import annotations

import socket
import time

import pytest

from segmo.errors import SegmoError
from segmo.network import hub_unreachable

PROXY_VARIABLES = ("https_proxy", "HTTPS_PROXY", "all_proxy", "ALL_PROXY", "no_proxy", "NO_PROXY")


@pytest.fixture
def no_network(monkeypatch):
    """Online settings (HF_HUB_OFFLINE unset), but no name resolves: a laptop on a train."""
    import huggingface_hub
    import huggingface_hub.constants

    def lookup(host, *args, **kwargs):
        raise socket.gaierror(-2, "Name or service not known")

    monkeypatch.delenv("HF_HUB_OFFLINE", raising=False)
    monkeypatch.delenv("TRANSFORMERS_OFFLINE", raising=False)
    for name in PROXY_VARIABLES:  # no proxy either: nothing could reach the hub
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_OFFLINE", False)
    monkeypatch.setattr(socket, "getaddrinfo", lookup)


def test_the_reason_names_the_host(no_network, monkeypatch):
    import huggingface_hub.constants

    monkeypatch.setattr(huggingface_hub.constants, "ENDPOINT", "https://hub.example.org")
    assert hub_unreachable() == ("hub.example.org cannot be reached, its name does not resolve: "
                                 "Name or service not known")


def test_a_model_id_reads_only_the_cache_when_the_hub_cannot_be_reached(no_network, monkeypatch):
    import huggingface_hub
    from huggingface_hub.errors import LocalEntryNotFoundError

    from segmo.models.hub import resolve

    asked = []

    def download(repo_id, **kwargs):
        asked.append(kwargs.get("local_files_only", False))
        if not asked[-1]:
            time.sleep(25)  # what the retries of the name lookup cost
        raise LocalEntryNotFoundError("not in the cache")

    monkeypatch.setattr(huggingface_hub, "snapshot_download", download)
    with pytest.raises(SegmoError, match=r"someone/segmo-tiny: no such model folder, and the hub "
                       r"repository is not in the Hugging Face cache \(huggingface.co cannot be "
                       r"reached, its name does not resolve"):
        resolve("someone/segmo-tiny")
    assert asked == [True]


def test_a_text_encoder_id_fails_at_once_when_the_hub_cannot_be_reached(no_network):
    import transformers  # noqa: F401 -- imported before the clock starts (seconds)

    from segmo.text.encoders import get_text_encoder

    start = time.monotonic()
    with pytest.raises(OSError, match=r"not downloadable here \(huggingface.co cannot be reached"):
        get_text_encoder("someone/encoder-that-is-not-cached")
    assert time.monotonic() - start < 10


def test_behind_a_proxy_the_local_name_lookup_is_not_asked(no_network, monkeypatch):
    """Behind an HTTPS proxy local DNS often resolves nothing while the proxy reaches the
    hub: the failed local lookup refused every download that would have worked."""
    monkeypatch.setenv("HTTPS_PROXY", "http://proxy.example.org:3128")
    assert hub_unreachable() is None
    monkeypatch.delenv("HTTPS_PROXY")
    monkeypatch.setenv("all_proxy", "http://proxy.example.org:3128")
    assert hub_unreachable() is None


def test_a_host_the_proxy_skips_is_still_looked_up(no_network, monkeypatch):
    monkeypatch.setenv("HTTPS_PROXY", "http://proxy.example.org:3128")
    monkeypatch.setenv("NO_PROXY", "localhost,.huggingface.co")
    assert hub_unreachable().startswith("huggingface.co cannot be reached")
