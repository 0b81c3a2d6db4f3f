"""``--local-broker``: private brokers for demos and tests, on a machine with none set up.

The protocols that need a broker of their own say how to start one (the registry in
engine/endpoints/__init__.py names each one's module; its ``private_broker(cluster, tls)`` gives a
:class:`PrivateBroker`, its ``CHECK_ENV`` what ``check --local-broker`` stands in for it).
Started, each private broker sets the environment its transport's default connection reads
(``Transport.default_connection_settings``), so the routes that name no connection use it,
and :data:`LOCAL_BROKER_ENV` names the brokers, so the loader warns about each connection
that leads elsewhere (``Transport.private_broker_warning``).
"""

from __future__ import annotations

import importlib
import os
from typing import Any, Iterable

from engine.common.processes import LOCAL_BROKER_ENV, PrivateBroker


def _modules(protocols: Iterable[str] | None = None) -> list[Any]:
    """The private-broker module of each protocol that has one (of ``protocols``, if given)."""
    from engine import endpoints

    wanted = endpoints.PRIVATE_BROKERS if protocols is None else {
        protocol: name for protocol, name in endpoints.PRIVATE_BROKERS.items() if protocol in protocols}
    return [importlib.import_module(name) for name in wanted.values()]


def private_brokers(cluster: int = 1, used: Iterable[str] | None = None, tls: bool = False) -> list[PrivateBroker]:
    """A private broker for each protocol that has one and is ``used`` by the routes (None:
    unknown, every one) or starts always (its module's ``ALWAYS``: the default connection of
    routes that name none); ``cluster`` nodes where the broker can cluster; ``tls``
    (``--local-broker-tls``): listening with TLS, a throwaway CA in its directory (BrokerError
    from a broker that cannot)."""
    used = None if used is None else set(used)
    return [module.private_broker(cluster, tls=tls) for module in _modules()
            if used is None or module.ALWAYS or module in _modules(used)]


def stand_in_for_check() -> None:
    """Set the environment ``check --local-broker`` loads the routes with: each broker's
    stand-in URL (never a host), so the loader warns as ``run --local-broker`` would."""
    for module in _modules():
        for key, value in module.CHECK_ENV.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value
    os.environ[LOCAL_BROKER_ENV] = ""
