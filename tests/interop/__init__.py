"""Tests of ``flylib.interop``."""
