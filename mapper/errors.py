"""Errors shared across the mapper's packages (a leaf module: imports nothing of the project)."""

from __future__ import annotations

__all__ = ["ConfigError", "RuntimeNotReady"]


class ConfigError(ValueError):
    """A configuration file or override is invalid; the message names the key and the source."""


class RuntimeNotReady(RuntimeError):
    """The runtime cannot answer yet (no checkpoint, no keyframes, no OV features, no text
    encoder); the message says what is missing. The node answers ``not_ready`` with it."""
