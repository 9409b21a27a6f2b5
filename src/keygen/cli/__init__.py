"""The ``keygen`` command line."""
