"""``jaximu.keyframes``: the import path of :mod:`jaximu.studies.keyframes`, where the module lives."""

from jaximu.studies.keyframes import *  # noqa: F403
from jaximu.studies.keyframes import __all__ as __all__
