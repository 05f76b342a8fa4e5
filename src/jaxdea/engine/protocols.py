"""Protocols as small self-validating objects: what a batch of cells runs and with what settings.

:class:`Paper`, :class:`Continuation` and :class:`Periodic` hold a protocol's settings and
check them when built (:class:`jaxdea.SweepError` naming the field and its allowed range), so
a bad setting fails where it is written, before any computation. :func:`jaxdea.sweep`,
:func:`jaxdea.powermap` and :func:`jaxdea.engine.batch.run_cells` take either such an object
or a protocol's name (:data:`PROTOCOLS`, the CLI's shorthand) with the keywords ``cycles``,
``average``, ``early_exit``, ``direction`` and ``tol``; :func:`as_protocol` maps the second
form onto the first. With an object, those keywords must stay at their defaults.
"""

from __future__ import annotations

import dataclasses
from typing import Any, ClassVar

from .._checks import (
    SweepError,
    check_choice,
    check_early_exit,
    check_protocol,
    check_unit_interval,
)

#: Protocols: the papers' N cycles from rest per cell; frequency continuation (each f starts
#: from the previous f's final state); periodic steady state (settle, then Newton shooting).
PROTOCOLS = ("paper", "continuation", "periodic")
DIRECTIONS = ("forward", "backward")
#: Where a map's periodic cells start: each from rest, or from the neighbouring payload's
#: orbit along the map's second axis (:mod:`jaxdea.engine.warmstart`).
STARTS = ("rest", "neighbour")

#: Early exit of the paper and continuation protocols: a cell stops once its trajectory is
#: periodic to this scaled residual (corrected for the observed contraction per cycle), since
#: its remaining cycles would repeat the last one; its metrics are then over that last cycle.
#: At 1e-8 the metrics equal the full N-cycle run's to ~1e-7 relative (tests/test_protocols;
#: 2e-9 at 1e-10, for 11 % more steps), far below the integration error (~5e-5 against LSODA
#: at rtol 1e-9). ``None`` runs every cell for all N cycles.
EARLY_EXIT = 1e-8

#: The protocol keywords of the studies and their defaults (the settings of a string protocol).
KEYWORD_DEFAULTS = dict(cycles=100, average=5, early_exit=EARLY_EXIT, direction="forward",
                        tol=1e-6, start="rest")


@dataclasses.dataclass(frozen=True)
class Paper:
    """The papers' protocol: every cell runs ``cycles`` drive periods from rest, and its
    metrics are the mean over the last ``average`` periods.

    **Arguments:**

    - `cycles`: drive periods per cell, an integer >= 1.
    - `average`: periods averaged at the end, an integer in [1, cycles].
    - `early_exit`: a cell stops once its trajectory is periodic to this tolerance in
      (0, 1) (its metrics are then over its last period; :data:`EARLY_EXIT`), or ``None``
      to run every cell for all ``cycles``.
    """

    name: ClassVar[str] = "paper"
    cycles: int = 100
    average: int = 5
    early_exit: float | None = EARLY_EXIT

    def __post_init__(self):
        check_protocol(self.cycles, self.average)
        check_early_exit(self.early_exit)


@dataclasses.dataclass(frozen=True)
class Continuation:
    """Frequency continuation: the papers' protocol, but each frequency starts from the
    previous frequency's final state (paper 000's sweep; run both directions to expose
    jumps).

    **Arguments:**

    - `cycles`: drive periods per frequency, an integer >= 1.
    - `average`: periods averaged at the end, an integer in [1, cycles].
    - `early_exit`: as for :class:`Paper`.
    - `direction`: ``"forward"`` (up the frequency axis) or ``"backward"`` (down it). Used by
      :func:`jaxdea.sweep` and :func:`jaxdea.powermap`; ``run_cells`` takes the chains as
      its ``successor`` argument instead (:func:`jaxdea.engine.batch.chain_successors`).
    """

    name: ClassVar[str] = "continuation"
    cycles: int = 100
    average: int = 5
    early_exit: float | None = EARLY_EXIT
    direction: str = "forward"

    def __post_init__(self):
        check_protocol(self.cycles, self.average)
        check_early_exit(self.early_exit)
        check_choice("direction", self.direction, DIRECTIONS)


@dataclasses.dataclass(frozen=True)
class Periodic:
    """Periodic steady state of every cell: settle from rest, then Newton shooting on the
    one-period map (:func:`jaxdea.engine.periodic.periodic_cells`).

    **Arguments:**

    - `tol`: convergence tolerance on the scaled periodicity residual, in (0, 1).
    - `start`: ``"rest"`` (every cell from rest) or, on a power map, ``"neighbour"``: each
      cell starts from the converged orbit of its neighbour along the map's second axis
      (c, or the payload law's axis), from the heaviest load down, and is solved by chord
      iterations (:mod:`jaxdea.engine.warmstart`). Where responses coexist it reports the
      branch continued from the heavier loads, which may differ from the from-rest orbit.
    """

    name: ClassVar[str] = "periodic"
    tol: float = 1e-6
    start: str = "rest"

    def __post_init__(self):
        check_unit_interval("tol", self.tol)
        check_choice("start", self.start, STARTS)


#: Protocol objects by name.
PROTOCOL_TYPES = {cls.name: cls for cls in (Paper, Continuation, Periodic)}
Protocol = Paper | Continuation | Periodic


def _fields(obj: Protocol) -> dict[str, Any]:
    return {f.name: getattr(obj, f.name) for f in dataclasses.fields(obj)}


def _check_keywords(keywords: dict[str, Any]) -> None:
    unknown = sorted(set(keywords) - set(KEYWORD_DEFAULTS))
    if unknown:
        raise SweepError(f"unknown protocol keyword {unknown[0]!r}: the keywords are "
                         f"{', '.join(KEYWORD_DEFAULTS)}")


def _is_default(name: str, value: Any) -> bool:
    default = KEYWORD_DEFAULTS[name]
    if value is None or default is None:
        return value is default
    try:
        return bool(value == default)
    except (TypeError, ValueError):  # an array, say: not the default
        return False


def as_protocol(protocol: str | Protocol, **keywords) -> Protocol:
    """The protocol object for ``protocol``.

    **Arguments:**

    - `protocol`: a protocol object (returned as it is), or one of the names
      :data:`PROTOCOLS`.
    - `keywords`: the studies' protocol keywords (``cycles``, ``average``, ``early_exit``,
      ``direction``, ``tol``). With a name, those the protocol uses become its settings
      (the others are ignored, as the studies ignore them; missing ones take their
      defaults). With an object, every one given must be at its default
      (:data:`KEYWORD_DEFAULTS`): the object's settings are used.

    Raises :class:`jaxdea.SweepError` for an unknown name or keyword, a setting out of its
    allowed range, or a keyword that conflicts with a protocol object (naming the keyword).
    """
    _check_keywords(keywords)
    if isinstance(protocol, tuple(PROTOCOL_TYPES.values())):
        for key, value in keywords.items():
            if not _is_default(key, value):
                fields = ", ".join(_fields(protocol))
                raise SweepError(
                    f"{key} = {value!r} conflicts with protocol = {protocol!r}: with a protocol "
                    f"object, leave {key} at its default ({KEYWORD_DEFAULTS[key]!r}) and set "
                    f"the settings on the object ({type(protocol).__name__} has: {fields})")
        return protocol
    if not isinstance(protocol, str):
        raise SweepError(f"protocol = {protocol!r} must be one of {', '.join(PROTOCOLS)} or a "
                         "Paper, Continuation or Periodic object")
    cls = PROTOCOL_TYPES[check_choice("protocol", protocol, PROTOCOLS)]
    names = {f.name for f in dataclasses.fields(cls)}
    return cls(**{k: v for k, v in keywords.items() if k in names})


def check_rest_start(protocol: str | Protocol, where: str) -> None:
    """Raise :class:`jaxdea.SweepError` when ``protocol`` is a :class:`Periodic` object with
    ``start="neighbour"`` given to ``where``, a study that is not a power map (it has no
    neighbouring payloads to start from)."""
    if getattr(protocol, "start", "rest") != "rest":
        raise SweepError(f"start = {protocol.start!r} warm-starts the cells of a power map from "
                         f"their neighbouring payloads; {where} has none: use start='rest'")


def as_keywords(protocol: str | Protocol, **keywords) -> tuple[Any, tuple]:
    """``protocol``'s name and the values of ``keywords``, in the order given, to run it with.

    The studies' bridge between the two forms: a name (or anything that is not a protocol
    object, for the caller's own checks to reject) comes back with ``keywords`` unchanged,
    so a string protocol behaves exactly as before protocol objects existed; a protocol
    object comes back as its name with its settings in place of the keywords, which must
    be at their defaults (:func:`as_protocol`). Keywords that the object does not set keep
    their (default) values.

    **Arguments:**

    - `protocol`: a protocol object or name.
    - `keywords`: the caller's protocol keywords (see :func:`as_protocol`).
    """
    if not isinstance(protocol, tuple(PROTOCOL_TYPES.values())):
        return protocol, tuple(keywords.values())
    settings = _fields(as_protocol(protocol, **keywords))
    return protocol.name, tuple(settings.get(k, v) for k, v in keywords.items())
