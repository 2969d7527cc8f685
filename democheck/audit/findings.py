"""What a check found in a demo, as data: a ``Finding`` is a kind from the check's own small vocabulary and the
kind's parameters (numbers, frames, dimension names, files).  The words are a template per kind, owned by the
check (``Vocabulary``); a reason is built from findings (``democheck.audit.reasons``), never parsed back out of
words.  Facts that only words need are computed once, in the check that owns them, and travel as parameters.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

Template = str | Callable[..., str]  # ``str.format`` fields of the parameters, or a function of them


@dataclass(frozen=True)
class Finding:
    """One check's finding in one demo: ``check``, ``kind`` (one of the check's ``Vocabulary``) and ``params``."""

    check: str
    kind: str
    params: Mapping[str, Any] = field(default_factory=dict)

    @property
    def key(self) -> str:
        """'check:kind', as the ranking recipe's precedence names it."""
        return f"{self.check}:{self.kind}"

    @property
    def words(self) -> str:
        """The kind's words; a finding on one of several cameras (``camera`` in its parameters) names it first."""
        words = VOCABULARIES[self.check].render(self)
        camera = self.params.get("camera")
        return f"on the {camera} camera, {words}" if camera else words

    def on_camera(self, camera: str) -> "Finding":
        """The same finding, on the named camera (``words`` say which)."""
        return Finding(self.check, self.kind, {**self.params, "camera": camera})


class Vocabulary:
    """A check's kinds of finding and one template each.  Creating it registers it (``VOCABULARIES``), so that
    a finding's words and the ranking recipe's names are checked against what the check declares."""

    def __init__(self, check: str, templates: Mapping[str, Template]):
        self.check, self.templates = check, dict(templates)
        VOCABULARIES[check] = self

    @property
    def kinds(self) -> tuple[str, ...]:
        return tuple(self.templates)

    def __call__(self, kind: str, **params: Any) -> Finding:
        if kind not in self.templates:
            raise ValueError(f"{self.check} has no kind {kind!r} (kinds: {', '.join(self.templates)})")
        return Finding(self.check, kind, params)

    def render(self, finding: Finding) -> str:
        """The kind's words of the finding's parameters (a template takes those it names; the others are facts
        for the precedence and for whoever reads the finding)."""
        template = self.templates[finding.kind]
        if not callable(template):
            return template.format(**finding.params)
        takes = inspect.signature(template).parameters
        if any(p.kind is p.VAR_KEYWORD for p in takes.values()):
            return template(**finding.params)
        return template(**{k: v for k, v in finding.params.items() if k in takes})


VOCABULARIES: dict[str, Vocabulary] = {}
CAMERA_MARK = "@"  # a check's column on another camera than the one read first: "frozen_video@wrist"


def camera_column(check: str, camera: str) -> str:
    """The column of ``check`` on one of the dataset's other cameras."""
    return f"{check}{CAMERA_MARK}{camera}"


def check_of(column: str) -> str:
    """The check a score column holds: its name, less the camera of a check on another camera."""
    return column.partition(CAMERA_MARK)[0]


def camera_of(column: str) -> str:
    """The other camera a score column was read on ("" for the first camera, or a check of no camera)."""
    return column.partition(CAMERA_MARK)[2]


def known(name: str) -> bool:
    """Whether ``name`` is a registered 'check' or 'check:kind'."""
    check, _, kind = name.partition(":")
    return check in VOCABULARIES and (not kind or kind in VOCABULARIES[check].templates)
