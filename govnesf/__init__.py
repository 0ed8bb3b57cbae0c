"""The govnesf distribution: its version, its optional extras and its packaged data.

A leaf: imports nothing of the project, so ``protocol``, ``mapper`` and ``clients`` may all use
it (docs/concepts/architecture.md). The version is declared here once; ``pyproject.toml`` reads it
(``[tool.setuptools.dynamic]``) and ``govnesf --version`` prints it.
"""

__version__ = "0.2.0"

__all__ = ["__version__"]
