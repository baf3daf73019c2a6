"""The compass parameters a dance is corrected with, checked against the vehicle before fitting and
before writing (issue 24, "parameters you can trust").

The samples of a dance come already corrected by the vehicle's COMPASS_OFS/DIA/ODI/SCALE/MOT/ORIENT
(PX4: CAL_MAGn_*OFF/SCALE/ODIAG/ROT); the fit un-applies exactly those.  ``CompassParamCheck``
keeps them as ``reference`` (the cache at the start, then the first value of each name heard), so a
PARAM_VALUE that changes one during the dance (another ground station wrote it, or a spoofed packet
reached the cache) is seen at once: ``on_value`` describes the change and the wizard stops the step
and re-reads.  ``start`` a re-read (PARAM_REQUEST_READ of every reference name, sent by the hub)
before fitting and before writing; ``done`` when every name answered or after ``REREAD_TIMEOUT_S``;
``differences`` lists what the vehicle now holds that is not the reference.  Pure state, no I/O.
"""
from __future__ import annotations

import re

import numpy as np

__all__ = ["CompassParamCheck", "is_correction_param", "REREAD_TIMEOUT_S", "REREAD_RESEND_S"]

REREAD_TIMEOUT_S = 4.0
REREAD_RESEND_S = 1.5
_CORRECTION = re.compile(r"COMPASS_(OFS|DIA|ODI)[23]?_[XYZ]|COMPASS_SCALE[23]?|COMPASS_MOT[23]?_[XYZ]|COMPASS_MOTCT"
                         r"|COMPASS_ORIENT[23]?|CAL_MAG\d_([XYZ](OFF|SCALE|ODIAG)|ROT)\Z")


def is_correction_param(name: str) -> bool:
    """A parameter the vehicle applies to the field it reports (so the fit un-applies it);
    COMPASS_DEC, COMPASS_USE, CAL_FIT ... are not (a change of those leaves the samples as they are)."""
    return bool(_CORRECTION.match(name))


def _same(a: float, b: float) -> bool:
    """Equal as the float32 a PARAM_VALUE carries."""
    return abs(float(np.float32(a)) - float(np.float32(b))) <= 1e-6 * max(1.0, abs(b))


class CompassParamCheck:
    def __init__(self) -> None:
        self.reference: dict[str, float] = {}
        self.purpose: str | None = None          # "fit" | "write" while a re-read runs
        self.requested_at: float | None = None
        self.resent = False
        self.pending: set[str] = set()
        self.answers: dict[str, float] = {}
        self.changes: list[str] = []              # changes seen during the dance (texts)
        self.verified_for_fit = False             # re-read before fitting found the reference

    def begin(self, params: dict[str, float]) -> None:
        """The dance starts with these values in force (the parameter cache)."""
        self.__init__()
        self.reference = {n: float(v) for n, v in params.items() if is_correction_param(n)}

    def on_value(self, name: str, value: float) -> str | None:
        """A trusted PARAM_VALUE: a re-read answer and/or a change of the reference ("NAME a -> b")."""
        if not is_correction_param(name):
            return None
        if self.purpose is not None and name in self.pending:
            self.pending.discard(name)
            self.answers[name] = float(value)
        ref = self.reference.get(name)
        if ref is None:
            self.reference[name] = float(value)
            return None
        if _same(ref, value):
            return None
        change = f"{name} {ref:g} -> {float(value):g}"
        self.changes.append(change)
        return change

    def start(self, purpose: str, now_s: float) -> list[str]:
        """Begin a re-read; the names to request (PARAM_REQUEST_READ)."""
        self.purpose, self.requested_at, self.resent = purpose, now_s, False
        self.pending, self.answers = set(self.reference), {}
        return sorted(self.pending)

    def resend(self, now_s: float) -> list[str]:
        """Names to request again (once, ``REREAD_RESEND_S`` after the start)."""
        if self.purpose is None or self.resent or self.requested_at is None:
            return []
        if now_s - self.requested_at < REREAD_RESEND_S:
            return []
        self.resent = True
        return sorted(self.pending)

    def done(self, now_s: float) -> bool:
        if self.purpose is None:
            return False
        return not self.pending or now_s - (self.requested_at or now_s) >= REREAD_TIMEOUT_S

    def differences(self) -> list[str]:
        """What the vehicle answered that is not the reference."""
        return [f"{n} {self.reference[n]:g} -> {v:g}" for n, v in sorted(self.answers.items())
                if n in self.reference and not _same(self.reference[n], v)]

    def finish(self) -> tuple[list[str], list[str]]:
        """End the re-read: (differences, names not answered)."""
        diffs, missing = self.differences(), sorted(self.pending)
        self.purpose, self.requested_at, self.pending = None, None, set()
        return diffs, missing

    def snapshot(self) -> dict:
        return {"rereading": self.purpose, "pending": len(self.pending), "checked": len(self.reference),
                "changes_during_dance": list(self.changes[-10:])}
