"""``jaximu.integrators``: the import path of :mod:`jaximu.schemes.integrators`, where the module lives."""

from jaximu.schemes.integrators import *  # noqa: F403
from jaximu.schemes.integrators import __all__ as __all__
