"""One exception type for everything a user can get wrong."""
from __future__ import annotations


class InputError(ValueError):
    """Bad user input. ``field`` names what was wrong; the CLI prints
    ``error: <field>: <message>`` and exits with status 2."""

    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}")
        self.field = field
        self.message = message
