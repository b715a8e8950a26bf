"""Policies behind one contract (see `policies.base`); found through `policies.registry`."""
