"""``jaximu.montecarlo``: the import path of :mod:`jaximu.studies.montecarlo`, where the module lives."""

from jaximu.studies.montecarlo import *  # noqa: F403
from jaximu.studies.montecarlo import __all__ as __all__
