"""Errors that name what was wrong."""

from __future__ import annotations


class ConfigError(ValueError):
    """A setting is out of range or unknown; the message names the setting and what is allowed."""
