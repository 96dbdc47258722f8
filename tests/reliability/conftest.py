"""The CLI's fixtures (a tiny model pair, a real photo) for the reliability tests of the photo path."""

from tests.cli.conftest import astronaut, astronaut_png, tiny_models  # noqa: F401
