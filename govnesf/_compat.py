"""Standard-library modules that moved between the Python versions the project runs on (>= 3.10)."""

from __future__ import annotations

import sys

if sys.version_info >= (3, 11):
    import tomllib
else:  # Python 3.10 (ROS 2 Humble): the same parser, published as tomli
    import tomli as tomllib

__all__ = ["tomllib"]
