"""Errors raised for bad user input.

Every message names the argument, what was received, what is valid and how to
fix it, so a user never has to read the source to understand a failure.
"""

from __future__ import annotations

import difflib


class CapssimError(Exception):
    """Base class of every error capssim raises on purpose."""


class InputError(CapssimError, ValueError):
    """An argument, file or option a user gave is not valid."""

    def __init__(self, argument: str, received: object, valid: str, fix: str | None = None):
        self.argument = argument
        self.received = received
        self.valid = valid
        self.fix = fix
        message = f"{argument}: got {received}; expected {valid}."
        if fix:
            message += f" {fix}"
        super().__init__(message)


class CaptureFormatError(CapssimError, ValueError):
    """A capture folder or one of its files is missing, corrupt or inconsistent."""


class UnknownNameError(CapssimError, KeyError):
    """A method, scene, preset or suite name is not registered."""

    def __init__(self, kind: str, name: str, known: list[str]):
        self.kind = kind
        self.name = name
        self.known = sorted(known)
        close = difflib.get_close_matches(str(name), self.known, n=1)
        hint = f" Did you mean {close[0]!r}?" if close else ""
        super().__init__(f"unknown {kind} {name!r}; valid names are: {', '.join(self.known)}.{hint}")

    def __str__(self) -> str:  # KeyError would otherwise quote the message
        return self.args[0]


class PluginError(CapssimError):
    """A plug-in method or prior (:mod:`capssim.reconstruct.plugins`) failed to load, to run, or returned an
    image of the wrong shape, dtype or with non-finite values. The message is one line naming the plug-in and
    its package; the other methods are not affected."""


class ResourceError(InputError):
    """An option asks for more memory (or time) than the machine has or than a documented sane range.

    The message names the option, the estimate, the limit and how to change either.
    """

    def __init__(self, option: str, received: object, message: str):
        CapssimError.__init__(self, f"{option}: {message}")
        self.argument = option
        self.received = received
        self.valid = message
        self.fix = None
