"""Tests of ``flylib.io``."""
