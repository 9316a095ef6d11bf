"""The base of every config section."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict


class Section(BaseModel):
    """A config section: an unknown key is an error naming it, never silently ignored (a typo)."""

    model_config = ConfigDict(extra="forbid")
