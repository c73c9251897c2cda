"""``jaximu.preintegration``: the import path of :mod:`jaximu.engine.preintegration`, where the module lives."""

from jaximu.engine.preintegration import *  # noqa: F403
from jaximu.engine.preintegration import __all__ as __all__
