"""``jaximu.plots``: the import path of :mod:`jaximu.studies.plots`, where the module lives."""

from jaximu.studies.plots import *  # noqa: F403
from jaximu.studies.plots import __all__ as __all__
