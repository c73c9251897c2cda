"""``jaximu.noise``: the import path of :mod:`jaximu.geometry.noise`, where the module lives."""

from jaximu.geometry.noise import *  # noqa: F403
from jaximu.geometry.noise import __all__ as __all__
