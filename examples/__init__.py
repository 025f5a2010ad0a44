"""Worked examples of the project's extension points, run by the tests (docs/development/adding-a-method.md)."""
