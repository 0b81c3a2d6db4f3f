"""The route language: route files loaded, checked and compiled into specifications, with
their templates, agents, mappings, stores and the option declarations of every stage.

Stands on engine/common/ and the protocol packages (engine/endpoints/, through their
contract); never imports the running engine or the operator's surface
(tests/project/test_import_graph.py): loading and checking routes starts nothing."""
