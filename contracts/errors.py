"""Errors that name what was wrong."""

from __future__ import annotations


class ConfigError(ValueError):
    """A setting is out of range or unknown; the message names the setting and what is allowed."""


class PolicyFileError(ValueError):
    """A policy file is not ours, lacks its contract, or does not fit the inputs it would get."""


class PolicyInputError(ValueError):
    """An observation cannot be fed to the policy (wrong length, non-finite pose or target)."""
