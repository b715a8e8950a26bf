"""`python -m harness` is `dvla-harness`."""

from harness.cli import entry

entry()
