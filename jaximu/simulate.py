"""``jaximu.simulate``: the import path of :mod:`jaximu.studies.simulate`, where the module lives."""

from jaximu.studies.simulate import *  # noqa: F403
from jaximu.studies.simulate import __all__ as __all__
