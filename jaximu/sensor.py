"""``jaximu.sensor``: the import path of :mod:`jaximu.geometry.sensor`, where the module lives."""

from jaximu.geometry.sensor import *  # noqa: F403
from jaximu.geometry.sensor import __all__ as __all__
