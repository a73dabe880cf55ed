"""Tests of ``flylib.config``."""
