"""``jaximu.recording``: the import path of :mod:`jaximu.studies.recording`, where the module lives."""

from jaximu.studies.recording import *  # noqa: F403
from jaximu.studies.recording import __all__ as __all__
