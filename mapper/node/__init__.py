"""The node: the transport (``service``), what requests share (``context``), the ingest path
(``ingest``, ``integration``), the answers by request (``answers``), the ways of answering
(``backends``), the background workers (``workers``), config, map store, CLI.

Imports no torch (tests/test_architecture.py proves it); the learned backend and the workers that
use the model are imported only when installed.
"""
