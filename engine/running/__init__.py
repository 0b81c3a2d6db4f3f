"""The running engine: connections, runners, pipelines, delivery, buffers, dead letters,
replies, fairness, throttles, observers, leases, reload plans and the watcher.

Runs what the route language (engine/language/) compiled; imported by the operator's
surface (engine/ops/) and never the other way round (tests/project/test_import_graph.py)."""
