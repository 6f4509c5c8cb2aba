"""The package version, in a module of its own so that any module can read it without importing the
package's flat API (``sage_core/__init__.py``). Kept equal to ``version`` in ``pyproject.toml``."""

__version__ = "0.1.0"
