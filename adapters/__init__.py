"""Simulator suites behind one contract (see `adapters.base`); found through `adapters.registry`."""
