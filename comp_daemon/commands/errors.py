"""The error a subcommand raises for a mistake the user can fix; the CLI prints it as one line."""

from __future__ import annotations

__all__ = ["UserError"]


class UserError(Exception):
    """An error in what the user asked for; printed without a traceback, exit code 2."""
