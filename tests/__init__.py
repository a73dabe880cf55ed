"""flylib's test suite. Each folder is a package, so test files in different
folders may share a name; the helpers beside this file are on pytest's ``pythonpath``."""
