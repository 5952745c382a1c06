"""recal: streaming in-use recalibration of triaxial accelerometers."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("recal")
except PackageNotFoundError:  # running from a source tree that was not installed
    __version__ = "0.0.0"
