"""``jaximu.errorstate``: the import path of :mod:`jaximu.engine.errorstate`, where the module lives."""

from jaximu.engine.errorstate import *  # noqa: F403
from jaximu.engine.errorstate import __all__ as __all__
