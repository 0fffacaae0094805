"""A failed download said in words: what the network did (no name resolution, refused, no answer,
unreachable), found anywhere in the exception chain a download client raised (clients wrap the
socket's error in their own types and long advice), and the exception cut to whole sentences."""

from __future__ import annotations

import errno
import os
import socket

#: Environment variables that send downloads through a proxy: what failed to answer is then the proxy.
PROXY_ENV = ("HTTPS_PROXY", "https_proxy", "HTTP_PROXY", "http_proxy", "ALL_PROXY", "all_proxy")
#: Seconds a connection may take to be accepted before it counts as no answer.
CONNECT_TIMEOUT_S = 10.0
#: The longest text quoted from an exception; a longer one is cut at a sentence's end.
CAUSE_CHARS = 300


def proxy_variable() -> str | None:
    """The first proxy variable set in the environment, or None."""
    return next((k for k in PROXY_ENV if os.environ.get(k)), None)


def network_problem(e: BaseException, host: str, port: int | None = None) -> str | None:
    """What a failed connection to `host` means, in words; None when `e` is no network failure."""
    where = f"{host}:{port}" if port else host
    if isinstance(e, socket.gaierror):
        why = f"no network: the name {host} does not resolve ({e.strerror or e})"
    elif isinstance(e, ConnectionRefusedError):
        why = f"{where} refused the connection"
    elif isinstance(e, (TimeoutError, socket.timeout)):
        why = f"no answer from {where} within {CONNECT_TIMEOUT_S:g} s"
    elif isinstance(e, OSError) and e.errno in (errno.ENETUNREACH, errno.EHOSTUNREACH, errno.ENETDOWN):
        why = f"no network: {host} is unreachable ({e.strerror})"
    elif isinstance(e, ConnectionError):
        why = f"the connection to {where} failed ({e.strerror or type(e).__name__})"
    else:
        return None
    proxy = proxy_variable()
    return f"{why} (through the proxy in ${proxy})" if proxy else why


def describe_failure(e: BaseException, host: str, port: int | None = None) -> str:
    """Why a download failed, in one whole line: a network failure anywhere in the exception's chain
    in words, else the exception (`first_sentences`)."""
    seen: set[int] = set()
    cur: BaseException | None = e
    while cur is not None and id(cur) not in seen:
        seen.add(id(cur))
        why = network_problem(cur, host, port)
        if why is not None:
            return why
        reason = getattr(cur, "reason", None)  # urllib's URLError keeps the socket's error here
        if isinstance(reason, BaseException) and (why := network_problem(reason, host, port)) is not None:
            return why
        cur = cur.__cause__ or cur.__context__
    return first_sentences(e)


def first_sentences(e: BaseException, limit: int = CAUSE_CHARS) -> str:
    """The exception's type and text on one line, whole sentences only: a text longer than `limit`
    ends at the last sentence that fits (never in the middle of one; at a word with '…' when not
    even the first sentence fits)."""
    text = " ".join(str(e).split())
    if len(text) > limit:
        cut = max(text.rfind(end, 0, limit) for end in (". ", "; ", "! ", "? "))
        text = text[:cut + 1] if cut > 0 else text[:max(text.rfind(" ", 0, limit), 0)] + " …"
    return f"{type(e).__name__}: {text}" if text else type(e).__name__


def check_reachable(host: str, port: int) -> str | None:
    """Why `host`:`port` cannot be reached now (words), or None when it accepts a connection or a
    proxy stands between (then the proxy is what the client reaches)."""
    if not host or proxy_variable() is not None:
        return None
    try:
        socket.create_connection((host, port), timeout=CONNECT_TIMEOUT_S).close()
    except OSError as e:
        return network_problem(e, host, port) or first_sentences(e)
    return None
