"""``jaximu.datasets``: the import path of :mod:`jaximu.io.datasets`, where the module lives."""

from jaximu.io.datasets import *  # noqa: F403
from jaximu.io.datasets import __all__ as __all__
