"""Clients of the mapper: client library, CLI, replay, importers and the simulated robot.

Imports `protocol`; never imports mapper internals (only `mapper.node.cli` entry points, lazily,
from the `govnesf` dispatcher).
"""
