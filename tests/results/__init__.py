"""Tests of ``flylib.results``."""
