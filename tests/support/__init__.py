"""Helpers shared by test files (importable as ``support.…``: pyproject.toml puts tests/ on the path)."""
