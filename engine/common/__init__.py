"""The foundation every other part of the engine stands on: typed options, did-you-mean,
secrets, the backoff, logging, TLS, canonical JSON and schemas, time stamps and frames, the
``{name}`` placeholder grammar, canonical field keys and server processes.

Imports nothing else of the engine (tests/project/test_import_graph.py), so the protocol packages
(engine/endpoints/) can use all of it."""
