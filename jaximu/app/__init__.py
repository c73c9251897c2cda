"""The ``jaximu`` command: parsing and printing only, over the library's functions.

* :mod:`jaximu.app.command`: the parser of every subcommand, the one error and exit-code
  rule (:func:`~jaximu.app.command.main`), the library's fixes rendered as flags, the
  options table of ``docs/accepts.md`` and the compilation cache.
* :mod:`jaximu.app.common`: the options and checks the subcommands share, and reading the
  recording named on the command line.
* One module per subcommand: :mod:`~jaximu.app.demo`, :mod:`~jaximu.app.propagate`,
  :mod:`~jaximu.app.preintegrate`, :mod:`~jaximu.app.montecarlo`,
  :mod:`~jaximu.app.calibrate`, :mod:`~jaximu.app.allan`, :mod:`~jaximu.app.learn`; each
  has ``add_parser(sub)`` and its ``cmd_*`` function.

Imports point down only: the command imports the library, and nothing in the library
imports the command.
"""

from jaximu.app.command import build_parser, main, options_table

__all__ = ["build_parser", "main", "options_table"]
