"""Small examples of the harness's formats (see docs/validation.md)."""
