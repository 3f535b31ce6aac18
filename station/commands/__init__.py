"""Subcommands of the ``ltc`` command line, one module each."""
