"""Whether the Hugging Face hub can be reached, asked before a download.

Without a network, `huggingface_hub` retries a failed name lookup five times with
back-off (about 25 s, five warnings) before it says so. One lookup of the hub's host
tells at once; a miss then reads only the local cache and says why. Behind an HTTPS proxy
the proxy looks the name up, not this machine, so the local lookup is not asked.
"""

from __future__ import annotations

import socket
import urllib.parse
import urllib.request


def hub_unreachable() -> str | None:
    """Why the hub's host (``HF_ENDPOINT``, huggingface.co by default) cannot be reached,
    or None when its name resolves or an HTTPS proxy (``HTTPS_PROXY``/``ALL_PROXY``, host
    not in ``NO_PROXY``) will resolve it: then huggingface_hub tries. Asked at each
    download, not remembered: a notebook that started offline finds the network when it
    comes back."""
    from huggingface_hub import constants

    host = urllib.parse.urlsplit(constants.ENDPOINT).hostname or ""
    proxies = urllib.request.getproxies()
    if (proxies.get("https") or proxies.get("all")) and not urllib.request.proxy_bypass(host):
        return None  # local DNS often resolves nothing behind a proxy that reaches the hub
    try:
        socket.getaddrinfo(host, 443, type=socket.SOCK_STREAM)
    except (OSError, UnicodeError) as error:
        reason = getattr(error, "strerror", None) or str(error) or type(error).__name__
        return f"{host} cannot be reached, its name does not resolve: {reason}"
    return None
