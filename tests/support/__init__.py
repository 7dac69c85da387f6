"""Helpers shared by the tests; the tests receive them as fixtures (tests/conftest.py).

Only :mod:`support.fuzz` is imported directly: its Hypothesis strategies and settings are needed when a
test module is imported, before any fixture exists.
"""
