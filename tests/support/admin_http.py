"""A plain HTTP(S) GET of an engine's or a supervisor's admin endpoint, as a browser or curl
would make it: no client library of ours, the throwaway certificate of the TLS tests accepted."""

from __future__ import annotations

import ssl
import urllib.error
import urllib.request
from typing import Any


def fetch(url: str, authorization: str | None = None) -> tuple[int, dict[str, Any], str]:
    """(status, headers, body text); an HTTP error status is answered, not raised (its headers:
    only ``WWW-Authenticate``, every value of it)."""
    request = urllib.request.Request(url)
    if authorization:
        request.add_header("Authorization", authorization)
    context = ssl.create_default_context()
    context.check_hostname, context.verify_mode = False, ssl.CERT_NONE  # the throwaway certificate
    try:
        with urllib.request.urlopen(request, timeout=10, context=context) as response:
            return response.status, dict(response.headers), response.read().decode()
    except urllib.error.HTTPError as exc:
        return exc.code, {"WWW-Authenticate": exc.headers.get_all("WWW-Authenticate")}, exc.read().decode()
