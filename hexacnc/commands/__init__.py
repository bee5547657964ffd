"""Subcommands of the ``hexacnc`` console command.

Each module defines ``HELP`` (one line), ``configure(parser)`` and
``main(args) -> int``.  Modules are imported lazily so that one command's
dependencies never slow down or break another.
"""
