"""``jaximu.state``: the import path of :mod:`jaximu.geometry.state`, where the module lives."""

from jaximu.geometry.state import *  # noqa: F403
from jaximu.geometry.state import __all__ as __all__
