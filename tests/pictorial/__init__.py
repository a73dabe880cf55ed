"""Tests of ``flylib.pictorial``."""
