"""``jaximu learn``'s import paths: a re-export of :mod:`jaximu.app.learn`, where the
subcommand lives."""

from jaximu.app.learn import LEARNING_EXTRA, add_parser, cmd_evaluate, cmd_train

__all__ = ["LEARNING_EXTRA", "add_parser", "cmd_evaluate", "cmd_train"]
