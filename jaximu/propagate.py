"""``jaximu.propagate``: the import path of :mod:`jaximu.engine.propagate`, where the module lives."""

from jaximu.engine.propagate import *  # noqa: F403
from jaximu.engine.propagate import __all__ as __all__
