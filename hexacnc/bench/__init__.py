"""Benchmarks printing JSON figures (``hexacnc bench NAME``).

Each module defines ``HELP``, ``configure(parser)`` and ``main(args) -> int``.
"""
