"""The operator's surface: the command line, the admin endpoint, the status views, route
tests and ``--local-broker``. The top of the import graph: nothing in the engine imports it
(tests/project/test_import_graph.py)."""
