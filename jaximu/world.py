"""``jaximu.world``: the import path of :mod:`jaximu.schemes.world`, where the module lives."""

from jaximu.schemes.world import *  # noqa: F403
from jaximu.schemes.world import __all__ as __all__
