"""``jaximu.so3``: the import path of :mod:`jaximu.geometry.so3`, where the module lives."""

from jaximu.geometry.so3 import *  # noqa: F403
from jaximu.geometry.so3 import __all__ as __all__
