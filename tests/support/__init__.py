"""Helpers shared by the tests; the tests receive them as fixtures (tests/conftest.py)."""
