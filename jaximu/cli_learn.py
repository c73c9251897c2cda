"""``jaximu learn``'s former home, kept so that its import paths work; the subcommand lives in
:mod:`jaximu.app.learn`."""

from jaximu.app.learn import LEARNING_EXTRA, _Usage, add_parser, cmd_evaluate, cmd_train

__all__ = ["LEARNING_EXTRA", "_Usage", "add_parser", "cmd_evaluate", "cmd_train"]
