"""The fixtures of ``pstoolkit.testing`` (imported here rather than through ``pytest_plugins``, which
pytest allows only in the top-level conftest of a run)."""

from pstoolkit.testing import pstoolkit_plugins, pstoolkit_plugins_alone  # noqa: F401
