"""The ``jaximu`` command's import paths (the console script ``jaximu.cli:main``,
``jaximu.cli.build_parser``, ``options_table``, ``flag_of``, …): a re-export of
:mod:`jaximu.app`, where the command lives, one module per subcommand."""

import sys

from jaximu.app.allan import cmd_allan
from jaximu.app.calibrate import _warnings_as_lines, cmd_calibrate
from jaximu.app.command import (
    API_ONLY_OPTIONS,
    FLAGS,
    INVERTED_FLAGS,
    UsageError,
    build_parser,
    cache_folder,
    enable_compilation_cache,
    flag_of,
    main,
    options_table,
)
from jaximu.app.demo import cmd_demo
from jaximu.app.montecarlo import FIX_SIGMA, cmd_montecarlo
from jaximu.app.preintegrate import cmd_preintegrate
from jaximu.app.propagate import REPORT_AT, cmd_propagate
from jaximu.studies.recording import (
    DEMO_SCHEMES,
    DEMO_SECONDS,
    NOISE_PRESETS,
    propagate_recording,
    run_demo,
)

__all__ = [
    "API_ONLY_OPTIONS",
    "DEMO_SCHEMES",
    "DEMO_SECONDS",
    "FIX_SIGMA",
    "FLAGS",
    "INVERTED_FLAGS",
    "NOISE_PRESETS",
    "REPORT_AT",
    "UsageError",
    "_warnings_as_lines",
    "build_parser",
    "cache_folder",
    "cmd_allan",
    "cmd_calibrate",
    "cmd_demo",
    "cmd_montecarlo",
    "cmd_preintegrate",
    "cmd_propagate",
    "enable_compilation_cache",
    "flag_of",
    "main",
    "options_table",
    "propagate_recording",
    "run_demo",
]

if __name__ == "__main__":
    sys.exit(main())
