"""A module whose import fails (the tests' bad import path)."""

raise ImportError("this module cannot be imported on purpose")
