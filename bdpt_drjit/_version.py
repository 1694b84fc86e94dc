"""The package's version (pyproject.toml has the same), in a module of its own so that
modules below the package's ``__init__`` (cluster.py's workers) can read it without
importing the package they are part of."""
__version__ = "0.1.0"
