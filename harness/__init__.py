"""The runner, CLI, configuration and execution backends of dvla-harness."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("dvla-harness")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.1.0+source"
