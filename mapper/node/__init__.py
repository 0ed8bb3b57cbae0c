"""The node core: config, keyframe window, map store, global map, queries, service, CLI.

Imports no torch (tests/test_architecture.py proves it); the learned model plugs in
through mapper/node/plugins/.
"""
