"""The package's version, in one place (the package's face and the site read it)."""

__version__ = "0.1.0"
