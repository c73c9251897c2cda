"""``jaximu.allan``: the import path of :mod:`jaximu.studies.allan`, where the module lives."""

from jaximu.studies.allan import *  # noqa: F403
from jaximu.studies.allan import __all__ as __all__
