"""``tomllib`` (Python 3.11+), or before 3.11 the same parser as the ``tomli`` backport."""

import sys

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

__all__ = ["tomllib"]
