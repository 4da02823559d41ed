"""hookwatch: needle-hook wear life from yarn tension, at the edge."""
from importlib.metadata import PackageNotFoundError
from importlib.metadata import version as _v

try:
    __version__ = _v("hookwatch")
except PackageNotFoundError:  # running from a source tree
    __version__ = "0.0.0+src"
