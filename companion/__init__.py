"""Model-free control of multirotors from a companion computer over MAVLink."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("mfc-companion")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.0.0+unknown"

__all__ = ["__version__"]
